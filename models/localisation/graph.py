"""The map's learned sequence structure: each stored row's predecessor link (docs/design/science.md §11.1).

A row's predecessor is `context_prev_seq`, the row its stream learned just before it (none: -1, the
start of a traverse). Successor links are the inverse. Several traverses, loops and branches are all
just rows with links; the localiser walks them forwards (successors) or backwards (predecessors).
Each row also knows its trail: the first row of the chain of links it ends (`trail`), so "is this row on
a stream's own trail since row s" is one comparison (docs/design/science.md §11.6), and its place: rows the
map knows to show one place (a learning stream's revisit joins its new row to the place it revisited) share
a place id, the id of the place's first row (docs/design/science.md §11.8).
"""

from __future__ import annotations

import numpy as np

NONE = -1


class SequenceGraph:
    """Predecessor and successor links of the stored rows, indexed by row id (seq).

    Args:
        prev: (N,) int, prev[r] = the row learned just before row r in the same stream sequence, or
            -1. Row ids are 0..N-1; a row that is not stored has prev -1 and no successor.

    Raises:
        ValueError: a link points outside 0..N-1 or to the row itself.

    Where two rows name the same predecessor (a stream that resumed from an older row), the later row
    is the successor a forward walk takes; the earlier branch is still reached backwards. Memory is
    two int64 per row, held once per map (not per stream).
    """

    def __init__(self, prev: np.ndarray | None = None) -> None:
        prev = np.zeros(0, np.int64) if prev is None else np.asarray(prev, dtype=np.int64)
        if prev.ndim != 1:
            raise ValueError(f"prev must be 1-D, got shape {prev.shape}")
        n = prev.size
        rows = np.arange(n)
        if np.any((prev < NONE) | (prev >= n) | (prev == rows)):
            raise ValueError("prev links must be -1 or another row id in 0..N-1")
        self._prev = prev.copy()
        self._next = np.full(n, NONE, dtype=np.int64)
        linked = prev >= 0
        self._next[prev[linked]] = rows[linked]  # later rows overwrite earlier: the later branch wins
        # Pointer doubling (O(N log depth)): a chain's rows all reach its first row. A hand-made cycle has
        # no first row; its rows get one of its rows after the bounded doubling.
        head = np.where(linked, prev, rows)
        for _ in range(64):
            nxt = head[head]
            if np.array_equal(nxt, head):
                break
            head = nxt
        self._trail = head
        self._place = rows.astype(np.int64)  # each row its own place until told otherwise (`join`)
        self._members: dict[int, list[int]] = {}  # place -> its rows still held (absent: just itself)
        # Links the prev/next arrays do not hold (a branch: a row whose predecessor's successor is
        # another; a consolidated stream's move onto a row that has a predecessor): both ends, for
        # `within` (a neighbourhood is every row a few links away, whichever way; §11.8).
        self._extra: dict[int, list[int]] = {}
        for r in rows[linked]:
            if self._next[prev[r]] != r:
                self._branch(int(prev[r]), int(r))
        self._n = n

    @classmethod
    def chain(cls, n: int, start: int = 0) -> SequenceGraph:
        """One traverse of n rows learned in order (row r's predecessor is r - 1), from row `start`."""
        prev = np.arange(-1, n - 1, dtype=np.int64)
        prev[:start + 1] = NONE
        return cls(prev)

    def __len__(self) -> int:
        return self._n

    def append(self, row: int, prev: int = NONE, *, place: int = NONE, joins: bool = True) -> None:
        """Add row `row` (a new seq, >= len(self)) learned after `prev` (-1: none); amortised O(1).

        Args:
            place: the place the row shows (-1: a new place, its id the row's own).
            joins: the row continues `prev`'s trail (False: `prev` is a row its stream only visited, a
                consolidated frame, so the row starts a trail of its own, linked back to `prev`; `prev`'s
                successor changes only if it had none: the route it lies on stays whole; §11.8).
        """
        if row < self._n:
            raise ValueError(f"row {row} is already in the graph (size {self._n})")
        if prev != NONE and not 0 <= prev < self._n:
            raise ValueError(f"predecessor {prev} is not a stored row")
        if row >= self._prev.size:
            cap = max(2 * self._prev.size, row + 1, 16)
            self._prev = np.concatenate([self._prev, np.full(cap - self._prev.size, NONE, np.int64)])
            self._next = np.concatenate([self._next, np.full(cap - self._next.size, NONE, np.int64)])
            self._trail = np.concatenate([self._trail, np.full(cap - self._trail.size, NONE, np.int64)])
            self._place = np.concatenate([self._place, np.full(cap - self._place.size, NONE, np.int64)])
        self._prev[row] = prev
        self._trail[row] = self._trail[prev] if prev != NONE and joins else row
        self._place[row] = row
        if place != NONE:
            self.join(row, place)
        if prev != NONE:
            if joins or self._next[prev] == NONE:
                old = int(self._next[prev])
                self._next[prev] = row
                if old != NONE:
                    self._branch(prev, old)  # the earlier branch is still a neighbour
            else:
                self._branch(prev, row)
        self._n = row + 1

    @property
    def prev(self) -> np.ndarray:
        """(N,) int64 predecessor of each row (-1: none); a view, do not modify."""
        return self._prev[:self._n]

    @property
    def next(self) -> np.ndarray:
        """(N,) int64 successor of each row (-1: none); a view, do not modify."""
        return self._next[:self._n]

    @property
    def trail(self) -> np.ndarray:
        """(N,) int64 the first row of each row's chain of predecessor links (itself at a chain's start):
        rows learned in one unbroken sequence of a stream share it; a view, do not modify."""
        return self._trail[:self._n]

    def link(self, prev: int, row: int, successor: bool = False) -> None:
        """A stream moved from row `prev` to row `row` (a consolidated frame, §11.8): a neighbour of it
        (`within`); with `successor`, also `prev`'s successor if it had none."""
        if not (0 <= prev < self._n and 0 <= row < self._n) or prev == row:
            return
        if successor and self._next[prev] == NONE:
            self._next[prev] = row
            return
        if self._next[prev] != row and self._prev[row] != prev and row not in self._extra.get(prev, ()):
            self._branch(prev, row)

    def _branch(self, a: int, b: int) -> None:
        self._extra.setdefault(a, []).append(b)
        self._extra.setdefault(b, []).append(a)

    @property
    def place(self) -> np.ndarray:
        """(N,) int64 the place id of each row (the id of the place's first row); a view, do not modify."""
        return self._place[:self._n]

    def join(self, row: int, place: int) -> None:
        """Row `row` shows place `place` (a place id, or any row of it): O(1)."""
        place = int(self._place[place])
        if place == row:
            return
        members = self._members.get(place)
        if members is None:
            members = self._members[place] = [place]
        members.append(row)
        self._place[row] = place

    def alone(self, rows: np.ndarray) -> np.ndarray:
        """(m,) bool: each row is a place of its own that no other row joined (a row made while its stream
        did not know where it was, before anything named it, §11.8)."""
        rows = np.asarray(rows, np.int64)
        return (self._place[rows] == rows) & np.array([r not in self._members for r in rows.tolist()], bool)

    def rejoin(self, row: int, place: int) -> None:
        """Row `row`, a place of its own that no other row joined (`alone`), shows place `place` after all
        (a warm-up join, docs/design/science.md §11.8): its own place is left with no row."""
        if not self.alone(np.array([row]))[0]:
            raise ValueError(f"row {row} is not a place of its own")
        if int(self._place[place]) == row:
            return
        self._members[row] = []
        self.join(row, place)

    def members(self, place: int) -> list[int]:
        """The rows of place `place` (a place id) still held, oldest first (`drop` removes one)."""
        return list(self._members.get(place, [place]))

    def drop(self, row: int) -> None:
        """Row `row` is no longer an appearance of its place (dropped or forgotten, §11.9); its links stay,
        so paths still walk through it."""
        place = int(self._place[row])
        members = self._members.get(place)
        if members is None:
            self._members[place] = []
        elif row in members:
            members.remove(row)

    def walk(self, rows: np.ndarray, direction: np.ndarray, steps: int) -> np.ndarray:
        """Rows reached by `steps` links from `rows`, forwards (direction +1) or backwards (-1).

        Args:
            rows: (H,) int64 start rows (-1 allowed: stays -1).
            direction: (H,) int8 or int, +1 = follow successors, -1 = follow predecessors.
            steps: links to follow, >= 0.

        Returns:
            (H,) int64 rows reached; -1 where a link ran out. O(H * steps), independent of N.
        """
        out = np.asarray(rows, dtype=np.int64).copy()
        fwd = np.asarray(direction) > 0
        for _ in range(steps):
            ok = out >= 0
            nxt = np.full_like(out, NONE)
            nxt[ok & fwd] = self._next[out[ok & fwd]]
            nxt[ok & ~fwd] = self._prev[out[ok & ~fwd]]
            out = nxt
        return out

    def route(self, row: int, direction: int, steps: int) -> np.ndarray:
        """(m,) int64: `row` and the rows up to `steps` successor (direction +1) or predecessor (-1) links
        from it, in walking order, until a link runs out; branches are not taken. O(steps)."""
        out, links = [row], self._next if direction > 0 else self._prev
        for _ in range(steps):
            row = int(links[row])
            if row < 0:
                break
            out.append(row)
        return np.array(out, np.int64)

    def within(self, row: int, links: int) -> np.ndarray:
        """Sorted rows at most `links` links from `row`, along any link either way (branches included),
        `row` included: O(links) on a chain, O(rows reached) where routes branch."""
        found, frontier = {row}, [row]
        for _ in range(links):
            step = []
            for r in frontier:
                for n in (int(self._next[r]), int(self._prev[r]), *self._extra.get(r, ())):
                    if n >= 0 and n not in found:
                        found.add(n)
                        step.append(n)
            if not step:
                break
            frontier = step
        return np.array(sorted(found), dtype=np.int64)
