"""Forgetting shown: recall of a first route against steps of novel input learned after it, with caps
that bind and with larger caps, in one run (issue 25 item 4; docs/benchmarks.md §12).

Run: `cortexloc bench forgetting [--novel 3000] [--every 300] [--quick]` (`make bench`).
Writes benchmarks/results/forgetting.json and forgetting.png.

Setup: a first route of 100 places (random SDRs of `active` of 2048 columns) learned twice (a reset
before each lap), then `--novel` steps of never-repeating random SDRs learned on another stream. Every
`--every` novel steps the first route is replayed with learning off on a fresh context
(`models.evaluation.forgetting.recall`): the fraction of its steps predicted, the winner cells kept,
recall@1 of the winner cells by Dice; and the fate of the segments that predicted it when it was
learned (`forgetting.fate`: intact, overwritten by overrun or decay, destroyed by LRU eviction).
Runs, each the same input and seed, differing only in the caps (maxSegmentsPerCell S x
maxSynapsesPerSegment K):

- `cortexloc-grid` (40 active columns): S=4 K=32 (binding within a few hundred steps), S=16 K=32
  (the preset's caps), S=32 K=128 (eight times the synapse room);
- `cortexloc-default` (308 active, the service preset) as shipped (S=16 K=32), fewer novel steps
  (its step costs ~10x more).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from benchmarks._common import RESULTS, quick_mode, write_json
from models import presets
from models.evaluation import forgetting
from models.evaluation.bench import random_sequence
from models.memory.temporal_memory import TemporalMemory

RUNS = [
    {"name": "grid S=4 K=32 (binds)", "preset": "cortexloc-grid", "active": 40, "S": 4, "K": 32},
    {"name": "grid S=16 K=32 (preset)", "preset": "cortexloc-grid", "active": 40, "S": 16, "K": 32},
    {"name": "grid S=32 K=128 (large)", "preset": "cortexloc-grid", "active": 40, "S": 32, "K": 128},
    {"name": "service S=16 K=32 (preset)", "preset": "cortexloc-default", "active": 308, "S": 16, "K": 32,
     "novel_fraction": 0.34},
]


def run(cfg: dict[str, Any], novel: int, every: int, seed: int = 0) -> dict[str, Any]:
    """One run of `cfg`: the curve of recall and of the route's segments against novel steps."""
    tm = TemporalMemory(presets.tm_options(cfg["preset"], {"maxSegmentsPerCell": cfg["S"],
                                                          "maxSynapsesPerSegment": cfg["K"]}))
    route = random_sequence(100, 2048, cfg["active"], seed + 7)
    stored = forgetting.learn(tm, route, laps=2)
    segments = forgetting.route_segments(tm, route)
    n = max(every, int(novel * cfg.get("novel_fraction", 1.0)) // every * every)
    curve = []

    def checkpoint(steps: int, ms: float | None) -> None:
        r = forgetting.recall(tm, route, stored)
        size = tm.size()
        point = {"steps_since_learned": steps, "predicted": round(r.predicted, 4),
                 "winners_kept": round(r.winners_kept, 4), "recall_at_1": r.recall_at_1,
                 "route_segments": forgetting.fate(tm, segments), "segments": size["segments"],
                 "segment_capacity": size["segment_capacity"], "evictions": size["evictions"],
                 "overrun_destroyed": size["overrun_destroyed"], "decay_destroyed": size["decay_destroyed"],
                 "ms_per_step": ms}
        curve.append(point)
        f = point["route_segments"]
        print(f"  {cfg['name']:>28} +{steps:>5}: predicted {r.predicted:.3f}, winners kept "
              f"{r.winners_kept:.3f}, R@1 {r.recall_at_1:.2f}; route segments intact {f['intact']}, "
              f"overwritten {f['overwritten']}, "
              f"destroyed {f['destroyed']} of {f['listed']}; evictions {size['evictions']}, overrun "
              f"{size['overrun_destroyed']}", flush=True)

    checkpoint(0, None)
    ctx = tm.new_context()
    seq = random_sequence(n, 2048, cfg["active"], seed + 8)
    for start in range(0, n, every):
        t0 = time.perf_counter()
        for x in seq[start:start + every]:
            tm.compute(x, learn=True, context=ctx)
        checkpoint(start + every, (time.perf_counter() - t0) / every * 1e3)
    return {**cfg, "caps_bytes": tm.size()["bytes"], "novel_steps": n, "curve": curve}


def plot(results: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for r in results:
        x = [p["steps_since_learned"] for p in r["curve"]]
        ax[0].plot(x, [p["predicted"] for p in r["curve"]], marker="o", label=r["name"])
        intact = [p["route_segments"]["intact"] / max(p["route_segments"]["listed"], 1) for p in r["curve"]]
        ax[1].plot(x, intact, marker="o", label=r["name"])
    ax[0].set(xlabel="novel steps learned since the route", ylabel="route steps predicted", ylim=(0, 1))
    ax[1].set(xlabel="novel steps learned since the route", ylabel="route segments intact", ylim=(0, 1))
    ax[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main(*, novel: int, every: int, quick: bool) -> None:
    if quick_mode(quick):
        novel, every = 300, 100
    t0 = time.perf_counter()
    results = [run(cfg, novel, every) for cfg in RUNS]
    plot(results, RESULTS / "forgetting.png")
    path = write_json("forgetting.json", {"config": {"novel": novel, "every": every, "quick": quick},
                                          "runs": results,
                                          "seconds": round(time.perf_counter() - t0, 1)})
    print(f"wrote {path} and {RESULTS / 'forgetting.png'} in {time.perf_counter() - t0:.0f} s")

