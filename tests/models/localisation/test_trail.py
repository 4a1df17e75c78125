"""A stream's own trail (docs/design/science.md §11.6): which of its own rows it has left, measured on
its frame codes, never by counting frames."""

from __future__ import annotations

import numpy as np
import pytest

from models.evaluation import online
from models.localisation import CodeStats, LocaliserOptions, SequenceGraph, SequenceLocaliser
from models.localisation.trail import UNKNOWN, OwnTrail, code_dice
from models.sdr import dice_matrix

W, N = 2048, 300
RNG = np.random.default_rng(7)


@pytest.fixture(autouse=True)
def _seeded() -> None:
    """Each test draws its codes from a fresh RNG: under pytest-xdist a test's neighbours in one worker
    vary, and the codes they drew changed this test's (one failed that way, in a run of this round)."""
    global RNG
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
    exclusion = SequenceLocaliser().options.exclusion
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


def test_the_background_of_an_empty_code_is_zero_not_nan():
    # as `code_dice` of two empty codes: nothing stored, or only empty codes stored (a NaN level would
    # make every comparison with it false)
    stats, empty = CodeStats(W), np.zeros(0, np.int64)
    assert stats.background(empty) == 0.0
    stats.add(empty)
    assert stats.background(empty) == 0.0 == code_dice(empty, empty)
    assert stats.level(empty, 0.5) == 0.5


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


def drifting(n: int, seed: int, pool: int = 100, rest: int = 200, drift: int = 2) -> list[np.ndarray]:
    """A route whose frames stay faintly alike along the way and never come back: each frame holds
    `pool` bits of a set that swaps `drift` bits per frame, and `rest` bits drawn afresh. Consecutive
    frames are unlike (Dice ~0.37, below the departure level), a frame 12 back only a little less so."""
    rng = np.random.default_rng(seed)
    cur, out = rng.choice(W, pool, replace=False), []
    for _ in range(n):
        cur = np.concatenate([np.delete(cur, rng.choice(cur.size, drift, replace=False)),
                              rng.choice(np.setdiff1d(np.arange(W), cur), drift, replace=False)])
        out.append(np.sort(np.concatenate([cur, rng.choice(np.setdiff1d(np.arange(W), cur), rest,
                                                             replace=False)])))
    return out


@pytest.mark.parametrize("seed", range(12))
def test_a_route_whose_frames_stay_faintly_alike_is_never_a_revisit_of_itself(seed: int) -> None:
    # Every row is left at once (no frame is like the one before), so rows just behind the rival window
    # are candidates, and the nearest stand a little above the rest on every frame: a path a dozen rows
    # behind, driven in step with the stream, would gather confidence from likeness alone (the echo of
    # docs/results.md §10.9). It ends where it reaches rows laid since it began.
    codes = drifting(120, seed)
    found = online.loop_closure(dice_matrix(codes), codes)
    assert found.confidence.max() < 0.9  # each seed reached 0.92-0.96 before the rule


def test_a_loop_driven_again_goes_on_across_the_rows_the_last_lap_laid() -> None:
    # Three laps of a short loop, each frame a noisy view of the lap's: lap 3 walks the rows lap 2 laid
    # while the path that follows them was already being followed; the frame shows them by looks.
    lap = [place() for _ in range(25)]
    codes = lap + [noisy(c) for c in lap] + [noisy(c) for c in lap]
    found = online.loop_closure(dice_matrix(codes), codes)
    third = np.arange(50, 75)
    assert np.all(found.best[third] % 25 == third % 25)
    # Sure across the lap's start. (Later in lap 3 the confidence falls: without places, which the
    # service's learning stream joins and `loop_closure` does not, lap 1's rows are a rival of lap 2's.)
    assert found.confidence[third[:5]].min() > 0.9


