"""Merges made from a stream's own recent trail, found again in a stored log (docs/design/science.md §11.6,
"Repairing a map"): the rule a repair lists and undoes.

A learning stream's frame consolidated into a row (a visit, §11.8), a row that joined a row's place, or a
loop closure that named a row, is a merge from the stream's own recent trail when that row was in the
stream's short-term memory at that moment: the rows it made over its last `short_term` moves
(`ShortTerm`), the memory `PlaceMap.rebuild` builds by taking rows and visits in the order they
were learned. Here the same memory is built again over the log as it was learned, so a map made before
the memory (or with `short_term` 0) is judged by the rule it would have had: its window is the map's
`short_term`, or the default's (`LocaliserParams.short_term`) where the map's is 0.

A log that lost steps (the visit log's prune) cannot tell how its streams moved before the loss: a pruned
visit was a move, and a memory built without it keeps rows its stream had left, so a real loop closure
there reads as a merge from the trail (an outside probe: a repair after the prune retracted a second lap's
closures). Such a log starts with steps that are learned but not judged, up to a `Pruned` mark where every
stream's memory starts again empty, and each stream is judged again only after `GRACE` memories' worth
of its moves past the mark. The moves are judged against the stream's last move, which the pruned steps
held: until a frame is a move both for that and for the rebuilt one, the rebuilt memory can count a
move the stream did not and reach further back than its memory did (a review's case: a true closure
read as an echo just after the mark). Past the grace the rebuilt memory is the stream's, but for a
stream whose frames stayed alike to one of the two last moves and not the other all that time.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from models.localisation.graph import NONE
from models.localisation.motion import NO_MOTION, Motion
from models.localisation.options import LocaliserOptions
from models.localisation.places import PlaceMap

__all__ = ["GRACE", "Learned", "Merges", "Named", "Pruned", "own_trail_merges", "window"]

#: Memories' worth of a stream's moves past a `Pruned` mark before it is judged again (module docstring):
#: one for its last move to agree with the stream's, one for its memory to lie past that.
GRACE = 2


@dataclass(frozen=True, eq=False)
class Learned:
    """One learned step of the log.

    Attributes:
        stream: the stream. seq: the row it made (`made`), or the row it was consolidated into (a visit).
        code: (n,) the frame's sorted code (`input_sdr`). made: a row (True) or a visit (False).
        through: a made row's merge: the row whose place it joined and the row its revisit named (empty:
            it joined no place).
        ref: the caller's name for it (a row's seq, a visit's log id), as `Merges` lists it.
        prev: a visit's row its stream continued (its `context_prev_seq`): a visit of that row by a frame
            that is no move is a rehearsal (§11.6), no merge. motion: the frame's (`Motion`), its move.
    """

    stream: str
    seq: int
    code: np.ndarray
    made: bool
    through: tuple[int, ...] = ()
    ref: int = 0
    prev: int | None = None
    motion: Motion = NO_MOTION


@dataclass(frozen=True)
class Named:
    """A logged loop closure: its `id`, `stream`, the row it named (`place_seq`), for a consolidated
    frame's the row it was consolidated into (`into`, NONE: none), and the trail its frame named
    (`metadata.trail`; None: unknown here, the trail the stream's last learned frame named)."""

    id: int
    stream: str
    place_seq: int
    into: int = NONE
    trail: str | None = None


@dataclass(frozen=True)
class Pruned:
    """The mark in a log after which it holds every step (the visits before it were pruned): the steps
    before it are not judged, and every stream's memory starts again here."""


@dataclass
class Merges:
    """What `own_trail_merges` found, in log order.

    Attributes:
        visits: the refs of the visits into a row of the stream's own memory.
        joins: the refs of the made rows that joined a place through a row of the stream's own memory.
        closures: the ids of the closures that named a row of the stream's own memory (or were logged
            with a visit into one).
    """

    visits: list[int] = field(default_factory=list)
    joins: list[int] = field(default_factory=list)
    closures: list[int] = field(default_factory=list)


def window(options: LocaliserOptions | None) -> int:
    """The moves a repair's memory spans: the map's `short_term`, or the default's where it is 0."""
    moves = 0 if options is None else options.short_term
    return moves or LocaliserOptions().short_term


def own_trail_merges(log: Iterable[Learned | Named | Pruned], options: LocaliserOptions | None,
                     code_width: int, *, pruned: bool = False) -> Merges:
    """The merges of a log made from each stream's own recent trail.

    Args:
        log: the learned steps (rows and visits) in the order they were learned, each loop closure just
            before the step that came after it (a learned row's closure just before its row): a closure is
            judged by its stream's memory at that moment, a step by the memory before it. With `pruned`, a
            `Pruned` mark where the log starts to hold every step (module docstring).
        options: the map's localiser options (its `departure` and `short_term`, `window`).
        code_width: the frame code's bit space (the code statistics the memory's moves read, §11.6).
        pruned: the log lost steps before its `Pruned` mark: nothing before the mark is judged, and a
            stream after it only past its grace (`GRACE`).

    Returns:
        The merges. One pass, O(log · memory) time, O(rows) memory (the codes are not kept).
    """
    place_map = PlaceMap(dataclasses.replace(options or LocaliserOptions(), short_term=window(options)),
                         code_width)
    out = Merges()
    marked = not pruned
    grace = GRACE * max(place_map.short_term, 1)
    moves: dict[str, int] = {}  # each stream's moves since the mark
    # The memory is a trail's (`Motion.trail`, else the stream's own name), as the live map keeps it: a
    # robot's cameras naming one trail share it. A closure's frame is read on its stream's latest trail.
    trails: dict[str, str] = {}

    def judged(stream: str) -> bool:
        return marked and (not pruned or moves.get(stream, 0) >= grace)

    for event in log:
        if isinstance(event, Pruned):
            place_map.forget_short_term()
            marked = True
            continue
        if isinstance(event, Named):
            recent = place_map.short_term_rows(event.trail or trails.get(event.stream, event.stream))
            if judged(event.stream) and np.isin([event.place_seq, event.into], recent).any():
                out.closures.append(event.id)
            continue
        trail = trails[event.stream] = event.motion.trail or event.stream
        stays = place_map.stays(event.stream, event.code, event.motion)
        if event.made:  # (the memory read only where the row joined a place: most rows did not)
            if judged(event.stream) and event.through and np.isin(
                    event.through, place_map.short_term_rows(trail)).any():
                out.joins.append(event.ref)
            place_map.add(event.seq, None, event.code, stream=event.stream, motion=event.motion)
        else:
            rehearsal = event.prev == event.seq and stays
            recent = place_map.short_term_rows(trail)
            if judged(event.stream) and not rehearsal and event.seq in recent:
                out.visits.append(event.ref)
            place_map.visit(None, event.seq, event.seq, event.stream, event.code, event.motion)
        if marked and not stays:
            moves[event.stream] = moves.get(event.stream, 0) + 1
    return out
