"""Merges made from a stream's own recent trail, found again in a stored log (docs/design/science.md §11.6,
"Repairing a map"): the rule a repair lists and undoes.

A learning stream's frame consolidated into a row (a visit, §11.8), a row that joined a row's place, or a
loop closure that named a row, is a merge from the stream's own recent trail when that row was in the
stream's short-term memory at that moment: the rows it made over its last `short_term` moves
(`ShortTerm`), the memory `PlaceMap.rebuild` builds by taking rows and visits in the order they
were learned. Here the same memory is built again over the log as it was learned, so a map made before
the memory (or with `short_term` 0) is judged by the rule it would have had: its window is the map's
`short_term`, or the default's (`LocaliserParams.short_term`) where the map's is 0.
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

__all__ = ["Learned", "Merges", "Named", "own_trail_merges", "window"]


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
    """A logged loop closure: its `id`, `stream`, the row it named (`place_seq`), and for a consolidated
    frame's the row it was consolidated into (`into`, NONE: none)."""

    id: int
    stream: str
    place_seq: int
    into: int = NONE


@dataclass
class Merges:
    """What `own_trail_merges` found, in log order.

    Attributes:
        visits: the refs of the visits into a row of the stream's own memory.
        joins: the refs of the made rows that joined a place through a row of the stream's own memory.
        closures: the ids of the closures that named a row of the stream's own memory (or were logged
            with a visit into one).
        past_repair: the ids among `closures` logged with a frame consolidated into a row of the
            stream's memory whose visit the log no longer holds (pruned, a snapshot covers it): the
            closure can be retracted, the frame cannot be split (its code is gone).
    """

    visits: list[int] = field(default_factory=list)
    joins: list[int] = field(default_factory=list)
    closures: list[int] = field(default_factory=list)
    past_repair: list[int] = field(default_factory=list)


def window(options: LocaliserOptions | None) -> int:
    """The moves a repair's memory spans: the map's `short_term`, or the default's where it is 0."""
    moves = 0 if options is None else options.short_term
    return moves or LocaliserOptions().short_term


def own_trail_merges(log: Iterable[Learned | Named], options: LocaliserOptions | None,
                     code_width: int) -> Merges:
    """The merges of a log made from each stream's own recent trail.

    Args:
        log: the learned steps (rows and visits) in the order they were learned, each loop closure just
            before the step that came after it (a learned row's closure just before its row): a closure is
            judged by its stream's memory at that moment, a step by the memory before it.
        options: the map's localiser options (its `departure` and `short_term`, `window`).
        code_width: the frame code's bit space (the code statistics the memory's moves read, §11.6).

    Returns:
        The merges. One pass, O(log · memory) time, O(rows) memory (the codes are not kept). A
        consolidated frame's closure comes just before its visit (the writer stamps it first and commits
        both at once; while the wall clock does not step back), so a closure whose frame went into a row
        of the memory, and whose stream's next step is not a visit into that row, lost its visit to the
        log's prune (`Merges.past_repair`). The pairing is by row, not identity: where the next kept
        visit of the stream went into the same row, the pruned one is not told.
    """
    place_map = PlaceMap(dataclasses.replace(options or LocaliserOptions(), short_term=window(options)),
                         code_width)
    out = Merges()
    awaiting: dict[str, Named] = {}  # per stream: a flagged consolidated frame's closure, its visit next
    for event in log:
        if not isinstance(event, Named) or event.into != NONE:
            was = awaiting.pop(event.stream, None)
            if was is not None and (isinstance(event, Named) or event.made or event.seq != was.into):
                out.past_repair.append(was.id)
        if isinstance(event, Named):
            recent = place_map.short_term_rows(event.stream)
            if np.isin([event.place_seq, event.into], recent).any():
                out.closures.append(event.id)
                if event.into != NONE and event.into in recent:
                    awaiting[event.stream] = event
        elif event.made:  # (the memory read only where the row joined a place: most rows did not)
            if event.through and np.isin(event.through, place_map.short_term_rows(event.stream)).any():
                out.joins.append(event.ref)
            place_map.add(event.seq, None, event.code, stream=event.stream, motion=event.motion)
        else:
            rehearsal = event.prev == event.seq and place_map.stays(event.stream, event.code, event.motion)
            if not rehearsal and event.seq in place_map.short_term_rows(event.stream):
                out.visits.append(event.ref)
            place_map.visit(None, event.seq, event.seq, event.stream, event.code, event.motion)
    out.past_repair.extend(c.id for c in awaiting.values())
    return out
