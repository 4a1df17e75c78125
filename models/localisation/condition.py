"""A stream's condition: the code bits its recent frames share count less (docs/design/science.md §11.10).

Why: a frame's code carries what it shows (the place) and the conditions it was seen in (season, light,
weather, the camera). Every frame of one condition shares the second part. A learning stream driving a
route it learned in summer, now in winter, stores a winter row per frame; from then on its winter frames
share more bits with its own earlier winter rows of other places than with the summer rows of the place
they show, and it names those (docs/results.md §10.6: 262 of 894 answers on held-out Nordland). The
stream's recent frames say what its condition is: a bit on in most of them says "winter", not "here".

The rule: a stream keeps how often each bit (sLSBH column) was on in its recent frames (`Condition`: the
mean of its first `frames` codes, then an exponential moving average with weight 1 / `frames`), and the
index weighs each query cell by `max(0, 1 - discount * rate)` of its column (`weights`): a bit on in
half of the recent frames counts nothing at the default discount 2. This is an inverse document
frequency over the stream's own recent past, the binary counterpart of subtracting a stream's running
mean (`models.frontend.adaptation`), but it changes neither the code the memory learns nor what the
own-trail rule (§11.6) or the consolidation (§11.8) compare: only how the index ranks.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Condition"]


class Condition:
    """How often each code bit was on in one stream's recent frames (§11.10).

    Args:
        width: the code's bit space (the memory's columns, 2k for sLSBH).
        frames: the time constant in frames (>= 1): the mean of the first `frames` codes, then an
            exponential moving average with weight 1 / `frames` for the newest.

    Attributes:
        rates: (width,) float64, each bit's rate in [0, 1]. seen: codes taken in so far.
    """

    def __init__(self, width: int, frames: int, rates: np.ndarray | None = None, seen: int = 0) -> None:
        if frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames}")
        self.frames = int(frames)
        self.rates = np.zeros(int(width)) if rates is None else np.array(rates, dtype=np.float64)
        self.seen = int(seen)

    def add(self, code: np.ndarray) -> None:
        """Take in one frame's code (indices of its on bits, distinct): O(width)."""
        self.seen += 1
        a = 1.0 / min(self.seen, self.frames)
        self.rates *= 1.0 - a
        self.rates[np.asarray(code, np.int64)] += a

    def weights(self, cells: np.ndarray, cells_per_column: int, discount: float) -> np.ndarray | None:
        """(q,) float64 weight in [0, 1] of each query cell: `max(0, 1 - discount * rate)` of its column
        (cell // cells_per_column); None (every cell counts 1: plain Dice) before any frame was taken in,
        without a discount, or when every cell would count 0 (nothing left to rank by)."""
        if self.seen == 0 or discount <= 0.0:
            return None
        columns = np.asarray(cells, np.int64) // int(cells_per_column)
        w = np.clip(1.0 - discount * self.rates[columns], 0.0, 1.0)
        return w if w.any() else None

    def state(self) -> np.ndarray:
        """(1 + width,) float64: frames seen, then the rates (for a snapshot; `from_state` reads it)."""
        return np.concatenate([[float(self.seen)], self.rates])

    @classmethod
    def from_state(cls, frames: int, state: np.ndarray) -> Condition:
        """Raises ValueError for a state that is not 1 + width finite values with rates in [0, 1]."""
        state = np.asarray(state, np.float64)
        if state.ndim != 1 or state.size < 1 or not np.all(np.isfinite(state)):
            raise ValueError("a stream's condition state must be a finite 1-D array")
        rates = state[1:]
        if rates.size and (rates.min() < 0.0 or rates.max() > 1.0 + 1e-9):
            raise ValueError("a stream's condition rates must lie in [0, 1]")
        return cls(rates.size, frames, np.clip(rates, 0.0, 1.0), int(state[0]))
