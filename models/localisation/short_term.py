"""A stream's short-term memory (docs/design/science.md §11.6): the rows it made over its last
`short_term` moves, which are never loop candidates, states of its paths or rows its frames are
consolidated into.

A move is a learned frame unlike the stream's last **anchor** (the frame of its last move) by the
departure level of the own-trail rule: Dice(frame, anchor) < b + departure · (1 − b), b the frame's
background likeness. Frames alike to the anchor (a robot that stands, a slower robot's extra frames, a
plateau where nothing changes) are no moves: the rows they make stay in the memory however many there
are, so the memory spans the same stretch of route at any frame rate. Clock time, frames not learned
and frames of other streams do not age it either. A learned frame consolidated into a row it visited
(known ground) is a move like any other but makes no row.
"""

from __future__ import annotations

import numpy as np

from models.localisation.graph import NONE
from models.localisation.trail import code_dice

__all__ = ["KEPT", "SPAN", "ShortTerm"]

#: The most learned frames a stream's memory remembers, as a multiple of its moves: a robot that stays
#: in one place (its frames all alike) for longer than SPAN x `short_term` learned frames loses the rows
#: from before its stop from the memory. It bounds the memory: 8 bytes a frame (`nbytes`).
SPAN = 50
#: How many streams' memories a map keeps, the most recently learning first: twice the default
#: `CORTEXLOC_MAX_STREAMS`, so a stream evicted for another (or renamed back) finds its memory again,
#: and a map fed a new stream name every drive stays bounded (at most KEPT x `ShortTerm.nbytes`).
KEPT = 128


class ShortTerm:
    """One stream's short-term memory: a ring of its last SPAN x `moves` learned frames, each the row it
    made (or NONE) and whether it was a move, and the code of its last move (the anchor).

    Args:
        moves: how many moves it spans (`LocaliserParams.short_term`, >= 1).
    """

    def __init__(self, moves: int) -> None:
        self.moves = int(moves)
        # each learned frame: (row made + 1) * 2 + moved (row NONE: a frame that made no row); 0: empty
        self._frames = np.zeros(SPAN * self.moves, np.int64)
        self._n = 0  # frames taken in, ever (the ring's write position is _n % size)
        self._anchor: np.ndarray | None = None

    @staticmethod
    def nbytes(moves: int, code_width: int) -> int:
        """Bytes one stream's memory holds at most: the ring and an anchor of up to `code_width` bits."""
        return 8 * (SPAN * int(moves) + int(code_width))

    def step(self, row: int, code: np.ndarray, level: float) -> None:
        """One learned frame of the stream: `row` the row it made (NONE: consolidated), `code` (n,) its
        sorted code, `level` its departure level (the Dice below which it moved from the anchor)."""
        moved = self._anchor is None or code_dice(code, self._anchor) < level
        if moved:
            self._anchor = np.asarray(code)
        self._frames[self._n % self._frames.size] = (int(row) + 1) * 2 + int(moved)
        self._n += 1

    def ages(self) -> dict[int, int]:
        """Each row the memory remembers -> how many of the stream's learned frames came after it (0: its
        row was the last frame's). O(frames remembered)."""
        size = self._frames.size
        held = min(self._n, size)
        rows = self._frames[(self._n - 1 - np.arange(held)) % size] // 2 - 1  # newest first
        return {int(r): i for i, r in enumerate(rows.tolist()) if r != NONE}

    def rows(self) -> np.ndarray:
        """(m,) int64 ascending: the rows made over the last `moves` moves (the frames since the oldest
        of them, the frames alike to it included). O(frames remembered), vectorised."""
        size = self._frames.size
        held = min(self._n, size)
        idx = (self._n - 1 - np.arange(held)) % size  # newest first
        entries = self._frames[idx]
        moved = np.cumsum(entries % 2)
        upto = int(np.searchsorted(moved, self.moves)) + 1  # through the frame of the moves-th move
        rows = entries[:upto] // 2 - 1
        return np.sort(rows[rows != NONE])
