"""A stream's condition: the code bits its recent frames share count less (docs/design/science.md §11.10).

Why: a frame's code carries what it shows (the place) and the conditions it was seen in (season, light,
weather, the camera). Every frame of one condition shares the second part. A learning stream driving a
route it learned in summer, now in winter, stores a winter row per frame; from then on its winter frames
share more bits with its own earlier winter rows of other places than with the summer rows of the place
they show, and it names those (docs/results.md §10.6: 262 of 894 answers on held-out Nordland). The
stream's recent frames say what its condition is: a bit on in most of them says "winter", not "here".

The rule: a stream keeps how often each bit (sLSBH column) was on in its recent frames (`Condition`: an
exponential moving average from zero with weight 1 / `frames`, so a few frames say little; a frame
that repeats the last one taken in is not taken in, `REPEAT`), and the
index weighs each query cell by `max(0, 1 - discount * rate)` of its column (`weights`): a bit on in
half of the recent frames counts nothing at the default discount 2. This is an inverse document
frequency over the stream's own recent past, the binary counterpart of subtracting a stream's running
mean (`models.frontend.adaptation`), but it changes neither the code the memory learns nor what the
own-trail rule (§11.6) or the consolidation (§11.8) compare: only how the index ranks.
"""

from __future__ import annotations

import numpy as np

__all__ = ["REPEAT", "Condition"]

#: A frame whose code shares at least this (condition-weighted) Dice with the last frame taken in is the
#: same view again (a stopped robot) and is not taken in: the condition is what frames of different
#: places share, and 40 frames of one stop would otherwise make that place's own bits "the condition"
#: and discount them in whatever comes next (`Condition.repeats`).
REPEAT = 0.9


class Condition:
    """How often each code bit was on in one stream's recent frames (§11.10).

    Args:
        width: the code's bit space (the memory's columns, 2k for sLSBH).
        frames: the time constant in frames (>= 1): an exponential moving average from zero with
            weight 1 / `frames` for the newest (a stream's first frames, one place or a few, are not yet
            a condition: starting at the mean of the first ones discounted their own bits at once).

    Attributes:
        rates: (width,) float64, each bit's rate in [0, 1]. seen: codes taken in so far.
        last: the last code taken in (sorted indices; empty before the first).
    """

    def __init__(self, width: int, frames: int, rates: np.ndarray | None = None, seen: int = 0,
                 last: np.ndarray | None = None) -> None:
        if frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames}")
        self.frames = int(frames)
        self.rates = np.zeros(int(width)) if rates is None else np.array(rates, dtype=np.float64)
        self.seen = int(seen)
        self.last = np.zeros(0, np.int64) if last is None else np.asarray(last, np.int64)

    def add(self, code: np.ndarray, discount: float) -> bool:
        """Take in one frame's code (sorted indices of its on bits, distinct) unless it shows the same view
        as the last one taken in (`repeats`); O(width). Returns whether it was taken in."""
        code = np.asarray(code, np.int64)
        if self.seen and self.repeats(code, discount):
            return False
        self.seen += 1
        a = 1.0 / self.frames
        self.rates *= 1.0 - a
        self.rates[code] += a
        self.last = code.copy()
        return True

    def repeats(self, code: np.ndarray, discount: float) -> bool:
        """Whether `code` shows the same view as the last code taken in: their Dice over the bits the
        condition leaves weight to (each bit at `max(0, 1 - discount * rate)`) is at least `REPEAT`.
        Plain Dice would not do: winter frames of different places share most of their bits, the
        condition's, and would all look like repeats of one another. A code of nothing but the condition
        is no repeat."""
        total = float(self._weight(code, discount).sum() + self._weight(self.last, discount).sum())
        if total <= 0.0:
            return False
        shared = np.intersect1d(code, self.last, assume_unique=True)
        return 2.0 * float(self._weight(shared, discount).sum()) / total >= REPEAT

    def _weight(self, columns: np.ndarray, discount: float) -> np.ndarray:
        """The one rule of a bit's weight: max(0, 1 - discount * its rate), for each of `columns`."""
        return np.clip(1.0 - discount * self.rates[columns], 0.0, 1.0)

    def weights(self, cells: np.ndarray, cells_per_column: int, discount: float) -> np.ndarray | None:
        """(q,) float64 weight in [0, 1] of each query cell: `max(0, 1 - discount * rate)` of its column
        (cell // cells_per_column); None (every cell counts 1: plain Dice) before any frame was taken in,
        without a discount, or when every cell would count 0 (nothing left to rank by)."""
        if self.seen == 0 or discount <= 0.0:
            return None
        w = self._weight(np.asarray(cells, np.int64) // int(cells_per_column), discount)
        return w if w.any() else None

    def state(self) -> np.ndarray:
        """(2 + width + |last|,) float64: frames seen, the width, the rates, the last code taken in (for
        a snapshot; `from_state` reads it)."""
        return np.concatenate([[float(self.seen), float(self.rates.size)], self.rates, self.last])

    @classmethod
    def from_state(cls, frames: int, state: np.ndarray) -> Condition:
        """Raises ValueError for a state that is not what `state` writes (finite, rates in [0, 1], the
        last code's bits within the width)."""
        state = np.asarray(state, np.float64)
        if state.ndim != 1 or state.size < 2 or not np.all(np.isfinite(state)):
            raise ValueError("a stream's condition state must be a finite 1-D array")
        width = int(state[1])
        if not 0 <= width <= state.size - 2:
            raise ValueError("a stream's condition state is shorter than its width")
        rates, last = state[2:2 + width], state[2 + width:].astype(np.int64)
        if rates.size and (rates.min() < 0.0 or rates.max() > 1.0 + 1e-9):
            raise ValueError("a stream's condition rates must lie in [0, 1]")
        if last.size and (last.min() < 0 or last.max() >= width):
            raise ValueError("a stream's condition's last code lies outside its width")
        return cls(width, frames, np.clip(rates, 0.0, 1.0), int(state[0]), last)
