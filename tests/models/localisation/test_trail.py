"""A stream's own trail (docs/design/science.md §11.6): which of its own rows it has left, measured on
its frame codes, never by counting frames."""

from __future__ import annotations

import numpy as np

from models.evaluation import online
from models.localisation import CodeStats, SequenceGraph, SequenceLocaliser
from models.localisation.trail import UNKNOWN
from models.sdr import dice_matrix

W, N = 2048, 300
RNG = np.random.default_rng(7)


def place() -> np.ndarray:
    return np.sort(RNG.choice(W, N, replace=False))


def noisy(code: np.ndarray, flip: float = 0.05) -> np.ndarray:
    """The same place seen again: `flip` of its bits moved elsewhere."""
    keep = RNG.random(code.size) >= flip
    extra = RNG.choice(np.setdiff1d(np.arange(W), code), int((~keep).sum()), replace=False)
    return np.sort(np.concatenate([code[keep], extra]))


def walk(codes: list[np.ndarray], loc: SequenceLocaliser | None = None) -> list:
    """One learning stream over `codes`: the own trail (first, last) after each frame."""
    loc = loc or SequenceLocaliser()
    graph, stats, state, out = SequenceGraph(), CodeStats(W), SequenceLocaliser().new_state(), []
    for i, c in enumerate(codes):
        own = loc.own_trail(state, graph, i - 1 if i else None, c, codes.__getitem__, stats)
        out.append(None if own is None else (state.here, own.first, own.last))
        graph.append(i, i - 1 if i else -1)
        stats.add(c)
    return out


def test_standing_still_keeps_every_row_of_the_stop_however_long():
    before = [place() for _ in range(20)]
    stop = [noisy(before[-1]) for _ in range(300)]  # far more frames than any window
    trail = walk(before + stop)
    assert all(t[0] == 19 for t in trail[21:])  # `here` stays at the first row of the stop
    # A frame unlike the stop leaves it all at once.
    after = walk(before + stop + [place()])
    assert after[-1][0] == len(before) + len(stop)  # past the last row: here = last + 1


def test_every_frame_unlike_the_last_leaves_it_and_the_margin_is_the_rival_window():
    codes = [place() for _ in range(40)]
    trail = walk(codes)
    exclusion = int(SequenceLocaliser().conf["exclusion"])
    for i, (here, first, last) in enumerate(trail[1:], start=1):
        assert here == last + 1 == i and first == max(0, last - exclusion)


def test_a_state_without_the_rule_starts_from_the_trail_and_a_new_trail_from_its_last_row():
    loc, graph, stats = SequenceLocaliser(), SequenceGraph(), CodeStats(W)
    codes = [place() for _ in range(5)] + [noisy(np.arange(N)) for _ in range(5)]
    for i, c in enumerate(codes):
        graph.append(i, i - 1 if i else -1)
        stats.add(c)
    state = loc.new_state()
    assert state.here == UNKNOWN
    frame = noisy(codes[-1])
    loc.own_trail(state, graph, 9, frame, codes.__getitem__, stats)
    assert state.here == 5  # walked from the trail's start to the first row the frame is like
    graph.append(10, -1)  # a new sequence: the old trail is no longer the stream's own
    own = loc.own_trail(state, graph, 10, frame, [*codes, frame].__getitem__, stats)
    assert state.here == 10 and own.holds(graph, np.arange(11)).tolist() == [False] * 10 + [True]


def test_background_likeness_sets_the_level_a_weak_backbone_shares_much():
    common = np.arange(200)  # every code shares 200 of its 300 bits: Dice 2/3 between unrelated places
    codes = [np.union1d(common, RNG.choice(np.arange(200, W), 100, replace=False)) for _ in range(30)]
    stats = CodeStats(W)
    for c in codes:
        stats.add(c)
    assert 0.6 < stats.background(codes[0]) < 0.75
    trail = walk(codes)
    assert all(t[0] == t[2] + 1 for t in trail[1:])  # unrelated places are left at once despite the overlap


def test_a_loop_closes_on_ones_own_trail_and_a_stop_does_not():
    lap = [place() for _ in range(40)]
    codes = lap + [noisy(c) for c in lap]
    found = online.loop_closure(dice_matrix(codes), codes)
    second = np.arange(40, 80)
    assert np.mean(found.best[second[10:]] == second[10:] - 40) > 0.9  # lap 2 names lap 1
    assert found.confidence[second[-10:]].min() > 0.9
    stop = [place() for _ in range(20)] + [noisy(lap[0]) for _ in range(60)]
    still = online.loop_closure(dice_matrix(stop), stop)
    assert still.confidence.max() < 0.5