def test_rows_laid_while_the_path_was_followed_end_it_unless_the_frame_came_back_to_them() -> None:
    # A stream's own trail of 60 rows; a path began when 20 were stored. The frame looks like where the
    # stream just was (its last row), so rows 20 on, laid after the path began, are an echo.
    loc, graph = SequenceLocaliser(), SequenceGraph.chain(60)
    codes = [place() for _ in range(60)]
    stats = CodeStats(W)
    for c in codes:
        stats.add(c)
    state = loc.new_state()
    state.here = 60  # every row left
    began = np.full(3, 20)
    frame = noisy(codes[59], 0.3)
    assert code_dice(frame, codes[59]) > 0.6  # like where the stream just was
    own = loc.own_trail(state, graph, 59, frame, codes.__getitem__, stats)
    assert own.laid_behind(graph, np.array([19, 20, 25]), began).tolist() == [False, True, True]
    # A frame more like row 25 (far behind the rows it just left) than like where it just was came back
    # to it: the path goes on there, not at row 20.
    own = loc.own_trail(state, graph, 59, noisy(codes[25]), codes.__getitem__, stats)
    assert own.laid_behind(graph, np.array([20, 25]), began[:2]).tolist() == [True, False]
    # Rows joined to a place known before the path began are no exception: an echo that once read as a
    # revisit (and so joined the rows it named to its place) must not follow the trail for ever.
    for r in range(20, 60):
        graph.join(r, r - 20)
    own = loc.own_trail(state, graph, 59, noisy(codes[59], 0.3), codes.__getitem__, stats)
    assert own.laid_behind(graph, np.array([19, 20, 25]), began).tolist() == [False, True, True]


@pytest.mark.parametrize("began, ends", [(20, True), (21, False)])
def test_a_path_ends_on_the_first_row_stored_after_it_began(began: int, ends: bool) -> None:
    # One path on the stream's own trail at row 19, walking on; the frame looks like where the stream
    # just was. Row 20 was stored when the map held 20 rows: after a path that began then, not after one
    # that began when it held 21 (rows are stored in seq order).
    loc, graph = SequenceLocaliser(LocaliserOptions.of({"move_costs": (3.0, 0.0)})), SequenceGraph.chain(40)
    codes = [place() for _ in range(40)]
    stats = CodeStats(W)
    for c in codes:
        stats.add(c)
    state = loc.new_state()
    state.here = 40
    state.rows[0], state.scores[0], state.ages[0], state.born[0], state.null = 19, 50.0, 10, began, 0.0
    own = loc.own_trail(state, graph, 39, noisy(codes[39], 0.3), codes.__getitem__, stats)
    loc.step(state, graph, np.array([5]), np.array([0.5]), own)
    moved = (state.rows == 20) & (state.dirs > 0)
    assert moved.any() != ends
    assert (state.rows == 19).any()  # staying put (move 0) is no step onto a new row


def test_without_the_frames_code_every_row_laid_since_a_path_began_ends_it():
    # `OwnTrail.shows` with no code: no row is more like the frame than where the stream just was, so a
    # path on rows laid since it began is an echo (§11.6), and a path back along the trail is no revisit
    # without odometry's word (§11.13).
    graph = SequenceGraph.chain(40)
    own = OwnTrail(first=30, here=40, last=39, trail=0)
    rows = np.array([35, 36, 37])
    assert own.shows(graph, rows).tolist() == [False] * 3
    assert own.laid_behind(graph, rows, np.zeros(3, np.int64)).tolist() == [True] * 3
    assert own.laid_behind(graph, rows, np.full(3, 38)).tolist() == [False] * 3  # laid before it began


def test_the_chain_a_robots_other_camera_lays_is_its_trail_for_the_mirror_rule_not_the_echo_rule():
    # Two cameras naming one trail each lay a chain (§11.6): `lays` counts the other camera's chain as
    # the robot's (the mirror rule reads it, §11.13); the echo rule ends paths on the stream's own chain
    # only (ending them on the other camera's too cost the stress suite's `cameras` case a false revisit).
    graph = SequenceGraph.chain(40)  # chain 0: the other camera's
    rows = np.array([35, 36, 37])
    alone = OwnTrail(first=1, here=2, last=1, trail=7)  # its own chain is another
    robot = alone._replace(others=frozenset({0}))
    assert robot.lays(graph, rows).all() and not alone.lays(graph, rows).any()
    assert robot.laid_behind(graph, rows, np.zeros(3, np.int64)).tolist() == [False] * 3
    assert alone._replace(trail=0).laid_behind(graph, rows, np.zeros(3, np.int64)).tolist() == [True] * 3
