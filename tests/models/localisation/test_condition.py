"""A stream's condition (docs/design/science.md §11.10): how often each code bit was on in its recent
frames, and the weight of a query cell it gives."""

from __future__ import annotations

import numpy as np
import pytest

from models.localisation.condition import REPEAT, Condition


def test_rates_are_an_exponential_average_from_zero() -> None:
    # Few frames say little about a condition: the rates start at 0 and grow by 1 / frames per frame.
    c = Condition(6, frames=4)
    assert c.add(np.array([0, 1]), 2.0)
    assert c.rates.tolist() == [0.25, 0.25, 0, 0, 0, 0]
    assert c.add(np.array([1, 2]), 2.0)
    assert c.rates.tolist() == [0.1875, 0.4375, 0.25, 0, 0, 0]
    assert c.seen == 2 and c.last.tolist() == [1, 2]


def test_a_repeated_view_is_not_taken_in() -> None:
    """A stopped robot posts the same view again and again: the condition is what frames of different
    places share, so a repeat (Dice >= REPEAT with the last frame taken in, over the bits the condition
    leaves weight to) changes nothing."""
    c = Condition(40, frames=10)
    code = np.arange(20)
    assert c.add(code, 2.0)
    before = c.rates.copy()
    nearly = np.r_[np.arange(19), 39]  # 19 of 20 bits shared: Dice 0.95
    assert REPEAT <= 0.95
    assert not c.add(code, 2.0) and not c.add(nearly, 2.0)
    assert np.array_equal(c.rates, before) and c.seen == 1
    assert c.add(np.arange(10, 30), 2.0)  # half new: another view
    assert c.seen == 2


def test_frames_that_share_only_the_condition_are_no_repeats() -> None:
    """Winter frames of different places share the winter bits: by plain Dice they repeat one another,
    over the bits the condition leaves weight to they do not, so the condition still learns winter."""
    c = Condition(64, frames=4)
    winter = np.arange(16)  # on in every frame
    for place in range(8):
        c.add(np.r_[winter, 16 + place * 4 + np.arange(4)], 2.0)  # 16 winter bits + 4 of the place
    a, b = np.r_[winter, 50, 51, 52, 53], np.r_[winter, 56, 57, 58, 59]
    assert 2 * 16 / 40 == 0.8  # plain Dice of two places: high
    assert c.add(a, 2.0) and c.add(b, 2.0)
    assert c.repeats(b.copy(), 2.0)  # the same view again is still a repeat


def test_a_bit_every_frame_shares_weighs_nothing_and_an_unseen_bit_weighs_one() -> None:
    c = Condition(8, frames=10)
    for _ in range(60):
        c.add(np.array([0, 1, 5]), 0.0)  # the condition: bits 0, 1 always on
        c.add(np.array([0, 1, 6]), 0.0)
    w = c.weights(np.array([0, 1, 5, 7]), 1, discount=2.0)
    assert w[:2].tolist() == [0.0, 0.0]  # on in every recent frame: says nothing of where
    assert 0.0 <= w[2] < 0.2  # on in half of them, near 0 at discount 2
    assert w[3] == 1.0  # never on lately
    # Cells map to their column: cells 0-3 are column 0, 4-7 column 1 with 4 cells per column.
    assert c.weights(np.array([3, 28, 29]), 4, discount=2.0).tolist() == [0.0, 1.0, 1.0]


def test_no_weights_before_a_frame_without_discount_or_when_every_cell_would_weigh_nothing() -> None:
    c = Condition(4, frames=1)
    assert c.weights(np.array([1]), 1, 2.0) is None
    c.add(np.array([1, 2]), 2.0)
    assert c.weights(np.array([1, 3]), 1, 0.0) is None
    assert c.weights(np.array([1, 2]), 1, 2.0) is None  # all 0: the index ranks by plain Dice
    assert c.weights(np.array([1, 3]), 1, 2.0).tolist() == [0.0, 1.0]


def test_state_round_trip_and_checks() -> None:
    c = Condition(5, frames=3)
    for code in ([0, 1], [1, 4], [2]):
        c.add(np.array(code), 2.0)
    back = Condition.from_state(3, c.state())
    assert back.seen == 3 and np.array_equal(back.rates, c.rates) and back.last.tolist() == [2]
    for code in ([2], [0, 3]):  # the repeat rule reads the restored last code too
        assert back.add(np.array(code), 2.0) == c.add(np.array(code), 2.0)
    assert np.array_equal(back.rates, c.rates)
    for bad in (np.array([1.0]), np.array([1.0, 2.0, 0.5]), np.array([1.0, 2.0, 0.5, -0.5]),
                np.array([1.0, 1.0, 0.5, 7.0]), np.array([np.nan, 1.0, 0.0]), np.zeros((2, 2))):
        with pytest.raises(ValueError):
            Condition.from_state(3, bad)
    with pytest.raises(ValueError):
        Condition(3, frames=0)
