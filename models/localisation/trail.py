"""A stream's own trail: which of its own stored rows it has left (docs/design/science.md §11.6).

A learning stream stores a row per frame, so its own last rows are always its best candidates: a stream
that continues along its trail, or stands still, would "revisit" the frame it stored a moment ago. The
rule: the stream's own rows it has not left are no answer. It has left row r once a frame since r was
unlike r: its code is nearer the map's background likeness than to r's code (`departure`). The
rows not left are always a tail of the current trail (from `LocaliserState.here` to the last stored
row), so they are one range on one chain of links (`OwnTrail`). A path of the filter that follows the
trail as the stream lays it is no revisit either (`OwnTrail.laid_behind`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import NamedTuple, Protocol

import numpy as np

from models.localisation.graph import NONE, SequenceGraph

__all__ = ["UNKNOWN", "CodeStats", "OwnTrail", "above_background", "code_dice", "own_trail"]

#: `LocaliserState.here` of a state saved before the own-trail rule: the stream's whole current trail
#: counts as not left until a frame unlike it is seen (§11.6).
UNKNOWN = -2
#: `OwnTrail.trail` of a stream with no current trail, only its short-term memory (§11.6).
NO_TRAIL = -3


class TrailState(Protocol):
    """What the rule keeps in a stream's state (`LocaliserState.here` and its code cache)."""

    here: int
    here_code: np.ndarray | None


