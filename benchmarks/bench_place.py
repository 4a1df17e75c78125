"""The service's per-frame `place` as the map grows: the index pass plus the localisation step (`make bench`).

Run: `cortexloc bench place [--sizes 1000 --sizes 100000 --sizes 1000000] [--frames 300] [--quick]`.

Setup: N stored rows of synthetic winner cells (40 of 8,192, as bench_index.py), stored as one traverse
(seqs 1..N, each row's predecessor the one before, the links `models.localisation.places.PlaceMap`
rebuilds from the store). A stream drives `--frames` consecutive stored rows, each frame a noisy copy
(`--keep` of 40 cells kept). Per frame, what `MapRuntime.apply` runs for the answer
(docs/design/science.md §11.2): one `InvertedIndex.rank` pass for the frame's cells (top
`candidates_wanted`) and `PlaceMap.step` on its candidates. Reported per size: medians and p90 of the
pass, the step and both, the ratio of the medians to the smallest size's, the stream state's bytes, the
index's bytes per stored row (`InvertedIndex.nbytes`, capacity included) and R@1 after the warm-up.
"""

from __future__ import annotations

import time
from types import SimpleNamespace
from typing import Any

import numpy as np

from benchmarks._common import RESULTS, quick_mode, write_json
from benchmarks.bench_index import build_index, noisy_query, random_sets
from models.localisation.places import PlaceMap


def bench_size(n: int, frames: int, keep: int = 30, seed: int = 0) -> dict[str, Any]:
    rng = np.random.Generator(np.random.PCG64(seed))
    sets = random_sets(rng, n)
    idx, _ = build_index(sets)
    loc = PlaceMap()
    loc.rebuild(SimpleNamespace(seq=i + 1, context_prev_seq=i or None, input_sdr=np.zeros(0, np.int64),
                                stream="bench")
                for i in range(n))
    state = loc.new_state()
    wanted = loc.candidates_wanted(0)
    start = int(rng.integers(0, max(n - frames, 1)))
    route = [start + t for t in range(min(frames, n))]
    queries = [noisy_query(rng, sets[r], keep) for r in route]
    t_rank, t_step, right, answered = [], [], 0, 0
    clock = time.perf_counter
    for r, q in zip(route, queries, strict=True):
        t0 = clock()
        ranked = idx.rank(q, wanted)
        t1 = clock()
        place = loc.step(state, ranked, None)  # a localising stream: no own trail
        t_step.append(clock() - t1)
        t_rank.append(t1 - t0)
        if place is not None:
            answered += 1
            right += place.seq == r + 1
    rank, step = np.array(t_rank) * 1e3, np.array(t_step) * 1e3
    both = rank + step
    return {"rows": n, "frames": len(route), "candidates": wanted,
            "rank_ms_median": float(np.median(rank)), "rank_ms_p90": float(np.percentile(rank, 90)),
            "step_ms_median": float(np.median(step)), "step_ms_p90": float(np.percentile(step, 90)),
            "total_ms_median": float(np.median(both)), "total_ms_p90": float(np.percentile(both, 90)),
            "state_bytes": int(sum(v.nbytes for v in state.to_arrays().values())),
            "graph_bytes": int(loc.graph.prev.nbytes + loc.graph.next.nbytes + loc.graph.trail.nbytes),
            "index_bytes_per_row": idx.nbytes() / n,
            "recall_at_1": right / max(answered, 1)}


def main(*, sizes: list[int] | None, frames: int | None, keep: int, quick: bool) -> None:
    quick = quick_mode(quick)
    sizes = sizes or ([1_000, 10_000] if quick else [1_000, 100_000, 1_000_000])
    frames = frames or (40 if quick else 300)
    results = []
    for n in sizes:
        r = bench_size(n, frames, keep)
        r["ratio_to_smallest"] = r["total_ms_median"] / (results[0] if results else r)["total_ms_median"]
        results.append(r)
        print(f"{n:>9} rows: rank {r['rank_ms_median']:.3f} ms (p90 {r['rank_ms_p90']:.3f}), step "
              f"{r['step_ms_median']:.3f} ms (p90 {r['step_ms_p90']:.3f}), total "
              f"{r['total_ms_median']:.3f} ms ({r['ratio_to_smallest']:.2f}x), state {r['state_bytes']} B, "
              f"index {r['index_bytes_per_row']:.0f} B/row, "
              f"R@1 {r['recall_at_1']:.3f}",
              flush=True)
    write_json("place.json", {"config": {"frames": frames, "keep": keep, "quick": quick},
                              "results": results}, RESULTS / "place.json")

