"""Temporal Memory benchmark (issue: memory core). Run: `make bench` or `cortexloc bench tm-suite`.

Two configurations, as the issue asks: 2048 columns x 4 cells with 40 active columns, and 2048 x 32
with 512 active columns; 5,000 learning steps each on a never-repeating random SDR sequence (the
stress case: every column bursts, segments are created every step and the caps bind). Reports the
median ms/step and the RSS growth after allocation; writes JSON next to this file under results/.
"""

from __future__ import annotations

import json
from pathlib import Path

from models.evaluation.bench import bench_tm

CONFIGS = [
    {"columns": 2048, "cells": 4, "active": 40},
    {"columns": 2048, "cells": 32, "active": 512},
    # NuPIC's thresholds (what htm.core runs by default), with caps so that memory is bounded.
    {"columns": 2048, "cells": 4, "active": 40, "preset": "numenta-defaults",
     "overrides": {"maxSegmentsPerCell": 32, "maxSynapsesPerSegment": 32}},
]


def main(*, steps: int, preset: str, out: Path | None) -> None:
    if out is None:
        out = Path(__file__).parent / "results" / "tm.json"
    results = []
    for cfg in CONFIGS:
        r = bench_tm(steps=steps, **{"preset": preset, **cfg})
        results.append(r)
        print(f"TM {cfg['columns']}x{cfg['cells']} active {cfg['active']} ({r['config']['preset']}): median "
              f"{r['ms_per_step_median']:.3f} ms/step (p90 {r['ms_per_step_p90']:.3f}), RSS growth "
              f"{r['rss_growth_mb']:.1f} MB, segments {r['segments']}, synapses {r['synapses']}, "
              f"preallocated {r['bytes'] / 2**20:.1f} MiB", flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2))