class OwnTrail(NamedTuple):
    """The rows of a stream's own current trail that are its own: the chain of links from `first` to
    `last` (§11.6). They are neither candidates nor states of the stream's filter; those from `here` on
    (the rows it has not left) are not its frame-level matches either.

    Attributes:
        first: `margin` links before `here` (the localiser's rival window). here: the oldest row the
        stream has not left (`LocaliserState.here`). last: the stream's last stored row.
        trail: `SequenceGraph.trail` of `last`, the chain they lie on.
        code: (n,) sorted int, the frame's code; code_of: a stored row's code in the same form (None:
            not given: no row is then more like the frame than where it just was).
        window: how many of the trail's last rows are where the stream just was (`margin` + 1).
        short_term: (m,) ascending, the rows of the stream's short-term memory (§11.6).
        beyond: rows (H,) -> (H,) bool, those its odometry says it cannot be back at (§11.12;
            `RowOdometry.beyond`); None: no word from odometry.
        others: the chains (`SequenceGraph.trail` ids) its robot's other cameras are laying, streams
            that name the same trail (`PlaceMap.laid_by_others`, §11.6): the robot's trail as much as
            `trail` is, for the mirror rule (`lays`, §11.13).
    """

    first: int
    here: int
    last: int
    trail: int
    code: np.ndarray | None = None
    code_of: Callable[[int], np.ndarray] | None = None
    window: int = 1
    short_term: np.ndarray = np.zeros(0, np.int64)
    beyond: Callable[[np.ndarray], np.ndarray] | None = None
    others: frozenset[int] = frozenset()

    @classmethod
    def short_term_only(cls, rows: np.ndarray) -> OwnTrail:
        """A stream with no current trail of its own (a new sequence, or travelling on rows it visited)
        whose short-term memory still holds the rows `rows` it made (§11.6)."""
        return cls(first=1, here=0, last=0, trail=NO_TRAIL, short_term=np.asarray(rows, np.int64))

    @property
    def has_trail(self) -> bool:
        """Whether the stream has a current trail (else only its short-term memory is its own)."""
        return self.trail != NO_TRAIL

    def with_short_term(self, rows: np.ndarray) -> OwnTrail:
        """This trail with the stream's short-term memory `rows` (ascending seqs)."""
        return self._replace(short_term=np.asarray(rows, np.int64))

    def born(self, graph: SequenceGraph, rows: np.ndarray, now: int, margin: int) -> np.ndarray:
        """(H,) `born` of paths that start now on `rows` (H,), `now` the map's row count: the oldest row of
        the stream's short-term memory for a path that starts on its trail within `margin` links, or a
        quarter of the memory's rows where more, behind that row (just behind the memory: where an echo
        of it starts, §11.6), so `laid_behind` follows it over the rows it walks onto; `now` for every
        other. The quarter: the memory is 20 moves and `margin` 5 links at one row a move; a robot that
        makes 10 rows a move lays its echo 10 times as many rows back."""
        rows = np.asarray(rows, np.int64)
        out = np.full(rows.size, int(now), np.int64)
        if not self.short_term.size or not self.has_trail or not rows.size:
            return out
        oldest = int(self.short_term[0])
        near = (rows < oldest) & (graph.trail[rows] == self.trail)
        if near.any():
            behind, row = set(), oldest
            for _ in range(max(margin, self.short_term.size // 4)):  # the rows just before the oldest
                row = int(graph.prev[row])
                if row < 0 or graph.trail[row] != self.trail:
                    break
                behind.add(row)
            near &= np.isin(rows, np.fromiter(behind, np.int64, len(behind)))
            out[near] = oldest
        return out

    def holds(self, graph: SequenceGraph, rows: np.ndarray) -> np.ndarray:
        """(H,) bool: which of `rows` (H,) are the stream's own: on this trail between `first` and `last`
        (a stream's rows on one trail are learned in seq order, so a range test), in its short-term
        memory, or where its odometry says it cannot be (`beyond`). O(H) (+ O(H log m) for the memory)."""
        rows = np.asarray(rows, np.int64)
        ok = (rows >= self.first) & (rows <= self.last)
        ok[ok] = graph.trail[rows[ok]] == self.trail
        if self.short_term.size:
            ok |= np.isin(rows, self.short_term)
        if self.beyond is not None and rows.size:
            ok |= self.beyond(rows)
        return ok

    def laid_behind(self, graph: SequenceGraph, rows: np.ndarray, began: np.ndarray) -> np.ndarray:
        """(H,) bool: which paths, now at `rows` (H,; none in `holds`), follow the trail the stream laid
        while they were followed (§11.6): the row is on this trail, was stored after the path began
        (`began`, (H,): the map's row count then), and the frame is no more like it than like where the
        stream just was (its highest Dice with the trail's last `window` rows). Such a path is an echo
        of where the stream just was (frames along a route stay faintly alike), not a place it came back
        to; a loop driven again looks more like its last lap than like the frames just before, and goes
        on. O(H); only where such a path exists, `window` + one Dice per distinct row of them (each a
        `code_of` read)."""
        rows = np.asarray(rows, np.int64)
        if not self.has_trail:
            return np.zeros(rows.size, bool)
        # its own chain only: ending echoes along its other cameras' chains too took rivals from the beam
        # and let an echo of its own through (the stress suite's `cameras` case, §11.6)
        laid = (graph.trail[rows] == self.trail) & (rows >= np.asarray(began, np.int64))
        if laid.any():
            laid[laid] = ~self.shows(graph, rows[laid])
        return laid

    def lays(self, graph: SequenceGraph, rows: np.ndarray) -> np.ndarray:
        """(H,) bool: which of `rows` (H,) lie on a chain its robot is laying: the stream's current trail
        or one of its other cameras' (`others`, §11.6). O(H)."""
        on = graph.trail[np.asarray(rows, np.int64)]
        return (on == self.trail) | (np.isin(on, tuple(self.others)) if self.others else False)

    def shows(self, graph: SequenceGraph, rows: np.ndarray) -> np.ndarray:
        """(H,) bool: whether the frame is at least as like each of `rows` (H,) as like where the stream
        just was (its highest Dice with the trail's last `window` rows and its short-term memory's): a
        place it came back to, not an echo of where it just was (§11.6). All False where the frame's code
        or `code_of` is not given (no row is then more like the frame). One Dice per distinct row, then
        one per recent row until one is more like the frame than every row asked of (each a `code_of`
        read): at most `window` + the memory's rows."""
        rows = np.asarray(rows, np.int64)
        if self.code is None or self.code_of is None or not rows.size:
            return np.zeros(rows.size, bool)
        unique, inverse = np.unique(rows, return_inverse=True)
        dice = np.array([code_dice(self.code, np.asarray(self.code_of(int(r)))) for r in unique])
        top = float(dice.max())
        recent, row = 0.0, self.last
        for _ in range(self.window):
            if recent > top or row < 0 or graph.trail[row] != self.trail:
                break
            recent = max(recent, code_dice(self.code, np.asarray(self.code_of(row))))
            row = int(graph.prev[row])
        for row in self.short_term:  # where it just was includes its short-term memory
            if recent > top:
                break  # (every row asked of is already less like the frame)
            recent = max(recent, code_dice(self.code, np.asarray(self.code_of(int(row)))))
        return (dice >= recent)[inverse]


def above_background(background: float, share: float) -> float:
    """The one rule of a level read above the background likeness (§11.6, §11.8): the Dice a `share` in
    [0, 1] of the way from `background` (`CodeStats.background`, what unrelated codes share) to 1. The
    departure level (a frame left a row, a move by appearance) and the consolidation level read it."""
    return background + share * (1.0 - background)


def code_dice(a: np.ndarray, b: np.ndarray) -> float:
    """Dice of two sorted, duplicate-free codes (index arrays): 2 |a ∩ b| / (|a| + |b|); 0 for two empty."""
    n = a.size + b.size
    return 2.0 * np.intersect1d(a, b, assume_unique=True).size / n if n else 0.0


class CodeStats:
    """How often each bit is on in a map's stored frame codes: the background likeness of a code
    (`background`), what a frame shares with a stored frame of another place on average. Codes of a
    weak or untrained backbone share a large common part (Dice 0.6 between unrelated places), those of a
    good one little (§11.6); the departure level is read above it. One int64 per bit. A map keeps two
    (`PlaceMap`): every stored row's, which consolidation reads (§11.8), and one code a move of its maker,
    which the departure level reads: a standing robot's copies would otherwise raise its own place's
    background, and its departure level, until they read as moves (§11.6).

    Args:
        width: the code's bit space (2k for sLSBH codes).
    """

    def __init__(self, width: int) -> None:
        self.counts = np.zeros(int(width), np.int64)
        self.n = 0
        self.bits = 0

    def add(self, code: np.ndarray) -> None:
        """One stored code (index array)."""
        self.counts[np.asarray(code, np.int64)] += 1
        self.n += 1
        self.bits += int(np.asarray(code).size)

    def rebuild(self, codes: Iterable[np.ndarray]) -> None:
        self.counts[:] = 0
        self.n = self.bits = 0
        for c in codes:
            self.add(c)

    def background(self, code: np.ndarray) -> float:
        """Expected Dice of `code` with a stored code drawn at random: sum of its bits' frequencies over
        the mean of the two sizes; 0 before anything is stored, and for an empty code among empty ones
        (as `code_dice` of two empty codes)."""
        code = np.asarray(code, np.int64)
        sizes = code.size + self.bits / self.n if self.n else 0.0
        if not sizes:
            return 0.0
        return float(2.0 * self.counts[code].sum() / self.n / sizes)

    def level(self, code: np.ndarray, share: float) -> float:
        """The Dice `share` of the way above `code`'s background likeness (`above_background`)."""
        return above_background(self.background(code), share)


def own_trail(state: TrailState, graph: SequenceGraph, last: int | None, code: np.ndarray,
              code_of: Callable[[int], np.ndarray], stats: CodeStats, departure: float,
              margin: int, informative: bool = True) -> OwnTrail | None:
    """The rows of the stream's own trail it has not left, after this frame (§11.6).

    Walking from `state.here` along the trail, every row the current frame is unlike is left (the
    stream passed a frame unlike it: this one), up to the first row it is like, or past the last row
    (`here` = last + 1: the frame is unlike every row of its trail it had not left). Like:
    Dice(frame, row) >= b + departure · (1 − b), b the frame's background likeness
    (`CodeStats.background`). Frame counts and clock time play no part:
    standing still keeps every row of the stop; a lap of any length is a revisit once it passed frames
    unlike its start. For the filter the rows not left are widened by `margin` links back along the trail
    (the localiser's `exclusion`, its rival window, §11.2): a path a few rows behind the stream on its own
    trail is where it is, not a revisit; a frame may still match such a row (a loop shorter than the
    window shows in the frame-level ranking, not as a place). O(margin) per frame
    plus one `code_of` per row passed (each row is passed once).

    Args:
        state: the stream's state; `here` (and its code cache) are updated in place.
        graph: the map's links; `last` must be a row of it.
        last: the stream's last stored row in its current sequence (None: none, no own trail).
        code: (n,) sorted int, the frame's code (the sLSBH code: what the frame looks like, whatever
            its context); code_of: a stored row's code in the same form.
        stats: the map's code statistics. departure: in [0, 1] (`LocaliserParams.departure`).
        margin: links before `here` that are still the stream's own (>= 0).
        informative: False for a frame too flat to say where it is (§11.7): it leaves no row (a dark
            tunnel is unlike everything, but says nothing about whether the stream moved on).

    Returns:
        OwnTrail(first, here, last, trail, code, code_of, margin + 1), first = `margin` links before
        `here` (or the trail's start), or None without a last row.
    """
    if last is None or last < 0:
        state.here, state.here_code = NONE, None
        return None
    trail = int(graph.trail[last])
    here = state.here
    if here == UNKNOWN:
        here, state.here_code = trail, None
    elif here < 0 or here > last + 1 or (here <= last and int(graph.trail[here]) != trail):
        # A new trail (a new sequence, or rows of others in between): only its last row may be its own.
        here, state.here_code = last, None
    level = stats.level(code, departure)
    while informative and here <= last:
        if state.here_code is None:
            state.here_code = np.asarray(code_of(here))
        if code_dice(code, state.here_code) >= level:
            break
        nxt = int(graph.next[here])
        here = last + 1 if here == last else (nxt if nxt >= 0 and graph.trail[nxt] == trail else last)
        state.here_code = None
    state.here = here  # last + 1: every stored row of the trail is left (this frame is unlike them all)
    first = min(here, last)
    for _ in range(margin):
        prev = int(graph.prev[first])
        if prev < 0:
            break
        first = prev
    return OwnTrail(first, here, int(last), trail, np.asarray(code), code_of, margin + 1)
