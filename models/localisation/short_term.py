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

from collections import deque

import numpy as np

from models.localisation.graph import NONE
from models.localisation.trail import code_dice

__all__ = ["SPAN", "ShortTerm"]

#: The most learned frames a stream's memory remembers, as a multiple of its moves: a robot that stays
#: in one place (its frames all alike) for longer than SPAN x `short_term` learned frames loses the rows
#: from before its stop from the memory (which bounds it: about 36 bytes a frame).
SPAN = 50


class ShortTerm:
    """One stream's short-term memory.

    Args:
        moves: how many moves it spans (`LocaliserParams.short_term`, >= 1).
    """

    def __init__(self, moves: int) -> None:
        self.moves = int(moves)
        # each learned frame: (row made + 1) * 2 + moved, row NONE for a frame that made no row
        self._frames: deque[int] = deque(maxlen=SPAN * self.moves)
        self._anchor: np.ndarray | None = None

    def step(self, row: int, code: np.ndarray, level: float) -> None:
        """One learned frame of the stream: `row` the row it made (NONE: consolidated), `code` (n,) its
        sorted code, `level` its departure level (the Dice below which it moved from the anchor)."""
        moved = self._anchor is None or code_dice(code, self._anchor) < level
        if moved:
            self._anchor = np.asarray(code)
        self._frames.append((int(row) + 1) * 2 + int(moved))

    def rows(self) -> np.ndarray:
        """(m,) int64 ascending: the rows made over the last `moves` moves (the frames since the oldest
        of them, the frames alike to it included)."""
        out: list[int] = []
        seen = 0
        for entry in reversed(self._frames):
            row, moved = entry // 2 - 1, entry % 2
            if row != NONE:
                out.append(row)
            seen += moved
            if seen >= self.moves:
                break
        return np.asarray(out[::-1], np.int64)
