"""In-memory inverted index over winner cells: who shares cells with a query, ranked by Dice
(docs/design/service.md §5).

Layout: one growable int32 array of row numbers per cell (its postings), plus per-row arrays of seq
and weight (|cells|). Rows are numbered 0, 1, … in insertion order and seqs must increase with them,
so "older" is simply "lower row" and ties go to the older observation for free in a stable sort.

A query gathers the postings of its cells and, in one compiled pass (`_top_k_touched`, numba), counts
overlaps per row in a reusable counter, turns them into Dice = 2·overlap / (|query| + |stored|) and
keeps the k best in a small sorted buffer (score descending, ties to the lower row); rows sharing a
single cell are looked at only when a bound says one could still enter the k best. A stream's query may
weigh its cells (its condition, docs/design/science.md §11.10): the same pass then also sums the weights
per row, and the score is the weighted Dice. The cost is the
postings touched (≈ |query| · rows · |cells| / n_cells: about 20,000 for 10^5 rows of 40 of 8,192
cells, 200,000 for 10^6) and nothing proportional to the number of rows: the earlier NumPy version
(`bincount` over all rows, then a pass over that vector) spent most of its time allocating and
scanning the per-row vector, about 11 ms per query at 10^6 rows here against the 5 ms target
(benchmarks/bench_index.py, docs/benchmarks.md). `min_overlap=0` (rank every row) keeps the NumPy path.

The index is derived data: it is rebuilt from `map.sqlite` (`rebuild`) and appended after each commit
(`add`). It is bounded: `max_observations` rows, then `IndexFull`. A row leaves it with `remove` (an
appearance dropped by its place's cap, a forgotten place: docs/design/science.md §11.9): it is no
candidate at once, and its postings are reclaimed when the removed rows reach a quarter of the rows, or
when an add finds the index full (`compact`, O(postings)).
Not thread-safe for concurrent writers; the map's single writer owns it. `rank` shares one scratch
counter, guarded by a lock, so concurrent readers are safe. `nbytes`/`postings`/`len` read plain
counters and may be called from other threads.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Sequence
from typing import NamedTuple, Protocol

import numpy as np
from numba import njit

__all__ = ["MAX_ROWS", "IndexFull", "IndexRow", "InvertedIndex", "Match"]

_ROW = np.int32  # row numbers, hence the cap below
MAX_ROWS = 2**31 - 1  # the most rows an index holds (`max_observations`): row numbers are int32
_MIN_CAP = 4  # first allocation of a cell's postings; doubled when full
_NO_WEIGHTS = np.zeros(0, dtype=np.float64)  # `_top_k_touched` without weights: plain Dice


class IndexFull(Exception):  # noqa: N818 - named after the problem slug `map-full`
    """Adding beyond `max_observations`."""

    def __init__(self, max_observations: int) -> None:
        super().__init__(f"index holds its maximum of {max_observations} observations")
        self.max_observations = max_observations


class Match(NamedTuple):
    """One ranked result: a plain (seq, overlap, score) tuple with names."""

    seq: int
    overlap: int
    score: float


class IndexRow(Protocol):
    """What `rebuild` reads from each row (`storage.mapstore.Observation` fits)."""

    @property
    def seq(self) -> int: ...

    @property
    def winner_cells(self) -> np.ndarray: ...

    @property
    def stream(self) -> str: ...


class _Grow:
    """An append-only int array with doubling capacity (amortised O(1) append, exact `nbytes`)."""

    __slots__ = ("data", "n")

    def __init__(self, dtype: type, cap: int = _MIN_CAP) -> None:
        self.data = np.empty(cap, dtype=dtype)
        self.n = 0

    def append(self, v: int) -> None:
        if self.n == self.data.size:
            self.data = np.concatenate([self.data, np.empty(max(self.data.size, _MIN_CAP),
                                                            dtype=self.data.dtype)])
        self.data[self.n] = v
        self.n += 1

    def view(self) -> np.ndarray:
        return self.data[: self.n]


def _check_cells(cells: np.ndarray | Sequence[int], n_cells: int) -> np.ndarray:
    """Validate sorted, distinct, in-range cell ids and return them as int64."""
    c = np.asarray(cells)
    if c.ndim != 1:
        raise ValueError(f"cells must be 1-D, got shape {c.shape}")
    if c.size == 0:
        return np.zeros(0, dtype=np.int64)
    if c.dtype.kind not in "iu":
        raise ValueError(f"cells must be integers, got {c.dtype}")
    c = c.astype(np.int64, copy=False)
    if c[0] < 0 or c[-1] >= n_cells or (c.size > 1 and not bool(np.all(c[1:] > c[:-1]))):
        raise ValueError(f"cells must be sorted, distinct and in [0, {n_cells})")
    return c


@njit(cache=True, inline="always")
def _offer(r, o, s, k, nb, best_row, best_ov, best_sc):  # pragma: no cover
    """Insert row r (overlap o, score s) into the k best kept so far; returns the new count kept.

    Order: score descending, ties to the lower row, a strict total order, so the k kept never depend on
    the order rows are offered in."""
    if nb == k:
        # Full: a newcomer must beat the worst kept one (higher score, or equal and older).
        if s < best_sc[k - 1] or (s == best_sc[k - 1] and r > best_row[k - 1]):
            return nb
        pos = k - 1
    else:
        pos = nb
        nb += 1
    while pos > 0 and (s > best_sc[pos - 1] or (s == best_sc[pos - 1] and r < best_row[pos - 1])):
        best_sc[pos] = best_sc[pos - 1]
        best_ov[pos] = best_ov[pos - 1]
        best_row[pos] = best_row[pos - 1]
        pos -= 1
    best_sc[pos] = s
    best_ov[pos] = o
    best_row[pos] = r
    return nb


@njit(cache=True)
def _count_column(rows: np.ndarray, j: int, mark: np.ndarray, counts: np.ndarray) -> None:  # pragma: no cover
    """`InvertedIndex.rank_columns`' pass over the postings `rows` of the query's column `j` (its cells'
    postings, a row once per cell it has there): each row counted once for the column (`mark`: the last
    column that counted it)."""
    for i in range(rows.size):
        r = rows[i]
        if mark[r] != j:
            mark[r] = j
            counts[r] += 1


@njit(cache=True)
def _top_k_touched(flat: np.ndarray, flat_w: np.ndarray, weight: np.ndarray, q_size: int,
                   w_total: float, w_max: float, k: int, min_overlap: int, w_min: int, excluded: np.ndarray,
                   counts: np.ndarray, acc: np.ndarray,
                   multi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Overlap counting and top-k Dice selection over the rows a query touches (compiled).

    Most touched rows share one cell with the query (about 98 % of the 200,000 touched at 10^6 random
    rows), and none of them can beat k rows of higher overlap unless a small stored row makes its Dice
    large: rows are listed only when their count reaches 2, ranked, and the single-overlap rows are
    offered only when the bound 2 / (w_min + q_size) could still enter the k best. That skips a write
    per touched row and a random read of its count and weight (issue 25).

    With a weight per query cell (a stream's condition, docs/design/science.md §11.10) the score is the
    weighted Dice (2|q| / W) · min(S, |stored| · W / |q|) / (|q| + |stored|): S the shared cells'
    weight, W the query's. For rows of the query's size (every code of a map has one size) it is S / W,
    the share of the query's weight the row holds; a row holds at most its size's share of the query's
    weight, which keeps the score in [0, 1] (1 for a row equal to the query), and with every weight 1
    it is Dice. A single-overlap row scores at most (2|q| / W) · w_max / (w_min + |q|).

    Args:
        flat: (p,) int32 rows from the query cells' postings (a row appears once per shared cell).
        flat_w: (p,) float64 the weight of the query cell each entry of `flat` came from; empty: every
            cell weighs 1 (plain Dice, no per-row sums).
        weight: (>= rows,) int32 |cells| of each stored row.
        q_size: |query|. w_total, w_max: the query cells' weights summed (> 0) and their largest (with
            `flat_w`; ignored without).
        k: results wanted (>= 1).
        min_overlap: rows sharing fewer cells are skipped (>= 1 here: untouched rows never qualify).
        w_min: a lower bound of the weights of the rows in `flat` (the bound above).
        excluded: (e,) int64 rows never returned.
        counts: (>= rows,) uint8 or int32 scratch, all zero on entry and left all zero on exit; uint8
            only when q_size <= 255 (an overlap never exceeds q_size).
        acc: (>= rows,) float64 scratch of the weighted sums (with `flat_w`), all zero on entry and exit.
        multi: (>= rows,) int32 scratch for the rows whose count reaches max(min_overlap, 2).

    Returns:
        rows, overlaps (int64) and scores (float64), each (m,) with m <= k, best first: score
        descending, ties to the lower row. The score is the same float64 expression as the NumPy path,
        2.0 * overlap / (weight + q_size), so equal fractions tie exactly.
    """
    weighted = flat_w.size > 0
    share = 2.0 * q_size / w_total if weighted else 2.0
    w_mean = w_total / q_size if weighted else 1.0
    listed = max(min_overlap, 2)
    m = 0
    for i in range(flat.size):
        r = flat[i]
        c = counts[r] + 1
        counts[r] = c
        if weighted:
            acc[r] += flat_w[i]
        if c == listed:
            multi[m] = r
            m += 1
    for i in range(excluded.size):
        counts[excluded[i]] = 0  # an excluded row keeps its place in `multi` with 0 < min_overlap: skipped
    best_row = np.empty(k, dtype=np.int64)
    best_ov = np.empty(k, dtype=np.int64)
    best_sc = np.empty(k, dtype=np.float64)
    nb = 0
    for j in range(m):
        r = multi[j]
        o = counts[r]
        if o < min_overlap:
            continue
        d = weight[r] + q_size
        x = share * min(acc[r], weight[r] * w_mean) if weighted else 2.0 * o
        nb = _offer(r, o, x / d if d > 0 else 0.0, k, nb, best_row, best_ov, best_sc)
    if min_overlap <= 1:
        d_min = w_min + q_size
        bound = (share * w_max if weighted else 2.0) / d_min if d_min > 0 else np.inf
        if nb < k or bound >= best_sc[k - 1]:
            # Single-overlap rows could still enter: each appears exactly once in `flat`.
            for i in range(flat.size):
                r = flat[i]
                if counts[r] == 1:
                    d = weight[r] + q_size
                    x = share * min(acc[r], weight[r] * w_mean) if weighted else 2.0
                    nb = _offer(r, 1, x / d if d > 0 else 0.0, k, nb, best_row, best_ov, best_sc)
    for i in range(flat.size):
        counts[flat[i]] = 0  # leave the scratch clean for the next query
        if weighted:
            acc[flat[i]] = 0.0
    return best_row[:nb], best_ov[:nb], best_sc[:nb]


