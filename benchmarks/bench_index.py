"""Retrieval as a map grows: the inverted index against a brute-force popcount, side by side (`make bench`).

Run: `cortexloc bench index [--sizes 1000 --sizes 100000 --sizes 1000000] [--queries 50] [--quick]`.

Setup: stored descriptors are synthetic winner-cell sets of constant weight (40 cells out of 8,192, the
default 2048x4 TM with 40 active columns), uniform at random. Queries are noisy copies of stored
descriptors (`--keep` of their 40 cells kept, the rest replaced), so every top-10 holds a real match
and a long tail of chance overlaps, as in a map. For each size:

- the index (`models.localisation.index.InvertedIndex.rank`, top-10): median and p90 latency;
- the brute-force baseline: every descriptor as a packed bit row ((n, 8192/64) uint64), the query's
  bits ANDed with all rows and counted with `np.bitwise_count` (chunked, so temporaries stay small),
  then the same top-10 selection (overlap = Dice order for constant weight, ties to the older row);
- the index's previous NumPy ranking (`bincount` over every row; `bincount_top`), as a reference for
  the compiled pass that replaced it;
- the index ranking with a weight per query cell (a stream's condition, docs/design/science.md §11.10:
  about a third of the cells at 0, the rest in (0, 1]), the pass every stream's frame now takes: its
  median and its ratio to the unweighted pass;
- the ratios of the medians, and whether all three returned the same top-10 (seq and overlap) for
  every query: the benchmark is also a correctness check at sizes the unit tests never reach.

Index, previous ranking and brute force alternate query by query, so machine noise hits both alike.
"""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from benchmarks._common import RESULTS, quick_mode, rss_mib, write_json
from models.localisation.index import InvertedIndex

N_CELLS, WEIGHT, TOP_K = 8192, 40, 10
_CHUNK = 1 << 16  # rows per popcount chunk: (65536, 128) uint64 = 64 MiB of temporaries at most


def random_sets(rng: np.random.Generator, n: int, w: int = WEIGHT, n_cells: int = N_CELLS) -> np.ndarray:
    """(n, w) int32 rows of w distinct sorted cells each, uniform over the w-subsets of [0, n_cells).

    Rejection sampling, vectorised: draw w cells per row with replacement, redraw the rows that hold a
    duplicate (about 9 % for 40 of 8,192), so every subset is equally likely.
    """
    out = np.sort(rng.integers(0, n_cells, (n, w), dtype=np.int32), axis=1)
    bad = np.flatnonzero(np.any(out[:, 1:] == out[:, :-1], axis=1))
    while bad.size:
        redo = np.sort(rng.integers(0, n_cells, (bad.size, w), dtype=np.int32), axis=1)
        out[bad] = redo
        bad = bad[np.any(redo[:, 1:] == redo[:, :-1], axis=1)]
    return out


def noisy_query(rng: np.random.Generator, base: np.ndarray, keep: int, n_cells: int = N_CELLS) -> np.ndarray:
    """`base` (w,) with w - keep cells replaced by cells outside it; (w,) sorted int64."""
    kept = rng.choice(base, keep, replace=False)
    fresh = np.setdiff1d(rng.choice(n_cells, 4 * base.size, replace=False), base)[: base.size - keep]
    return np.sort(np.concatenate([kept, fresh]).astype(np.int64))


