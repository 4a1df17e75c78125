"""A stream makes a new row only after it has moved (issue 35 item 1, issue 36; docs/design/science.md
§11.6): a learned frame that is no move of its short-term memory (no pose change of `move_metres`, or
without poses the same view as its last move) is a visit of the stream's newest row, a rehearsal: the
memory learns it, the answer is the same, no row is made; replayed, it gives the same memory."""

from __future__ import annotations

import numpy as np

from models.localisation.motion import NO_MOTION, Motion
from models.pipeline import MapModel, Stream, observe, replay, revisit

TM = {"columnDimensions": 128, "cellsPerColumn": 4, "maxSegmentsPerCell": 4, "maxSynapsesPerSegment": 16,
      "activationThreshold": 3, "minThreshold": 2, "seed": 3}
K, S = 64, 0.1


def model(**localiser) -> MapModel:
    return MapModel.new(TM, localiser, max_observations=1000, s=S)


def run(m: MapModel, frames, motions=None, threshold: float | None = 0.9) -> tuple[list, dict]:
    """Learn `frames` as stream "a" (each with its motion): (steps, the stored rows' codes)."""
    st, codes, steps = Stream(), {}, []
    seq = 1
    for i, y in enumerate(frames):
        step = observe(m, st, y, learn=True, stream="a", top_k=3, seq=seq, code_of=codes.__getitem__,
                       threshold=threshold, motion=NO_MOTION if motions is None else motions[i])
        steps.append(step)
        if step.visit is None:
            codes[seq] = step.code
            seq += 1
    return steps, codes


def noisy(base: np.ndarray, n: int, sigma: float, seed: int) -> np.ndarray:
    return (base + sigma * np.random.default_rng(seed).normal(size=(n, K))).astype(np.float32)


def route(n: int = 20, seed: int = 9) -> np.ndarray:
    """A drive of `n` unlike views (a map with a few rows: a code's background likeness is settled)."""
    return np.random.default_rng(seed).normal(size=(n, K)).astype(np.float32)


def test_a_parked_robot_without_poses_makes_one_row_and_rehearses_it() -> None:
    """A drive of 20 frames, then 60 frames of one view with sensor noise: before, 60 rows of the stop
    (each in the stream's short-term memory); now the stop's first frame's row and 59 visits of it."""
    here = np.random.default_rng(1).normal(size=K)
    m = model()
    steps, _ = run(m, np.concatenate([route(), noisy(here, 60, 0.05, 2)]))
    assert all(s.visit is None for s in steps[:21])
    assert [s.visit for s in steps[21:]] == [21] * 59
    assert len(m.index) == 21 and m.links.held == 21 and m.links.visits == 59
    assert all(s.place is None or not s.place.is_revisit(0.9) for s in steps)  # no answer changed: no revisit


def test_a_slow_robot_without_poses_makes_a_row_per_view_not_per_frame() -> None:
    """Each of 12 views posted 3 times (the copies slightly noisy): a row per view, the copies rehearse
    it (before: a row per frame)."""
    views = np.random.default_rng(3).normal(size=(12, K))
    frames = np.concatenate([noisy(v, 3, 0.05, 10 + i) for i, v in enumerate(views)])
    m = model()
    steps, _ = run(m, frames)
    made = [i for i, s in enumerate(steps) if s.visit is None]
    assert made == list(range(0, 36, 3))
    for i, s in enumerate(steps):
        if s.visit is not None:  # the copy of view i // 3 visits that view's row, its stream's newest
            assert s.visit == made.index(3 * (i // 3)) + 1 and s.prev_seq == s.visit


def test_with_poses_a_row_only_after_move_metres_whatever_the_view() -> None:
    """A robot creeping at 0.25 m a frame through changing views: a row every metre (`move_metres` 1),
    the frames between rehearse the newest row; a frame 1 m on is a row even if it looks the same."""
    views = np.random.default_rng(4).normal(size=(20, K)).astype(np.float32)
    motions = [Motion((0.25 * i, 0.0), float(i)) for i in range(20)]
    m = model()
    steps, _ = run(m, views, motions)
    assert [i for i, s in enumerate(steps) if s.visit is None] == [0, 4, 8, 12, 16]
    same = np.repeat(views[:1], 3, axis=0)
    m = model()
    steps, _ = run(m, same, [Motion((2.0 * i, 0.0), float(i)) for i in range(3)])
    assert [s.visit for s in steps] == [None, None, None]  # every frame 2 m on: a move


def test_a_rehearsal_replays_to_the_same_memory_and_without_a_memory_every_frame_is_a_row() -> None:
    here = np.random.default_rng(5).normal(size=K)
    frames = np.concatenate([route(), noisy(here, 10, 0.05, 6), route(5, seed=7)])
    m = model()
    steps, _ = run(m, frames)
    assert sum(s.visit is not None for s in steps) == 9
    again, st = m.fresh(model().tm), Stream()
    seq = 0
    for s in steps:  # rows and visits again, in the order they were learned
        if s.visit is None:
            seq += 1
            winners = replay(again, st, s.code, seq=seq, prev_seq=s.prev_seq)
        else:
            winners = revisit(again, st, s.code, row=s.visit, prev_seq=s.prev_seq)
        assert np.array_equal(winners, s.winners)
    off = model(short_term=0)
    steps, _ = run(off, frames)
    assert all(s.visit is None for s in steps) and len(off.index) == 35
