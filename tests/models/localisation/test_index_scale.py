"""The compiled ranking pass of the inverted index: same answers as the NumPy path and a brute force,
with large queries (int32 counters), after growth, after exclusions, and from concurrent readers.

Its speed is measured in benchmarks/bench_index.py, never here.
"""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np

from models.localisation import index
from models.localisation.index import InvertedIndex, Match, warm_up


def random_sets(rng: np.random.Generator, n: int, w: int, n_cells: int) -> list[np.ndarray]:
    return [np.sort(rng.choice(n_cells, w, replace=False)) for _ in range(n)]


def brute(sets: list[np.ndarray], q: np.ndarray, k: int,
          exclude: frozenset[int] = frozenset()) -> list[Match]:
    """Dice over every row (seq = row + 1), overlap >= 1, best first, ties to the older row."""
    qs = set(q.tolist())
    out = []
    for i, cells in enumerate(sets):
        o = len(qs & set(cells.tolist()))
        if o >= 1 and i + 1 not in exclude:
            out.append(Match(i + 1, o, 2 * o / (len(qs) + cells.size)))
    out.sort(key=lambda m: (-m.score, m.seq))
    return out[:k]


def build(sets: list[np.ndarray], n_cells: int) -> InvertedIndex:
    idx = InvertedIndex(n_cells, 1_000_000)
    idx.rebuild(SimpleNamespace(seq=i + 1, winner_cells=c, stream="s") for i, c in enumerate(sets))
    return idx


def test_compiled_pass_equals_numpy_path() -> None:
    """min_overlap=1 (compiled) equals min_overlap=0 (NumPy, every row) without its zero-overlap tail."""
    rng = np.random.default_rng(11)
    sets = random_sets(rng, 5_000, 40, 2048)
    idx = build(sets, 2048)
    for _ in range(20):
        q = np.sort(rng.choice(2048, 40, replace=False))
        full = [m for m in idx.rank(q, len(idx), min_overlap=0) if m.overlap >= 1]
        for k in (1, 10, 100):
            assert idx.rank(q, k) == full[:k]


def test_queries_above_255_cells_use_wide_counters() -> None:
    """Overlaps above 255 would wrap a uint8 counter: a 400-cell query must still count them exactly."""
    rng = np.random.default_rng(3)
    n_cells = 1024
    sets = random_sets(rng, 300, 350, n_cells)
    idx = build(sets, n_cells)
    for _ in range(5):
        q = np.sort(rng.choice(n_cells, 400, replace=False))
        got = idx.rank(q, 10)
        assert got == brute(sets, q, 10)
        assert got[0].overlap > 100
    same = idx.rank(sets[7], 1)
    assert same == [Match(8, 350, 1.0)]  # 350 shared cells: beyond uint8


def test_results_do_not_depend_on_earlier_queries() -> None:
    """The scratch counters are left clean: interleaved queries, exclusions and adds change nothing."""
    rng = np.random.default_rng(5)
    n_cells = 512
    sets = random_sets(rng, 3_000, 20, n_cells)
    idx = build(sets, n_cells)
    queries = [np.sort(rng.choice(n_cells, 20, replace=False)) for _ in range(30)]
    first = [idx.rank(q, 5) for q in queries]
    for q in queries:  # exclusions of touched rows, then queries without them
        ex = frozenset(m.seq for m in idx.rank(q, 3))
        assert idx.rank(q, 5, exclude_seqs=ex) == brute(sets, q, 5, ex)
        idx.rank(np.arange(300), 2)  # a wide query in between
    assert [idx.rank(q, 5) for q in queries] == first
    fresh = build(sets, n_cells)
    assert [fresh.rank(q, 5) for q in queries] == first


def test_rows_added_after_a_query_are_found() -> None:
    """The counters grow with the index: rows past the first scratch capacity are counted."""
    idx = InvertedIndex(64, 100_000)
    rng = np.random.default_rng(2)
    sets = random_sets(rng, 10, 8, 64)
    for i, c in enumerate(sets):
        idx.add(i + 1, c, "s")
    assert idx.rank(sets[3], 1) == [Match(4, 8, 1.0)]
    more = random_sets(rng, 5_000, 8, 64)
    for i, c in enumerate(more):
        idx.add(11 + i, c, "s")
    target = np.array([60, 61, 62, 63, 0, 1, 2, 3])
    idx.add(6_000, np.sort(target), "s")
    assert idx.rank(target, 1) == [Match(6_000, 8, 1.0)]
    assert idx.rank(sets[3], 1) == [Match(4, 8, 1.0)]  # an identical later set would tie: older first


def test_concurrent_readers_agree_with_sequential() -> None:
    rng = np.random.default_rng(8)
    sets = random_sets(rng, 4_000, 30, 1024)
    idx = build(sets, 1024)
    queries = [np.sort(rng.choice(1024, 30, replace=False)) for _ in range(40)]
    expected = [idx.rank(q, 10) for q in queries]
    got: dict[int, list[list[Match]]] = {}

    def reader(t: int) -> None:
        got[t] = [idx.rank(q, 10) for q in queries]

    threads = [threading.Thread(target=reader, args=(t,)) for t in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(got[t] == expected for t in range(4))


def test_warm_up_compiles_without_side_effects() -> None:
    warm_up()
    # every kernel a frame can reach, a stream's first (ranked by its columns) too
    assert index._top_k_touched.signatures and index._count_column.signatures
    idx = InvertedIndex(16, 10)
    idx.add(1, [1, 2, 3], "s")
    assert idx.rank([1, 2, 3], 3) == [Match(1, 3, 1.0)]
