"""Forgetting in the Temporal Memory's bounded memory: what a learned route keeps while other input is
learned after it (docs/design/science.md §3.5; issue 25 item 4; benchmarks/bench_forgetting.py).

A route is a sequence of random SDRs (columns). After it is learned, the segments that predict it are
listed with their connected presynaptic cells (`route_segments`). While novel input is learned, the
route is replayed with learning off on a fresh context (`recall`): the fraction of its steps whose
columns were predicted (sequence recall: the first step of a replay is never predicted and is left
out), the winner cells reproduced against those stored when it was learned, and recall@1 of those
winner cells by Dice among the stored ones. `fate` says what became of each listed segment: still
able to predict (at least activationThreshold of its original connected synapses left), overwritten
(live, but its synapses were replaced by overrun or decayed below that), or destroyed (evicted by the
segment cap's LRU rule or emptied).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.memory.temporal_memory import TemporalMemory

__all__ = ["Recall", "fate", "learn", "recall", "route_segments"]


@dataclass(frozen=True)
class Recall:
    """What a replay of a learned route found (learning off, fresh context).

    Attributes:
        predicted: mean over steps 1.. of predicted columns / active columns.
        winners_kept: mean Jaccard of each step's winner cells with those stored when it was learned.
        recall_at_1: fraction of steps whose winner cells are closest by Dice to the stored ones of
            the same step (ties count against).
    """

    predicted: float
    winners_kept: float
    recall_at_1: float


def learn(tm: TemporalMemory, route: list[np.ndarray], laps: int) -> list[np.ndarray]:
    """Learn `route` `laps` times, a reset before each lap; returns the last lap's winner cells (the
    stored descriptors, (w,) int64 each)."""
    stored: list[np.ndarray] = []
    for _ in range(laps):
        ctx = tm.new_context()
        stored = [tm.compute(x, learn=True, context=ctx) for x in route]
    return stored


def route_segments(tm: TemporalMemory, route: list[np.ndarray]) -> dict[int, np.ndarray]:
    """The segments that predict `route`'s steps on a replay (learning off): segment id -> (n,) sorted
    presynaptic cells of its connected synapses when listed."""
    ctx = tm.new_context()
    S = int(tm.options.maxSegmentsPerCell)
    cpc = tm.cells_per_column
    out: dict[int, np.ndarray] = {}
    for t, x in enumerate(route):
        tm.compute(x, learn=False, context=ctx)
        if t + 1 < len(route):
            nxt = route[t + 1]
            for g in ctx.active_segs:
                if np.isin((g // S) // cpc, nxt):
                    out[int(g)] = tm.connected_presyn(int(g))
    return out


def fate(tm: TemporalMemory, segments: dict[int, np.ndarray]) -> dict[str, int]:
    """What became of `segments` (from `route_segments`): counts of intact, overwritten, destroyed."""
    thr = int(tm.options.activationThreshold)
    out = {"listed": len(segments), "intact": 0, "overwritten": 0, "destroyed": 0}
    for g, cells in segments.items():
        if tm.nsyn[g] == 0:
            out["destroyed"] += 1
        elif np.intersect1d(tm.connected_presyn(g), cells, assume_unique=True).size >= thr:
            out["intact"] += 1
        else:
            out["overwritten"] += 1
    return out


def recall(tm: TemporalMemory, route: list[np.ndarray], stored: list[np.ndarray]) -> Recall:
    """Replay `route` with learning off on a fresh context against its `stored` winner cells."""
    ctx = tm.new_context()
    predicted, kept, hits = [], [], 0
    for t, x in enumerate(route):
        w = tm.compute(x, learn=False, context=ctx)
        if t:
            predicted.append(ctx.stats.predicted_columns / max(ctx.stats.active_columns, 1))
        kept.append(np.intersect1d(w, stored[t]).size / max(np.union1d(w, stored[t]).size, 1))
        dice = np.array([2 * np.intersect1d(w, s).size / (w.size + s.size) for s in stored])
        hits += int(np.argmax(dice) == t and np.count_nonzero(dice == dice[t]) == 1)
    return Recall(float(np.mean(predicted)) if predicted else 0.0, float(np.mean(kept)), hits / len(route))
