"""A trail's short-term memory (docs/design/science.md §11.6): the rows its streams made over their last
`short_term` moves, or their last `short_term_metres` of path where frames carry poses; those rows are
never loop candidates, states of its paths or rows its frames are consolidated into.

A **move** is judged by each stream against its last move's frame (its `Anchor`):
- with poses (`Motion.pose`) on the frame and on the anchor, a pose at least `move_metres` from the
  anchor's; it covers its distance of the memory's `short_term_metres`. A step from the stream's last
  posed frame longer than `max_speed` x Δt (Δt from the stamps) is a **reset** (a relocalisation, an
  odometry jump, a teleport, a bag played faster than real time): that step is judged by appearance
  (below), and the memory goes on from the new pose. With
  Δt <= 0 (a bag replayed in a loop, a clock stepped back) a step of `move_metres` or more is a reset;
  without stamps there is no speed to check and a step is distance;
- otherwise by appearance: Dice(frame, anchor) < b + departure · (1 − b), b the frame's background
  likeness; it covers 1 / `short_term` of the memory.
Frames that are no move (a robot that stands, a slower robot's extra frames, a plateau) cover nothing: the
rows they make stay in the memory however many there are. Clock time, frames not learned and frames of
other trails do not age it. A learned frame consolidated into a row it visited (known ground) is a move
like any other but makes no row.

Streams that name one trail (`Motion.trail`: two cameras of one robot, a renamed node) share its memory:
it spans back until one of them has covered the whole of it, so two cameras driving together hold the
rows of the last D metres (not D/2), and a renamed node holds the old name's last D metres until the new
one has driven D itself.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import NamedTuple

import numpy as np

from models.localisation.graph import NONE
from models.localisation.motion import Motion
from models.localisation.options import LocaliserOptions
from models.localisation.trail import code_dice

__all__ = ["KEPT", "SLOTS", "SPAN", "Anchor", "ShortTerm", "ring_moves"]

#: The most learned frames a trail's memory remembers, as a multiple of its moves (`ring_moves`): a robot
#: that stays in one place (its frames all alike, its pose within `move_metres`) for longer than SPAN x
#: that many learned frames loses the rows from before its stop from the memory. It bounds the memory:
#: 18 bytes a frame (`nbytes`).
SPAN = 50
#: How many streams' anchors and trails' memories a map keeps, the most recently learning first: twice
#: the default `CORTEXLOC_MAX_STREAMS`, so a stream evicted for another (or renamed back) finds its
#: memory again, and a map fed a new stream name every drive stays bounded (at most KEPT x
#: `ShortTerm.nbytes`).
KEPT = 128
#: Streams one trail tells apart (each covers the memory on its own); a further one takes the least
#: recently learning one's slot, and that one's frames in the ring belong to no stream from then on: they
#: stay in the memory until the others cover it, and they are never the new stream's (its look-back for
#: warm-up joins, `ShortTerm.ages`, counts its own frames only).
SLOTS = 8
#: The slot of a frame whose stream left the trail's slots (`SLOTS`).
_UNOWNED = -1
#: A span below 1 by less than this is the whole memory (20 x 1/20 sums to 0.9999999999999999).
_EPS = 1e-9


def ring_moves(conf: LocaliserOptions) -> int:
    """How many moves a memory's ring is sized for: `short_term`, or the most moves of `move_metres`
    that `short_term_metres` holds where more (at most 1,000, `short_term`'s bound); 0: no memory."""
    moves = int(conf.short_term)
    if not moves:
        return 0
    metres, step = float(conf.short_term_metres), float(conf.move_metres)
    return max(moves, min(1000, math.ceil(metres / step))) if metres > 0 else moves


class View(NamedTuple):
    """A posed frame's view: its code (n,) sorted and its pose (x, y) in metres."""

    code: np.ndarray
    pose: tuple[float, float]


class Anchor:
    """One stream's last move (its code and pose) and its last posed learned frame (pose and stamp);
    `stood`: whether the poses of the frame `move` judged last said it stood (no move within
    `move_metres` of the last move's pose; never a reset's, whose pose says nothing of how far it went)."""

    def __init__(self) -> None:
        self.code: np.ndarray | None = None
        self.pose: tuple[float, float] | None = None
        self.last: tuple[tuple[float, float], float | None] | None = None
        self.stood = False

    def move(self, code: np.ndarray, level: float, motion: Motion, conf: LocaliserOptions) -> float | None:
        """The share of the memory this learned frame covers, as a move (0 for a reset), or None when it
        is no move. `code` (n,) sorted; `level` its departure level (the Dice below which it moved by
        appearance); `conf` the localiser options (`short_term`, `short_term_metres`, `move_metres`,
        `max_speed`)."""
        metres = float(conf.short_term_metres)
        pose = motion.pose if metres > 0 else None
        reset, self.stood = False, False
        if pose is not None:
            if self.last is not None:
                (lx, ly), stamp = self.last
                step = math.hypot(pose[0] - lx, pose[1] - ly)
                dt = None if stamp is None or motion.stamp is None else motion.stamp - stamp
                if dt is not None and dt > 0:
                    reset = step > float(conf.max_speed) * dt
                elif dt is not None:  # no time to judge a speed by: a move's worth of step is a jump
                    reset = step >= float(conf.move_metres)
            self.last = (pose, motion.stamp)
        if reset:
            # The pose cannot say how far it went: appearance does, and the memory goes on from the new
            # pose. (A reset that covered nothing would leave a robot whose every step reads as one, a
            # bag played faster than `max_speed` allows, a memory that never ages: no loop ever closes.)
            self.pose = pose
            if self.code is not None and code_dice(code, self.code) >= level:
                return None
            self.code = np.asarray(code)
            return 1.0 / int(conf.short_term)
        if pose is not None and self.pose is not None:
            gone = math.hypot(pose[0] - self.pose[0], pose[1] - self.pose[1])
            if gone < float(conf.move_metres):
                self.stood = True
                return None
            self.code, self.pose = np.asarray(code), pose
            return gone / metres
        # no pose on the frame or on its anchor: by appearance
        if self.code is not None and code_dice(code, self.code) >= level:
            return None
        self.code, self.pose = np.asarray(code), pose
        return 1.0 / int(conf.short_term)


class ShortTerm:
    """One trail's short-term memory: a ring of its streams' last SPAN x `moves` learned frames, each the
    row it made (or NONE), the share of the memory it covered (0: no move), whether its poses said it
    stood still (no move by `Anchor.move` where the frame and its stream's last move carry poses: the
    frames a stream's paths need not keep pace with, `PlaceMap.moves`) and its stream's slot.

    Args:
        moves: the ring's size in moves (`ring_moves`, >= 1).
    """

    def __init__(self, moves: int) -> None:
        size = SPAN * int(moves)
        self._rows = np.full(size, NONE, np.int64)
        self._span = np.zeros(size, np.float64)
        self._still = np.zeros(size, bool)
        self._slot = np.zeros(size, np.int8)
        self._n = 0  # frames taken in, ever (the ring's write position is _n % size)
        self._slots: OrderedDict[str, int] = OrderedDict()  # stream -> slot, least recently learning first

    @staticmethod
    def nbytes(moves: int, code_width: int) -> int:
        """Bytes one stream's memory holds at most: the ring (18 bytes a frame) and its stream's anchor,
        a code of up to `code_width` bits."""
        return 18 * SPAN * int(moves) + 8 * int(code_width)

    def add(self, row: int, span: float | None, stream: str = "", still: bool = False) -> None:
        """One learned frame of `stream`: `row` the row it made (NONE: consolidated), `span` the share of
        the memory it covered as a move (`Anchor.move`; None: no move); `still`: its poses said it stood."""
        slot = self._slots.get(stream)
        if slot is None:
            if len(self._slots) < SLOTS:
                slot = len(self._slots)
            else:
                slot = self._slots.popitem(last=False)[1]
                self._slot[self._slot == slot] = _UNOWNED  # the evicted stream's frames: no one's
            self._slots[stream] = slot
        self._slots.move_to_end(stream)
        i = self._n % self._rows.size
        self._rows[i], self._span[i], self._slot[i] = int(row), 0.0 if span is None else span, slot
        self._still[i] = bool(still)
        self._n += 1

    def ages(self, stream: str = "") -> dict[int, int]:
        """Each row `stream` made that the memory remembers -> how many of that stream's learned frames
        came after it (0: its row was the stream's last frame's), newest first; a trail's other streams'
        frames do not count. O(frames remembered)."""
        rows = self._rows[self._frames_of(stream)]
        return {int(r): i for i, r in enumerate(rows.tolist()) if r != NONE}

    def moves_after(self, stream: str = "") -> dict[int, int]:
        """As `ages`, counting only the frames after each row that were moves for its stream's paths
        (not `still`): how many rows a path that kept pace with it advanced since. O(frames remembered)."""
        idx = self._frames_of(stream)
        moved = (~self._still[idx]).astype(np.int64)
        newer = np.cumsum(moved) - moved  # the moves among the frames newer than each
        return {int(r): int(k) for r, k in zip(self._rows[idx].tolist(), newer.tolist(), strict=True)
                if r != NONE}

    def _frames_of(self, stream: str) -> np.ndarray:
        """(m,) int64 the ring positions of `stream`'s frames it remembers, newest first (none: unknown)."""
        slot = self._slots.get(stream)
        if slot is None:
            return np.zeros(0, np.int64)
        size = self._rows.size
        idx = (self._n - 1 - np.arange(min(self._n, size))) % size  # newest first
        return idx[self._slot[idx] == slot]

    def rows(self) -> np.ndarray:
        """(m,) int64 ascending: the rows made since one of the trail's streams last covered the whole
        memory (the frames since its oldest move, the frames alike to it included). O(frames
        remembered · streams), vectorised."""
        size = self._rows.size
        held = min(self._n, size)
        idx = (self._n - 1 - np.arange(held)) % size  # newest first
        upto = held
        for slot in set(self._slots.values()):
            covered = np.cumsum(np.where(self._slot[idx] == slot, self._span[idx], 0.0))
            upto = min(upto, int(np.searchsorted(covered, 1.0 - _EPS)) + 1)  # through the covering move
        rows = self._rows[idx[:upto]]
        return np.sort(rows[rows != NONE])