def warm_up() -> None:
    """Compile (or load from numba's disk cache) the ranking kernels now, not in the first query (nor in
    a stream's first frame: `rank_columns`)."""
    idx = InvertedIndex(512, 4)
    idx.add(1, [1, 2], "s")
    idx.rank_columns([0, 1], 2, 1)
    idx.rank([1, 3], 1)  # the uint8 counters
    idx.rank(np.arange(300), 1)  # the int32 counters
    idx.rank([1, 3], 1, weights=np.array([0.5, 1.0]))  # the weighted pass
    idx.rank(np.arange(300), 1, weights=np.ones(300))


class InvertedIndex:
    """Cell → rows index with Dice ranking.

    Args:
        n_cells: size of the cell space (the TM's cells); cells must lie in [0, n_cells).
        max_observations: the most rows it will hold (docs/design/service.md §1.4).
    """

    def __init__(self, n_cells: int, max_observations: int) -> None:
        if n_cells <= 0:
            raise ValueError(f"n_cells must be positive, got {n_cells}")
        if not 0 < max_observations <= MAX_ROWS:
            raise ValueError(f"max_observations must be in [1, {MAX_ROWS}], got {max_observations}")
        self.n_cells = int(n_cells)
        self.max_observations = int(max_observations)
        self._clear()

    def _clear(self) -> None:
        # Postings are allocated lazily per cell: most of a large cell space may never be a winner.
        self._post: list[np.ndarray | None] = [None] * self.n_cells
        self._plen: list[int] = [0] * self.n_cells
        self._post_bytes = 0
        self._postings = 0
        self._seq = _Grow(np.int64, 1024)
        self._weight = _Grow(np.int32, 1024)
        self._w_min = 0  # least weight of a non-empty row (the bound of `_top_k_touched`; 0 when none)
        self._stream_id: dict[str, int] = {}
        self._stream_rows: list[_Grow] = []
        self._dead: set[int] = set()  # rows removed but not yet compacted away (`remove`)
        # Scratch of `rank`, grown with the rows and all zero between queries: per-row overlap counters
        # (uint8 for queries of at most 255 cells, whose overlaps cannot overflow it: 1 MB at 10^6 rows
        # stays in a 2 MiB L2 cache, which makes the random increments about 3x faster than int32;
        # int32 for larger queries) and the list of rows sharing two cells or more.
        self._counts8 = np.zeros(0, dtype=np.uint8)
        self._counts32 = np.zeros(0, dtype=np.int32)
        self._touched = np.zeros(0, dtype=np.int32)
        self._acc = np.zeros(0, dtype=np.float64)  # the weighted pass's per-row sums (all zero between)
        self._scratch_lock = threading.Lock()

    # ------------------------------------------------------------------ sizes

    def __len__(self) -> int:
        """Number of observations held (removed ones not counted)."""
        return self._seq.n - len(self._dead)

    def postings(self) -> int:
        """Total number of (cell, row) entries."""
        return self._postings

    def nbytes(self) -> int:
        """Exact bytes of the index's numpy arrays (allocated capacity, not just the used part).

        Python object overhead (the per-cell list, dict entries) is not included: it is not array
        memory, and `process_rss_bytes` reports the whole process anyway.
        """
        rows = self._seq.data.nbytes + self._weight.data.nbytes
        streams = sum(g.data.nbytes for g in self._stream_rows)
        scratch = self._counts8.nbytes + self._counts32.nbytes + self._touched.nbytes + self._acc.nbytes
        return int(self._post_bytes + rows + streams + scratch)

    def last_seq(self) -> int:
        """Highest stored seq (0 when empty)."""
        return int(self._seq.data[self._seq.n - 1]) if self._seq.n else 0

    # ------------------------------------------------------------------ writes

    def add(self, seq: int, cells: np.ndarray | Sequence[int], stream: str) -> int:
        """Append one observation (after its commit).

        Args:
            seq: its seq; must exceed every stored seq.
            cells: its winner cells, sorted and distinct.
            stream: its stream (for `exclude_own`).

        Returns:
            Its row number.

        Raises:
            IndexFull: already `max_observations` rows.
            ValueError: seq not increasing, or bad cells.
        """
        if self._seq.n >= self.max_observations and self._dead:
            self.compact()
        if self._seq.n >= self.max_observations:
            raise IndexFull(self.max_observations)
        seq = int(seq)
        if self._seq.n and seq <= self.last_seq():
            raise ValueError(f"seq {seq} is not above the last indexed seq {self.last_seq()}")
        c = _check_cells(cells, self.n_cells)
        row = self._seq.n
        post, plen = self._post, self._plen
        for cell in c.tolist():
            arr, n = post[cell], plen[cell]
            if arr is None:
                arr = post[cell] = np.empty(_MIN_CAP, dtype=_ROW)
                self._post_bytes += arr.nbytes
            elif n == arr.size:
                grown = np.empty(2 * n, dtype=_ROW)
                grown[:n] = arr
                self._post_bytes += grown.nbytes - arr.nbytes
                arr = post[cell] = grown
            arr[n] = row
            plen[cell] = n + 1
        self._postings += int(c.size)
        self._seq.append(seq)
        self._weight.append(int(c.size))
        if c.size and (self._w_min == 0 or c.size < self._w_min):
            self._w_min = int(c.size)
        self._rows_of(stream).append(row)
        return row

    def remove(self, seqs: Iterable[int]) -> int:
        """Take stored seqs out of the ranking (seqs not held are ignored); returns how many left.
        Compacts once removed rows are a quarter of the rows."""
        ex = np.fromiter((int(s) for s in seqs), dtype=np.int64)
        if not ex.size or not self._seq.n:
            return 0
        view = self._seq.view()
        pos = np.clip(np.searchsorted(view, ex), 0, view.size - 1)
        new = {int(p) for p in pos[view[pos] == ex]} - self._dead
        self._dead |= new
        if 4 * len(self._dead) >= self._seq.n:
            self.compact()
        return len(new)

    def compact(self) -> None:
        """Reclaim the postings and rows of removed rows, renumbering the rest in order (so ties still go
        to the older seq): O(postings)."""
        if not self._dead:
            return
        n = self._seq.n
        keep = np.ones(n, bool)
        keep[np.fromiter(self._dead, np.int64)] = False
        new_row = (np.cumsum(keep) - 1).astype(_ROW)
        total = postings = 0
        for cell in range(self.n_cells):
            arr = self._post[cell]
            if arr is None:
                continue
            rows = arr[:self._plen[cell]]
            rows = new_row[rows[keep[rows]]]
            if rows.size == 0:
                self._post[cell], self._plen[cell] = None, 0
                continue
            out = np.empty(max(_MIN_CAP, rows.size + rows.size // 4), dtype=_ROW)
            out[:rows.size] = rows
            self._post[cell], self._plen[cell] = out, int(rows.size)
            total += out.nbytes
            postings += int(rows.size)
        self._post_bytes, self._postings = total, postings
        for name in ("_seq", "_weight"):
            old: _Grow = getattr(self, name)
            kept = old.view()[keep]
            g = _Grow(old.data.dtype.type, max(1024, kept.size))
            g.data[:kept.size] = kept
            g.n = int(kept.size)
            setattr(self, name, g)
        w = self._weight.view()
        self._w_min = int(w[w > 0].min()) if bool(np.any(w > 0)) else 0
        for i, g in enumerate(self._stream_rows):
            rows = g.view()
            rows = new_row[rows[keep[rows]]]
            fresh = _Grow(_ROW, max(_MIN_CAP, rows.size))
            fresh.data[:rows.size] = rows
            fresh.n = int(rows.size)
            self._stream_rows[i] = fresh
        self._dead.clear()

    def _rows_of(self, stream: str) -> _Grow:
        sid = self._stream_id.get(stream)
        if sid is None:
            sid = self._stream_id[stream] = len(self._stream_rows)
            self._stream_rows.append(_Grow(_ROW))
        return self._stream_rows[sid]

    def rebuild(self, rows: Iterable[IndexRow]) -> None:
        """Replace the contents with `rows` (seq order), in bulk.

        One stable counting pass over all (cell, row) pairs instead of per-row appends, so a map of
        10^6 observations is rebuilt in seconds, not minutes. On any error the index is left as it was.

        Raises:
            IndexFull: more rows than `max_observations`.
            ValueError: seqs not increasing, or bad cells.
        """
        seqs: list[int] = []
        cells: list[np.ndarray] = []
        streams: list[str] = []
        for r in rows:
            if len(seqs) >= self.max_observations:
                raise IndexFull(self.max_observations)
            seqs.append(int(r.seq))
            cells.append(np.asarray(r.winner_cells))
            streams.append(r.stream)
        n = len(seqs)
        seq_arr = np.asarray(seqs, dtype=np.int64)
        if n > 1 and not bool(np.all(seq_arr[1:] > seq_arr[:-1])):
            raise ValueError("rows must come in strictly increasing seq order")
        lens = np.fromiter((c.size for c in cells), dtype=np.int64, count=n)
        flat = np.concatenate(cells).astype(np.int64) if n else np.zeros(0, np.int64)
        # Validate every row at once: in range, and increasing inside each row (row starts exempt).
        if flat.size:
            if flat.min() < 0 or flat.max() >= self.n_cells:
                raise ValueError(f"cells out of range [0, {self.n_cells})")
            inside = np.ones(flat.size - 1, dtype=bool)
            starts = np.cumsum(lens)[:-1]
            inside[starts[(starts > 0) & (starts < flat.size)] - 1] = False
            if not bool(np.all((flat[1:] > flat[:-1]) | ~inside)):
                raise ValueError("each row's cells must be sorted and distinct")
        row_of = np.repeat(np.arange(n, dtype=_ROW), lens)
        # Group pairs by cell. A uint16 key lets NumPy's stable sort use radix sort (linear time).
        key = flat.astype(np.uint16) if self.n_cells <= 1 << 16 else flat
        order = np.argsort(key, kind="stable")
        grouped = row_of[order]
        counts = np.bincount(flat, minlength=self.n_cells)
        bounds = np.concatenate([[0], np.cumsum(counts)])

        self._clear()
        post, plen = self._post, self._plen
        total = 0
        for cell in np.flatnonzero(counts).tolist():
            lo, hi = int(bounds[cell]), int(bounds[cell + 1])
            # Exact size plus room to grow, so the first adds after a rebuild do not all reallocate.
            arr = np.empty(max(_MIN_CAP, (hi - lo) + (hi - lo) // 4), dtype=_ROW)
            arr[: hi - lo] = grouped[lo:hi]
            post[cell] = arr
            plen[cell] = hi - lo
            total += arr.nbytes
        self._post_bytes = total
        self._postings = int(flat.size)
        cap = max(1024, n)
        self._seq = _Grow(np.int64, cap)
        self._seq.data[:n] = seq_arr
        self._seq.n = n
        self._weight = _Grow(np.int32, cap)
        self._weight.data[:n] = lens
        self._weight.n = n
        self._w_min = int(lens[lens > 0].min()) if bool(np.any(lens > 0)) else 0
        for row, stream in enumerate(streams):
            self._rows_of(stream).append(row)

    # ------------------------------------------------------------------ queries

    def rank(self, cells: np.ndarray | Sequence[int], top_k: int, *, exclude_seqs: Iterable[int] = (),
             exclude_own: tuple[str, int] | None = None, min_overlap: int = 1,
             weights: np.ndarray | None = None) -> list[Match]:
        """The `top_k` stored observations most similar to `cells`, best first.

        Args:
            cells: the query's winner cells (distinct; order free).
            top_k: how many to return (0 → none; more than available → all that qualify).
            exclude_seqs: seqs never returned.
            exclude_own: (stream, seq): that stream's observations from seq on are skipped (the rows of its
                own trail it has not left, docs/design/science.md §11.6); O(their number) per query.
            min_overlap: rows sharing fewer cells are not candidates. The default 1 returns only rows
                that share something with the query; 0 ranks every row (zero-overlap rows last).
            weights: (len(cells),) each query cell's weight in [0, 1], in the order of `cells` (a stream's
                condition, docs/design/science.md §11.10); None: every cell 1.

        Returns:
            `Match(seq, overlap, score)` tuples, score = Dice = 2·overlap / (|query| + |stored|) or, with
            `weights`, the weighted Dice of `_top_k_touched` (Dice when every weight is 1, in [0, 1], 1
            only for a stored row equal to the query); sorted by score descending, ties to the lower
            (older) seq. `overlap` counts cells.
        """
        n = self._seq.n
        if top_k <= 0 or n == 0:
            return []
        q, first = np.unique(np.asarray(cells, dtype=np.int64), return_index=True)
        if q.size and (q[0] < 0 or q[-1] >= self.n_cells):
            raise ValueError(f"cells must lie in [0, {self.n_cells})")
        w = None
        if weights is not None:
            w = np.asarray(weights, dtype=np.float64)
            if w.shape != (np.asarray(cells).size,) or not np.all((w >= 0.0) & (w <= 1.0)):
                raise ValueError("weights must be one value in [0, 1] per query cell")
            w = w[first]
            if not w.any():
                w = None  # nothing to rank by: plain Dice
        post, plen = self._post, self._plen
        parts = [post[c][: plen[c]] for c in q.tolist() if plen[c]]
        if min_overlap >= 1:
            # The usual case: only touched rows can qualify, so the compiled pass never looks at the others.
            if not parts:
                return []
            flat = np.concatenate(parts) if len(parts) > 1 else parts[0]
            excluded = self._excluded_rows(exclude_seqs, exclude_own)
            cap = self._seq.data.size  # scratch grows with the row arrays, not row by row
            with self._scratch_lock:
                if self._touched.size < n:
                    self._touched = np.zeros(cap, dtype=np.int32)
                if q.size <= 255:
                    if self._counts8.size < n:
                        self._counts8 = np.zeros(cap, dtype=np.uint8)
                    counts: np.ndarray = self._counts8
                else:
                    if self._counts32.size < n:
                        self._counts32 = np.zeros(cap, dtype=np.int32)
                    counts = self._counts32
                if w is None:
                    flat_w, w_total, w_max = _NO_WEIGHTS, 0.0, 0.0
                else:
                    if self._acc.size < n:
                        self._acc = np.zeros(cap, dtype=np.float64)
                    flat_w = np.repeat(w[[plen[c] > 0 for c in q.tolist()]], [len(p) for p in parts])
                    w_total, w_max = float(w.sum()), float(w.max())
                rows, ovs, scores = _top_k_touched(
                    flat, flat_w, self._weight.data, int(q.size), w_total, w_max, min(int(top_k), n),
                    int(min_overlap), self._w_min, excluded, counts, self._acc, self._touched)
            seqs = self._seq.data[rows]
            return [Match(int(s), int(o), float(x)) for s, o, x in zip(seqs, ovs, scores, strict=True)]
        # min_overlap <= 0: every row not excluded is a candidate, zero-overlap rows included.
        counts = np.bincount(np.concatenate(parts), minlength=n) if parts else np.zeros(n, dtype=np.int64)
        keep = np.ones(n, dtype=bool)
        keep[self._excluded_rows(exclude_seqs, exclude_own)] = False
        cand = np.flatnonzero(keep)
        if cand.size == 0:
            return []
        ov = counts[cand]
        denom = (self._weight.data[cand] + q.size).astype(np.float64)
        # Dice is 0 when both sets are empty (models.sdr.dice's convention). Equal fractions give
        # bit-identical doubles (IEEE division is correctly rounded), so ties are exact.
        if w is not None:  # the compiled pass's expression, so both rank equal rows alike
            acc = np.zeros(n)
            for c, wc in zip(q.tolist(), w.tolist(), strict=True):
                if plen[c]:
                    acc[post[c][: plen[c]]] += wc
            total = float(w.sum())
            held = np.minimum(acc[cand], self._weight.data[cand] * (total / q.size))
            score = np.divide(2.0 * q.size / total * held, denom, out=np.zeros(cand.size), where=denom > 0)
        else:
            score = np.divide(2.0 * ov, denom, out=np.zeros(cand.size), where=denom > 0)

        return self._best(cand, ov, score, top_k)

    def rank_columns(self, columns: np.ndarray | Sequence[int], cells_per_column: int, top_k: int, *,
                     exclude_own: tuple[str, int] | None = None) -> list[Match]:
        """The `top_k` stored rows most like a frame the memory saw without context, best first
        (docs/design/science.md §11.2 step 1).

        With no previous activity every column of the frame bursts and its winner cells are the
        least-used cells of those columns: they say which columns are on, not which stored row the frame
        is, so ranked by cells it matches only rows learned the same way (other first frames). Its columns
        do say it: a stored row shares a query column where one of its winner cells lies in it (a
        predicted column's several winners count once).

        Args:
            columns: (k,) the frame's active columns (its code; distinct, order free).
            cells_per_column: the memory's cells per column (cell `c · cells_per_column + j` lies in
                column c).
            top_k, exclude_own: as `rank`.

        Returns:
            `Match(seq, overlap, score)`, overlap = the query columns the row shares, score = overlap / k
            in [0, 1] (the Dice of the two codes, which have one size in a map), 1 for a row with a winner
            in each of the frame's columns; sorted by score descending, ties to the lower (older) seq.
            Rows sharing no column are not returned. One compiled pass per column over its cells' postings,
            about rows · k² / columns entries in all, with two scratch ints a row; once a sequence.
        """
        n = self._seq.n
        if top_k <= 0 or n == 0:
            return []
        cols = np.unique(np.asarray(columns, dtype=np.int64))
        cpc = int(cells_per_column)
        if cols.size and (cols[0] < 0 or (cols[-1] + 1) * cpc > self.n_cells):
            raise ValueError(f"columns must lie in [0, {self.n_cells // max(cpc, 1)})")
        post, plen = self._post, self._plen
        mark = np.full(n, -1, dtype=np.int32)
        counts = np.zeros(n, dtype=np.int32)
        for j, col in enumerate(cols.tolist()):
            parts = [post[c][: plen[c]] for c in range(col * cpc, (col + 1) * cpc) if plen[c]]
            if parts:
                _count_column(np.concatenate(parts) if len(parts) > 1 else parts[0], j, mark, counts)
        keep = counts > 0
        keep[self._excluded_rows((), exclude_own)] = False
        cand = np.flatnonzero(keep)
        if cand.size == 0:
            return []
        ov = counts[cand].astype(np.int64)
        return self._best(cand, ov, ov / float(cols.size), top_k)

    def _best(self, cand: np.ndarray, ov: np.ndarray, score: np.ndarray, top_k: int) -> list[Match]:
        """The `top_k` best of the candidate rows `cand` (ascending, (m,)) by `score` (m,), overlaps `ov`
        (m,): score descending, ties to the lower (older) row."""
        k = min(int(top_k), cand.size)
        if k < cand.size:
            # Partition finds the k-th best score; everything strictly better is in, and the places
            # left go to the equal scores of the lowest rows (cand is ascending), i.e. the older ones.
            kth = np.partition(score, cand.size - k)[cand.size - k]
            better = np.flatnonzero(score > kth)
            equal = np.flatnonzero(score == kth)[: k - better.size]
            pick = np.sort(np.concatenate([better, equal]))
        else:
            pick = np.arange(cand.size)
        # Stable sort on -score keeps ascending row (older first) among equal scores.
        pick = pick[np.argsort(-score[pick], kind="stable")]
        seqs = self._seq.data[cand[pick]]
        return [Match(int(s), int(o), float(x)) for s, o, x in zip(seqs, ov[pick], score[pick], strict=True)]

    def _excluded_rows(self, exclude_seqs: Iterable[int], own: tuple[str, int] | None) -> np.ndarray:
        parts = [np.fromiter(self._dead, np.int64, len(self._dead))] if self._dead else []
        ex = np.fromiter((int(s) for s in exclude_seqs), dtype=np.int64)
        if ex.size:
            seqs = self._seq.view()
            pos = np.searchsorted(seqs, ex)
            hit = pos < seqs.size
            pos = pos[hit]
            parts.append(pos[seqs[pos] == ex[hit]])
        if own is not None:
            sid = self._stream_id.get(own[0])
            if sid is not None:
                rows = self._stream_rows[sid].view()  # ascending rows, so ascending seqs
                first = int(np.searchsorted(self._seq.data[rows], int(own[1])))
                parts.append(rows[first:].astype(np.int64))
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)
