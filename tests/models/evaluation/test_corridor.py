"""The rendered corridor of issue 35's indoor check (models/evaluation/corridor.py): deterministic, the
lens matters, and a small step changes a frame less than another place does."""

from __future__ import annotations

import numpy as np

from models.evaluation.corridor import Corridor, Lens, render


def _diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(np.float64) - b).mean())


def test_a_corridor_frame_is_a_function_of_the_corridor_the_pose_and_the_lens() -> None:
    c = Corridor(20.0, seed=3)
    a = render(c, 5.0, Lens())
    assert a.shape == (120, 160, 3) and a.dtype == np.uint8
    assert np.array_equal(a, render(Corridor(20.0, seed=3), 5.0, Lens()))
    assert _diff(a, render(Corridor(20.0, seed=4), 5.0, Lens())) > 0  # another layout
    other_lens = render(c, 5.0, Lens(80.0, 0.25))
    assert _diff(a, other_lens) > 3 * _diff(a, render(c, 5.0, Lens(), noise=0.0))


def test_a_slow_robot_sees_its_next_frame_closer_than_a_place_metres_on() -> None:
    c = Corridor(20.0, seed=3)
    here, step, far = (render(c, s, Lens(), noise=0.0) for s in (6.0, 6.12, 12.0))
    assert 0 < _diff(here, step) < _diff(here, far)
