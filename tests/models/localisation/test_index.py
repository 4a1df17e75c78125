"""Inverted index: rankings equal a brute-force Dice ranking, ties to the older row, exclusions, bounds."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from models.localisation.index import IndexFull, InvertedIndex, Match


def random_sets(rng: np.random.Generator, n: int, w: int, n_cells: int) -> np.ndarray:
    """(n, w) sorted rows of w distinct cells each, uniform over [0, n_cells) (vectorised sampling)."""
    a = np.sort(rng.integers(0, n_cells, (n, w + 24)), axis=1)
    dup = np.zeros(a.shape, dtype=bool)
    dup[:, 1:] = a[:, 1:] == a[:, :-1]
    keys = rng.random(a.shape)
    keys[dup] = 2.0  # duplicates sort last and are never picked
    pick = np.argsort(keys, axis=1)[:, :w]
    out = np.sort(np.take_along_axis(a, pick, axis=1), axis=1)
    assert bool(np.all(np.diff(out, axis=1) > 0))
    return out


def brute(rows: list[tuple[int, np.ndarray, str]], q: np.ndarray, top_k: int, exclude: set[int],
          min_overlap: int) -> list[Match]:
    """Dice over every row with Python sets; sort by score, then older (lower seq) first."""
    qs = {int(c) for c in q}
    out = []
    for seq, cells, _ in rows:
        if seq in exclude:
            continue
        o = len(qs & {int(c) for c in cells})
        if o < min_overlap:
            continue
        denom = len(qs) + len(cells)
        out.append(Match(seq, o, 0.0 if denom == 0 else 2 * o / denom))
    out.sort(key=lambda m: (-m.score, m.seq))
    return out[:top_k]


def build(rng: np.random.Generator, n: int, n_cells: int, streams: tuple[str, ...] = ("a", "b"),
          seq_step: int = 3) -> tuple[InvertedIndex, list[tuple[int, np.ndarray, str]]]:
    idx = InvertedIndex(n_cells, 10_000)
    rows = []
    for i in range(n):
        # Variable widths, empty rows included: Dice must use each row's own weight.
        w = int(rng.integers(0, 12))
        cells = np.sort(rng.choice(n_cells, size=w, replace=False))
        seq = 5 + seq_step * i  # gaps, as after a restore
        stream = streams[int(rng.integers(len(streams)))]
        idx.add(seq, cells, stream)
        rows.append((seq, cells, stream))
    return idx, rows


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rank_equals_brute_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n_cells = 48  # small cell space: many overlaps and many exact ties
    idx, rows = build(rng, 300, n_cells)
    for _ in range(40):
        q = rng.choice(n_cells, size=int(rng.integers(0, 12)), replace=False)  # unsorted query
        for top_k in (1, 3, 10, 299, 1000):
            for min_overlap in (0, 1, 2):
                got = idx.rank(q, top_k, min_overlap=min_overlap)
                assert got == brute(rows, q, top_k, set(), min_overlap)
        ex = set(rng.choice([r[0] for r in rows], size=20, replace=False).tolist()) | {10**9}
        assert idx.rank(q, 7, exclude_seqs=ex) == brute(rows, q, 7, ex, 1)


@pytest.mark.parametrize("seed", [0, 1])
def test_rank_equals_brute_force_when_single_overlap_rows_are_skipped(seed: int) -> None:
    """Rows of equal weight: once k rows share two cells, the rows sharing one are never looked at
    (the bound of `_top_k_touched`); the ranking must not change, exclusions and ties included."""
    rng = np.random.default_rng(seed)
    n_cells, w = 200, 12
    idx = InvertedIndex(n_cells, 10_000)
    rows = []
    for i, cells in enumerate(random_sets(rng, 2_000, w, n_cells)):
        idx.add(i + 1, cells, "a")
        rows.append((i + 1, cells, "a"))
    for _ in range(30):
        q = rng.choice(n_cells, size=w, replace=False)
        for top_k in (1, 5, 40):
            assert idx.rank(q, top_k) == brute(rows, q, top_k, set(), 1)
        ex = {m.seq for m in idx.rank(q, 3)}
        assert idx.rank(q, 5, exclude_seqs=ex) == brute(rows, q, 5, ex, 1)


def test_a_small_row_sharing_one_cell_beats_large_rows_sharing_two() -> None:
    idx = InvertedIndex(1_000, 100)
    q = np.arange(10)
    for seq in range(1, 21):  # 100 cells each, two shared: Dice 4 / 110
        idx.add(seq, np.concatenate([[0, 1], np.arange(100, 198) + seq]), "a")
    idx.add(21, [5], "a")  # one cell, shared: Dice 2 / 11
    got = idx.rank(q, 3)
    assert [m.seq for m in got] == [21, 1, 2] and got[0].overlap == 1


def test_scores_are_dice() -> None:
    idx = InvertedIndex(100, 10)
    idx.add(1, [1, 2, 3, 4], "s")
    idx.add(2, [1, 2, 10, 11, 12, 13, 14, 15], "s")
    got = idx.rank([1, 2, 3], 5)
    assert got == [Match(1, 3, 2 * 3 / 7), Match(2, 2, 2 * 2 / 11)]
    assert all(isinstance(m, tuple) and len(m) == 3 for m in got)
    assert idx.rank([99], 5) == []  # nothing shared: no candidates by default
    assert idx.rank([99], 5, min_overlap=0) == [Match(1, 0, 0.0), Match(2, 0, 0.0)]
    assert idx.rank([], 5, min_overlap=0) == [Match(1, 0, 0.0), Match(2, 0, 0.0)]


def test_ties_go_to_the_older_observation() -> None:
    idx = InvertedIndex(64, 100)
    same = [3, 7, 9, 20]
    for seq in (4, 9, 10, 31, 40):
        idx.add(seq, same, "s")
    idx.add(41, [3, 7, 9, 21], "s")  # lower score
    assert [m.seq for m in idx.rank(same, 10)] == [4, 9, 10, 31, 40, 41]
    # The cut falls inside the tie: the older ones are kept.
    assert [m.seq for m in idx.rank(same, 2)] == [4, 9]
    assert [m.seq for m in idx.rank(same, 4)] == [4, 9, 10, 31]
    # Equal Dice from different overlaps and weights: 2·2/(4+6) = 2·1/(4+1) = 0.4, exactly.
    idx2 = InvertedIndex(64, 100)
    idx2.add(1, [0, 1, 2, 3, 4, 5], "s")       # q has 4 cells; overlap 2 → 4/10 = 0.4
    idx2.add(2, [0], "s")                      # overlap 1 → 2/5 = 0.4
    assert idx2.rank([0, 1, 50, 51], 1) == [Match(1, 2, 0.4)]
    assert idx2.rank([0, 1, 50, 51], 2) == [Match(1, 2, 0.4), Match(2, 1, 0.4)]


def test_exclude_own_skips_one_streams_rows_from_a_seq_on() -> None:
    idx = InvertedIndex(16, 100)
    cells = [1, 2, 3]
    for seq, stream in [(1, "a"), (2, "b"), (3, "a"), (4, "a"), (5, "b"), (6, "a")]:
        idx.add(seq, cells, stream)
    seqs = lambda **kw: [m.seq for m in idx.rank(cells, 10, **kw)]  # noqa: E731
    assert seqs() == [1, 2, 3, 4, 5, 6]
    # The own-trail rule (docs/design/science.md §11.6): rows of stream "a" from seq 4 on; others stay.
    assert seqs(exclude_own=("a", 4)) == [1, 2, 3, 5]
    assert seqs(exclude_own=("a", 2)) == [1, 2, 5]  # seq 2 is b's: a's rows from 2 on are 3, 4, 6
    assert seqs(exclude_own=("b", 5)) == [1, 2, 3, 4, 6]
    assert seqs(exclude_own=("a", 0)) == [2, 5]
    assert seqs(exclude_own=("zzz", 3)) == [1, 2, 3, 4, 5, 6]
    assert seqs(exclude_own=("a", 7)) == [1, 2, 3, 4, 5, 6]
    assert seqs(exclude_own=("a", 6), exclude_seqs=[1, 2]) == [3, 4, 5]


def test_a_frame_without_context_is_ranked_by_its_columns() -> None:
    """`rank_columns` (docs/design/science.md §11.2 step 1): 4 cells per column; a stored row shares a
    query column where one of its winner cells lies in it, whichever cell the context chose, and a
    column counts once however many winners the row has in it."""
    cpc = 4
    idx = InvertedIndex(16 * cpc, 10)
    idx.add(1, [0 * cpc + 1, 1 * cpc + 3, 2 * cpc + 0], "s")  # columns 0, 1, 2, other cells
    idx.add(2, [0 * cpc + 0, 1 * cpc + 0, 9 * cpc + 0], "s")  # columns 0, 1, 9
    idx.add(3, [5 * cpc + 2], "s")                             # column 5 only
    idx.add(4, [0 * cpc + 1, 0 * cpc + 2, 1 * cpc + 1, 1 * cpc + 2], "t")  # columns 0, 1: two winners each
    # by cells, the least-used cells of columns 0, 1 and 2 name row 2, whose columns are not the frame's
    assert idx.rank([0, 4, 8], 5) == [Match(2, 2, 2 * 2 / 6), Match(1, 1, 2 * 1 / 6)]
    got = idx.rank_columns([2, 0, 1], cpc, 5)
    assert got == [Match(1, 3, 1.0), Match(2, 2, 2 / 3), Match(4, 2, 2 / 3)]  # row 3 shares none
    # a row holding two of the frame's four columns, twice each, is no full match (a reviewer's case)
    idx.add(5, [0 * cpc + 3, 1 * cpc + 3, 2 * cpc + 3, 3 * cpc + 3], "u")
    assert idx.rank_columns([0, 1, 2, 3], cpc, 2) == [Match(5, 4, 1.0), Match(1, 3, 0.75)]
    assert {m.seq: m.score for m in idx.rank_columns([0, 1, 2, 3], cpc, 5)}[4] == 0.5
    assert [m.seq for m in idx.rank_columns([0, 1], cpc, 5)] == [1, 2, 4, 5]  # ties to the older row
    assert [m.seq for m in idx.rank_columns([0, 1, 2], cpc, 5, exclude_own=("s", 2))] == [1, 5, 4]
    assert idx.rank_columns([7], cpc, 5) == [] and idx.rank_columns([0], cpc, 0) == []
    with pytest.raises(ValueError):
        idx.rank_columns([16], cpc, 3)


def test_top_k_bounds_and_empty() -> None:
    idx = InvertedIndex(16, 100)
    assert idx.rank([1], 5) == [] and len(idx) == 0
    idx.add(1, [1, 2], "s")
    idx.add(2, [2, 3], "s")
    assert idx.rank([2], 0) == []
    assert [m.seq for m in idx.rank([2], 1000)] == [1, 2]
    with pytest.raises(ValueError):
        idx.rank([16], 3)


def test_add_validates() -> None:
    idx = InvertedIndex(16, 100)
    idx.add(5, [1, 2], "s")
    with pytest.raises(ValueError):
        idx.add(5, [1], "s")  # seq not increasing
    for bad in ([2, 1], [1, 1], [-1], [16], [[1]]):
        with pytest.raises(ValueError):
            idx.add(9, bad, "s")
    assert len(idx) == 1 and idx.postings() == 2


def test_index_full() -> None:
    idx = InvertedIndex(16, 3)
    for seq in (1, 2, 3):
        idx.add(seq, [seq], "s")
    with pytest.raises(IndexFull) as err:
        idx.add(4, [4], "s")
    assert err.value.max_observations == 3
    assert len(idx) == 3 and [m.seq for m in idx.rank([1, 2, 3, 4], 10)] == [1, 2, 3]
    rows = [SimpleNamespace(seq=s, winner_cells=np.array([s]), stream="s") for s in range(1, 5)]
    with pytest.raises(IndexFull):
        idx.rebuild(rows)
    assert len(idx) == 3  # a failed rebuild leaves the index as it was
    with pytest.raises(ValueError):
        idx.rebuild([rows[1], rows[0]])
    with pytest.raises(ValueError):
        idx.rebuild([SimpleNamespace(seq=1, winner_cells=np.array([3, 2]), stream="s")])
    assert len(idx) == 3


def test_rebuild_equals_incremental_and_sizes() -> None:
    rng = np.random.default_rng(5)
    idx, rows = build(rng, 500, 256)
    other = InvertedIndex(256, 10_000)
    other.rebuild(SimpleNamespace(seq=s, winner_cells=c, stream=st) for s, c, st in rows)
    assert len(other) == len(idx) == 500
    assert other.postings() == idx.postings() == sum(len(c) for _, c, _ in rows)
    assert other.last_seq() == idx.last_seq() == rows[-1][0]
    for _ in range(30):
        q = rng.choice(256, size=10, replace=False)
        kw = {"exclude_own": ("a", rows[-40][0])}
        assert other.rank(q, 8, **kw) == idx.rank(q, 8, **kw)
    # Adding after a rebuild continues where it left off.
    other.add(10**6, [1, 2, 3], "a")
    assert other.rank([1, 2, 3], 1) == [Match(10**6, 3, 1.0)]
    # nbytes counts allocated array bytes exactly, and grows with the postings.
    before = idx.nbytes()
    assert before >= idx.postings() * 4 + len(idx) * 12
    for i in range(200):
        idx.add(10**7 + i, list(range(i % 200, i % 200 + 40)), "c")
    assert idx.nbytes() > before
    other.rebuild([])
    assert len(other) == 0 and other.postings() == 0 and other.rank([1], 3) == []


def test_rank_at_1e5_descriptors() -> None:
    """10^5 stored descriptors of 40 cells out of 8,192 (its speed: benchmarks/bench_index.py)."""
    rng = np.random.default_rng(0)
    n, w, n_cells = 100_000, 40, 8192
    cells = random_sets(rng, n, w, n_cells)
    idx = InvertedIndex(n_cells, 1_000_000)
    idx.rebuild(SimpleNamespace(seq=i + 1, winner_cells=cells[i], stream="s") for i in range(n))
    assert idx.postings() == n * w
    # A stored descriptor finds itself first.
    assert idx.rank(cells[1234], 1)[0] == Match(1235, 40, 1.0)


def brute_weighted(rows: list[tuple[int, np.ndarray, str]], q: np.ndarray, w: np.ndarray, top_k: int,
                   exclude: set[int], min_overlap: int) -> list[tuple[int, int, float]]:
    """The weighted Dice of `rank(weights=...)` over every row: (2|q| / W) min(S, |row| W / |q|) /
    (|q| + |row|), S the shared cells' weight, W the query's; sorted by score, then older first."""
    weight = {int(c): float(x) for c, x in zip(q, w, strict=True)}
    total = sum(weight.values())
    out = []
    for seq, cells, _ in rows:
        shared = set(weight) & {int(c) for c in cells}
        if seq in exclude or len(shared) < min_overlap:
            continue
        acc = sum(weight[c] for c in sorted(shared))  # in cell order, as the index sums
        held = min(acc, len(cells) * (total / len(weight)))  # at most its size's share of the weight
        denom = len(weight) + len(cells)
        out.append((seq, len(shared), 0.0 if denom == 0 else 2.0 * len(weight) / total * held / denom))
    out.sort(key=lambda m: (-m[2], m[0]))
    return out[:top_k]


def _same(got: list[Match], want: list[tuple[int, int, float]]) -> bool:
    return [(m.seq, m.overlap) for m in got] == [(s, o) for s, o, _ in want] and np.allclose(
        [m.score for m in got], [x for _, _, x in want], rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_weighted_rank_equals_brute_force(seed: int) -> None:
    """A stream's condition weighs the query's cells (docs/design/science.md §11.10): the compiled pass
    and the every-row pass rank by the weighted Dice, exclusions and min_overlap as without weights."""
    rng = np.random.default_rng(seed)
    n_cells = 48
    idx, rows = build(rng, 300, n_cells)
    for _ in range(30):
        q = rng.choice(n_cells, size=int(rng.integers(1, 12)), replace=False)
        # Quantised weights (zeros included) so that equal scores are equal floats and ties are exact.
        w = rng.integers(0, 5, q.size) / 4.0
        if not w.any():
            w[0] = 1.0
        for top_k in (1, 3, 10, 1000):
            for min_overlap in (0, 1, 2):
                got = idx.rank(q, top_k, min_overlap=min_overlap, weights=w)
                want = brute_weighted(rows, q, w, top_k, set(), min_overlap)
                if min_overlap == 0:  # the every-row pass also lists rows sharing nothing, last
                    got = [m for m in got if m.overlap > 0]
                    want = [m for m in want if m[1] > 0][:len(got)]
                assert _same(got, want)
        ex = set(rng.choice([r[0] for r in rows], size=20, replace=False).tolist())
        assert _same(idx.rank(q, 7, exclude_seqs=ex, weights=w), brute_weighted(rows, q, w, 7, ex, 1))


def test_weighted_rank_skips_single_overlap_rows_only_when_they_cannot_enter() -> None:
    """The bound of the weighted pass: a small row sharing one heavily weighted cell beats large rows
    sharing two light ones, and is found although k rows share two cells."""
    idx = InvertedIndex(1_000, 100)
    q = np.arange(10)
    w = np.full(10, 0.1)
    w[5] = 1.0
    for seq in range(1, 21):  # 100 cells each, cells 0 and 1 shared
        idx.add(seq, np.concatenate([[0, 1], np.arange(100, 198) + seq]), "a")
    idx.add(21, [5], "a")
    got = idx.rank(q, 3, weights=w)
    assert [m.seq for m in got] == [21, 1, 2] and got[0].overlap == 1
    # Cell 5 discounted to nothing: the one-cell row scores 0 and the large rows come first.
    w[5] = 0.0
    assert [m.seq for m in idx.rank(q, 3, weights=w)] == [1, 2, 3]


def test_weighted_scores_stay_within_zero_and_one() -> None:
    """A row smaller than the query that holds its heaviest cells must not score above an equal row."""
    idx = InvertedIndex(100, 10)
    idx.add(1, [1, 2], "a")  # two of the query's three cells, the heavy ones
    idx.add(2, [1, 2, 3], "a")  # the query itself
    got = idx.rank([1, 2, 3], 2, weights=np.array([1.0, 1.0, 0.1]))
    assert [m.seq for m in got] == [2, 1] and got[0].score == pytest.approx(1.0) and got[1].score < 1.0


def test_weights_of_one_are_plain_dice_and_an_equal_row_scores_one() -> None:
    rng = np.random.default_rng(7)
    idx, _ = build(rng, 200, 64)
    for _ in range(20):
        q = rng.choice(64, size=8, replace=False)
        plain, ones = idx.rank(q, 20), idx.rank(q, 20, weights=np.ones(8))
        assert [(m.seq, m.overlap) for m in plain] == [(m.seq, m.overlap) for m in ones]
        assert np.allclose([m.score for m in plain], [m.score for m in ones], atol=1e-12)
    idx.add(10**6, [3, 9, 20], "b")
    top = idx.rank([20, 3, 9], 1, weights=np.array([0.2, 0.9, 0.5]))[0]
    assert top.seq == 10**6 and top.score == pytest.approx(1.0)


def test_weights_are_per_query_cell_in_the_callers_order_and_checked() -> None:
    idx = InvertedIndex(100, 10)
    idx.add(1, [1, 2], "a")
    idx.add(2, [3, 4], "a")
    # cells given unsorted: weight 1 goes with cell 3, weight 0 with cell 1
    assert [m.seq for m in idx.rank([3, 1], 2, weights=np.array([1.0, 0.0]))] == [2, 1]
    assert [m.seq for m in idx.rank([3, 1], 2, weights=np.array([0.0, 1.0]))] == [1, 2]
    # every weight 0: nothing to rank by, plain Dice
    assert idx.rank([3, 1], 2, weights=np.zeros(2)) == idx.rank([3, 1], 2)
    for bad in (np.ones(3), np.array([0.5, 1.5]), np.array([-0.1, 1.0]), np.array([np.nan, 1.0])):
        with pytest.raises(ValueError, match="weights"):
            idx.rank([3, 1], 2, weights=bad)
