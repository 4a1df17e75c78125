"""Retrieval benchmark: median rank() latency of the inverted index as a map grows (`make bench`).

Random descriptors of 40 winner cells out of 8,192 (the default 2048x4 TM), top-5, 100 queries.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from storage.index import InvertedIndex


def main() -> None:
    rng = np.random.default_rng(0)
    n_cells, w = 8192, 40
    results = []
    for n in (1_000, 100_000):
        cells = [np.sort(rng.choice(n_cells, w, replace=False)) for _ in range(n)]
        idx = InvertedIndex(n_cells, 1_000_000)
        t0 = time.perf_counter()
        idx.rebuild(SimpleNamespace(seq=i + 1, winner_cells=cells[i], stream="s") for i in range(n))
        rebuild_s = time.perf_counter() - t0
        times = []
        for _ in range(100):
            q = np.sort(rng.choice(n_cells, w, replace=False))
            t = time.perf_counter()
            idx.rank(q, 5)
            times.append(time.perf_counter() - t)
        r = {"descriptors": n, "rank_ms_median": float(np.median(times) * 1e3),
             "rebuild_s": rebuild_s, "index_bytes": idx.nbytes()}
        results.append(r)
        print(f"index with {n} descriptors: rank median {r['rank_ms_median']:.3f} ms, rebuild "
              f"{rebuild_s:.2f} s, {idx.nbytes()} bytes", flush=True)
    out = Path(__file__).parent / "results" / "index.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
