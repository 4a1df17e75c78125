"""The forgetting measurement (models/evaluation/forgetting.py, issue 25 item 4): recall of a learned route
and the fate of the segments that predicted it, as the bounded memory learns other input after it."""

from __future__ import annotations

import numpy as np

from models import presets
from models.evaluation import forgetting
from models.evaluation.bench import random_sequence
from models.memory.temporal_memory import TemporalMemory

Learned = tuple[TemporalMemory, list[np.ndarray], list[np.ndarray], dict[int, np.ndarray]]


def _learned(S: int, K: int) -> Learned:
    overrides = {"columnDimensions": 512, "maxSegmentsPerCell": S, "maxSynapsesPerSegment": K}
    tm = TemporalMemory(presets.tm_options("cortexloc-grid", overrides))
    route = random_sequence(30, 512, 20, 1)
    stored = forgetting.learn(tm, route, laps=2)
    return tm, route, stored, forgetting.route_segments(tm, route)


def test_a_route_just_learned_is_recalled_and_its_segments_are_intact() -> None:
    tm, route, stored, segments = _learned(16, 32)
    r = forgetting.recall(tm, route, stored)
    assert r.predicted > 0.9 and r.winners_kept > 0.9 and r.recall_at_1 == 1.0
    assert len(segments) >= len(route) - 1
    assert forgetting.fate(tm, segments) == {"listed": len(segments), "intact": len(segments),
                                             "overwritten": 0, "destroyed": 0}


def test_fate_tells_a_destroyed_segment_from_an_overwritten_one() -> None:
    tm, _, _, segments = _learned(16, 32)
    gone, weakened = list(segments)[:2]
    tm.nsyn[gone] = 0
    K = int(tm.params["maxSynapsesPerSegment"])
    tm.perm[weakened * K:(weakened + 1) * K] = 0.1  # below connected: it can no longer predict
    f = forgetting.fate(tm, segments)
    assert (f["destroyed"], f["overwritten"], f["intact"]) == (1, 1, len(segments) - 2)


def test_novel_input_makes_binding_caps_forget_the_route() -> None:
    tm, route, stored, segments = _learned(2, 24)
    before = forgetting.recall(tm, route, stored)
    ctx = tm.new_context()
    for x in random_sequence(600, 512, 20, 2):
        tm.compute(x, learn=True, context=ctx)
    after = forgetting.recall(tm, route, stored)
    f = forgetting.fate(tm, segments)
    assert after.predicted < before.predicted / 2
    assert f["intact"] < len(segments) / 2
    assert f["intact"] + f["overwritten"] + f["destroyed"] == len(segments)
