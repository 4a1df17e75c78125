"""A stream's condition (docs/design/science.md §11.10): how often each code bit was on in its recent
frames, and the weight of a query cell it gives."""

from __future__ import annotations

import numpy as np
import pytest

from models.localisation.condition import Condition


def test_rates_are_the_mean_of_the_first_frames_then_an_exponential_average() -> None:
    c = Condition(6, frames=2)
    c.add(np.array([0, 1]))
    assert c.rates.tolist() == [1, 1, 0, 0, 0, 0]
    c.add(np.array([1, 2]))  # the mean of two frames
    assert c.rates.tolist() == [0.5, 1, 0.5, 0, 0, 0]
    c.add(np.array([3]))  # from the third on, weight 1 / frames for the newest
    assert c.rates.tolist() == [0.25, 0.5, 0.25, 0.5, 0, 0]
    assert c.seen == 3


def test_a_bit_every_frame_shares_weighs_nothing_and_an_unseen_bit_weighs_one() -> None:
    c = Condition(8, frames=10)
    for _ in range(30):
        c.add(np.array([0, 1, 5]))  # the condition: bits 0, 1 always on
        c.add(np.array([0, 1, 6]))
    w = c.weights(np.array([0, 1, 5, 7]), 1, discount=2.0)
    assert w[:2].tolist() == [0.0, 0.0]  # on in every recent frame: says nothing of where
    assert 0.0 <= w[2] < 0.2  # on in half of them, near 0 at discount 2
    assert w[3] == 1.0  # never on lately
    # Cells map to their column: cells 0-3 are column 0, 4-7 column 1 with 4 cells per column.
    assert c.weights(np.array([3, 28, 29]), 4, discount=2.0).tolist() == [0.0, 1.0, 1.0]


def test_no_weights_before_a_frame_without_discount_or_when_every_cell_would_weigh_nothing() -> None:
    c = Condition(4, frames=5)
    assert c.weights(np.array([1]), 1, 2.0) is None
    c.add(np.array([1, 2]))
    assert c.weights(np.array([1, 3]), 1, 0.0) is None
    assert c.weights(np.array([1, 2]), 1, 2.0) is None  # all 0: the index ranks by plain Dice
    assert c.weights(np.array([1, 3]), 1, 2.0).tolist() == [0.0, 1.0]


def test_state_round_trip_and_checks() -> None:
    c = Condition(5, frames=3)
    for code in ([0, 1], [1, 4], [2]):
        c.add(np.array(code))
    back = Condition.from_state(3, c.state())
    assert back.seen == 3 and np.array_equal(back.rates, c.rates)
    back.add(np.array([0]))
    c.add(np.array([0]))
    assert np.array_equal(back.rates, c.rates)
    for bad in (np.array([1.0, 2.0]), np.array([1.0, -0.5]), np.array([np.nan, 0.0]), np.zeros((2, 2))):
        with pytest.raises(ValueError):
            Condition.from_state(3, bad)
    with pytest.raises(ValueError):
        Condition(3, frames=0)
