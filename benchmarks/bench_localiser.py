"""The online localiser's step as the map grows: per-frame cost and state size (`make bench`).

Run: `cortexloc bench localiser [--sizes 1000 --sizes 100000 --sizes 1000000] [--frames 400] [--quick]`.

Setup (docs/design/science.md §11.2): one traverse of N stored rows (`SequenceGraph.chain`); a stream
drives along it at one row per frame; per frame the candidates are what an index's top-100 gives: the
true row (similarity 0.6) and 99 random rows (uniform 0-0.5). Reported per size: the median and p90 of
`SequenceLocaliser.step` (candidates already ranked: the similarity pass is the index's and is measured
by bench_index.py), the state's bytes, R@1 after the warm-up (a correctness check at sizes the unit
tests never reach), and the ratio of each median to the smallest size's.
"""

from __future__ import annotations

import time

import numpy as np

from benchmarks._common import RESULTS, quick_mode, write_json
from models.localisation import SequenceGraph, SequenceLocaliser


def bench_size(n: int, frames: int, seed: int = 0) -> dict[str, float]:
    rng = np.random.default_rng(seed)
    graph = SequenceGraph.chain(n)
    loc = SequenceLocaliser()
    state = loc.new_state()
    k = loc.options.top_k
    start = int(rng.integers(0, max(n - frames, 1)))
    times, right = [], 0
    for t in range(frames):
        truth = min(start + t, n - 1)
        seqs = np.concatenate([[truth], rng.integers(0, n, k - 1)])
        scores = np.concatenate([[0.6], rng.uniform(0, 0.5, k - 1)])
        t0 = time.perf_counter()
        place = loc.step(state, graph, seqs, scores)
        times.append(time.perf_counter() - t0)
        right += place is not None and place.seq == truth
    us = np.array(times) * 1e6
    return {"n": n, "median_us": float(np.median(us)), "p90_us": float(np.percentile(us, 90)),
            "state_bytes": sum(v.nbytes for v in state.to_arrays().values()),
            "recall_at_1": right / (frames - loc.options.warmup + 1)}


def main(*, sizes: list[int], frames: int, quick: bool) -> None:
    sizes, frames = ([1_000, 10_000], 100) if quick_mode(quick) else (sizes, frames)
    rows = [bench_size(n, frames) for n in sizes]
    for r in rows:
        r["median_ratio"] = r["median_us"] / rows[0]["median_us"]
        print(f"N {r['n']:>9,}: step median {r['median_us']:.0f} us (x{r['median_ratio']:.2f}), p90 "
              f"{r['p90_us']:.0f} us, state {r['state_bytes']} B, R@1 {r['recall_at_1']:.3f}", flush=True)
    print(write_json("localiser.json", {"frames": frames, "sizes": rows}, None if not quick_mode(quick)
                     else RESULTS / "localiser-quick.json"))