def pack(sets: np.ndarray, n_cells: int = N_CELLS) -> np.ndarray:
    """(n, w) cell sets -> (n, n_cells/64) uint64 bit rows (bit c of row i set iff c in sets[i])."""
    n = sets.shape[0]
    words = np.zeros((n, n_cells // 64), dtype=np.uint64)
    rows = np.repeat(np.arange(n), sets.shape[1])
    flat = sets.ravel().astype(np.int64)
    # Distinct cells within a row never share a bit, so adding the bits equals OR-ing them.
    np.add.at(words, (rows, flat >> 6), np.left_shift(np.uint64(1), (flat & 63).astype(np.uint64)))
    return words


def brute_top(packed: np.ndarray, q: np.ndarray, k: int = TOP_K) -> list[tuple[int, int]]:
    """Top-k rows by overlap with query cells `q` over packed rows: [(row, overlap)], ties to lower rows."""
    qw = pack(q[None, :])[0]
    n = packed.shape[0]
    ov = np.empty(n, dtype=np.int32)
    for lo in range(0, n, _CHUNK):
        block = np.bitwise_and(packed[lo:lo + _CHUNK], qw)
        ov[lo:lo + _CHUNK] = np.bitwise_count(block).sum(axis=1, dtype=np.int32)
    k = min(k, n)
    kth = np.partition(ov, n - k)[n - k]
    better = np.flatnonzero(ov > kth)
    equal = np.flatnonzero(ov == kth)[: k - better.size]
    pick = np.concatenate([better, equal])
    pick = pick[np.lexsort((pick, -ov[pick]))]  # overlap descending, then the older (lower) row
    return [(int(r), int(ov[r])) for r in pick]


def bincount_top(idx: InvertedIndex, q: np.ndarray, k: int = TOP_K) -> list[tuple[int, int]]:
    """The index's previous NumPy ranking (before the compiled pass), kept here as a reference:
    `bincount` over all rows, a pass over that vector, partition; [(seq, overlap)], ties to older."""
    n = len(idx)
    parts = [idx._post[c][: idx._plen[c]] for c in q.tolist() if idx._plen[c]]
    counts = np.bincount(np.concatenate(parts), minlength=n)
    cand = np.flatnonzero(counts >= 1)
    ov = counts[cand]
    score = 2.0 * ov / (idx._weight.data[cand] + q.size)
    k = min(k, cand.size)
    kth = np.partition(score, cand.size - k)[cand.size - k]
    better = np.flatnonzero(score > kth)
    equal = np.flatnonzero(score == kth)[: k - better.size]
    pick = np.sort(np.concatenate([better, equal]))
    pick = pick[np.argsort(-score[pick], kind="stable")]
    return [(int(idx._seq.data[cand[i]]), int(ov[i])) for i in pick]


def build_index(sets: np.ndarray) -> tuple[InvertedIndex, float]:
    """An index holding `sets` as seqs 1..n (one stream); returns it and the rebuild time in s."""
    idx = InvertedIndex(N_CELLS, max(1, sets.shape[0]))
    t0 = time.perf_counter()
    idx.rebuild(SimpleNamespace(seq=i + 1, winner_cells=row, stream="s") for i, row in enumerate(sets))
    return idx, time.perf_counter() - t0


def bench_size(n: int, queries: int, keep: int, seed: int = 0, brute: bool = True) -> dict[str, Any]:
    """Index vs brute force on n stored descriptors; see the module docstring.

    Returns:
        descriptors, index (rank_ms_median/p90, rebuild_s, bytes), brute (ms_median/p90, packed_bytes),
        ratio_brute_to_index, same_top10 (queries where both agree), queries.
    """
    rng = np.random.Generator(np.random.PCG64(seed))
    sets = random_sets(rng, n)
    rss0 = rss_mib()
    idx, rebuild_s = build_index(sets)
    rss_index = rss_mib() - rss0
    packed = pack(sets) if brute else None
    # Queries near stored descriptors spread over the whole map (old and new rows alike).
    targets = rng.integers(0, n, queries)
    qs = [noisy_query(rng, sets[t], keep) for t in targets]
    for q in qs[:3]:  # warm-up: allocator, caches
        idx.rank(q, TOP_K)
    weights = [np.where(rng.random(q.size) < 0.33, 0.0, rng.random(q.size)) for q in qs]
    idx.rank(qs[0], TOP_K, weights=weights[0])
    t_idx, t_brute, t_old, t_w, agree, found = [], [], [], [], 0, 0
    clock = time.perf_counter
    for q, target, w in zip(qs, targets, weights, strict=True):
        t0 = clock()
        got = idx.rank(q, TOP_K)
        t_idx.append(clock() - t0)
        t0 = clock()
        idx.rank(q, TOP_K, weights=w)
        t_w.append(clock() - t0)
        found += int(any(m.seq == target + 1 for m in got))
        t0 = clock()
        old = bincount_top(idx, q)
        t_old.append(clock() - t0)
        agree_old = [(m.seq, m.overlap) for m in got] == old
        if packed is not None:
            t0 = clock()
            ref = brute_top(packed, q)
            t_brute.append(clock() - t0)
            agree += int([(m.seq, m.overlap) for m in got] == [(r + 1, o) for r, o in ref] and agree_old)
    out: dict[str, Any] = {
        "descriptors": n, "queries": queries,
        "index": {"rank_ms_median": float(np.median(t_idx) * 1e3),
                  "rank_ms_p90": float(np.percentile(t_idx, 90) * 1e3),
                  "rebuild_s": rebuild_s, "bytes": idx.nbytes(), "postings": idx.postings(),
                  "rss_growth_mib": round(rss_index, 1)},
        "previous_numpy_rank_ms_median": float(np.median(t_old) * 1e3),
        "weighted_rank_ms_median": float(np.median(t_w) * 1e3),
        "ratio_weighted_to_index": float(np.median(t_w) / np.median(t_idx)),
        "target_in_top10": found,
    }
    out["ratio_previous_to_index"] = out["previous_numpy_rank_ms_median"] / out["index"]["rank_ms_median"]
    if packed is not None:
        out["brute"] = {"ms_median": float(np.median(t_brute) * 1e3),
                        "ms_p90": float(np.percentile(t_brute, 90) * 1e3), "packed_bytes": packed.nbytes}
        out["ratio_brute_to_index"] = out["brute"]["ms_median"] / out["index"]["rank_ms_median"]
        out["same_top10"] = agree
    return out


def main(*, sizes: list[int] | None, queries: int | None, keep: int, quick: bool, out: Path | None) -> None:
    if out is None:
        out = RESULTS / "index.json"
    quick = quick_mode(quick)
    sizes = sizes or ([1_000, 10_000] if quick else [1_000, 100_000, 1_000_000])
    queries = queries or (10 if quick else 50)
    results = []
    for n in sizes:
        r = bench_size(n, queries, keep)
        results.append(r)
        print(f"{n:>9} descriptors: index rank median {r['index']['rank_ms_median']:.3f} ms "
              f"(p90 {r['index']['rank_ms_p90']:.3f}), "
              f"brute-force popcount {r['brute']['ms_median']:.2f} ms, "
              f"ratio {r['ratio_brute_to_index']:.1f}x; previous NumPy rank "
              f"{r['previous_numpy_rank_ms_median']:.2f} ms ({r['ratio_previous_to_index']:.1f}x); "
              f"same top-10 {r['same_top10']}/{queries}; weighted rank {r['weighted_rank_ms_median']:.3f} ms "
              f"({r['ratio_weighted_to_index']:.2f}x the unweighted); "
              f"rebuild {r['index']['rebuild_s']:.2f} s, index {r['index']['bytes'] / 2**20:.1f} MiB, "
              f"packed {r['brute']['packed_bytes'] / 2**20:.1f} MiB", flush=True)
    write_json(out.name, {"config": {"n_cells": N_CELLS, "weight": WEIGHT, "top_k": TOP_K,
                                          "keep": keep, "quick": quick}, "results": results}, out)

