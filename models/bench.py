"""Benchmarks of the model stages, shared by `benchmarks/` and `cortexloc bench` (no timed asserts).

Timings on shared machines are noisy: report medians, and compare in ratios within one run.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from models import presets
from models.temporal_memory import TemporalMemory


def rss_mb() -> float:
    """Resident set size of this process in MiB (Linux /proc; 0.0 where unavailable)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return 0.0
    import os

    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def random_sequence(n: int, columns: int, active: int, seed: int = 0) -> list[np.ndarray]:
    """n random SDRs of exactly `active` ones out of `columns`, each (active,) int64 sorted."""
    rng = np.random.Generator(np.random.PCG64(seed))
    return [np.sort(rng.choice(columns, active, replace=False)) for _ in range(n)]


def bench_tm(columns: int = 2048, cells: int = 4, active: int = 40, steps: int = 5000,
             preset: str = "cortexloc-grid", period: int = 0, seed: int = 0,
             overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Time `steps` learning steps of a Temporal Memory on a random SDR sequence.

    Args:
        columns, cells: columnDimensions and cellsPerColumn (override the preset's).
        active: ones per input SDR.
        steps: learning steps timed.
        preset: TM preset supplying the other parameters (caps, thresholds).
        period: repeat a random sequence of this length (0: never repeat, every step is novel).
        overrides: further TM parameters (e.g. smaller caps for `numenta-defaults`).

    Returns:
        ms_per_step_median, ms_per_step_p90, rss_growth_mb (after allocation and compilation),
        segments, synapses, bytes, and the parameters used.
    """
    params = presets.tm_params(preset, {**(overrides or {}), "columnDimensions": columns,
                                        "cellsPerColumn": cells})
    # Compile the kernels on a tiny memory first, so compilation is neither timed nor counted in RSS.
    warm = TemporalMemory({**params, "columnDimensions": 64, "maxSegmentsPerCell": 2})
    for x in random_sequence(20, 64, min(active, 8), seed):
        warm.compute(x, learn=True)
        warm.compute(x, learn=False)
    seq = random_sequence(period or steps, columns, active, seed + 1)
    tm = TemporalMemory(params)
    rss0 = rss_mb()
    times = np.empty(steps)
    clock = time.perf_counter
    predicted = 0
    for i in range(steps):
        x = seq[i % len(seq)]
        t0 = clock()
        tm.compute(x, learn=True)
        times[i] = clock() - t0
        predicted += tm.context.stats.predicted_columns
    rss1 = rss_mb()
    size = tm.size()
    return {
        "ms_per_step_median": float(np.median(times) * 1e3),
        "ms_per_step_p90": float(np.percentile(times, 90) * 1e3),
        "rss_growth_mb": rss1 - rss0,
        "segments": size["segments"],
        "synapses": size["synapses"],
        "evictions": size["evictions"],
        "bytes": size["bytes"],
        "predicted_column_fraction": predicted / (steps * active),
        "config": {"columns": columns, "cells": cells, "active": active, "steps": steps,
                   "preset": preset, "period": period, "seed": seed, "overrides": overrides or {}},
    }
