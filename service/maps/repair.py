"""Merges made from a stream's own recent trail, read from a map's store (docs/design/science.md §11.6,
"Repairing a map"; docs/design/service.md §1.2, §4.2): what `cortexloc verify` and
`GET /v1/maps/{id}/repair` list and `POST /v1/maps/{id}/repair` undoes.

The store's log is read in the order it was learned (rows by seq, visits after the row before them, as
the replay takes them: `recovery.in_order`), each loop closure placed among them: a learned row's just
before its row, any other (a consolidated frame's, a localising stream's) before the first step logged
at or after it (`created_at`, microseconds, one writer; a wall clock stepped back misplaces it).
`models.localisation.repair.own_trail_merges` judges them; what an earlier repair already undid
(`MapStore.repairs`, the closures a retraction withdraws) is left out, so a second repair finds
nothing. Where the log pruned visits (a snapshot covers them, `max_visits`), the steps up to the oldest
visit it keeps are learned, not judged: a pruned visit was a move of its stream, and without it the
memory keeps rows its stream had left, so a real loop closure reads as a merge (an outside probe: a
repair then retracted a second lap's true closures). The mark (`Pruned`) is put just before the oldest kept
visit a consolidated frame made (`MapStore.oldest_plain_visit`) and the closures stamped since the step
before it: every pruned visit was learned before that visit (a warm-up join's visit sits at its row's
place, back in the log, so the oldest kept visit may be one and later than pruned ones, a review
found); where no such visit is kept, at the end of the log. After it each stream is judged by a memory
that starts empty (`models.localisation.repair`).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from models.localisation.graph import NONE
from models.localisation.motion import Motion
from models.localisation.repair import Learned, Named, Pruned, own_trail_merges, window
from service.maps.config import MapConfig, map_model
from service.maps.recovery.memory import in_order, learned_rows
from storage.catalog import Catalog, MapRecord
from storage.mapstore import LoopClosure, MapStore, Observation, Visit

__all__ = ["Found", "find", "listing", "pruned_below"]

_PAGE = 1000  # loop closures read per query


@dataclass
class Found:
    """The merges of one map still to undo (`find`).

    Attributes:
        window: the moves the stream's memory spanned (`models.localisation.repair.window`).
        visits: the visits into a row of their stream's own memory, in log order (each to be re-made as
            a row of its own).
        joins: (row, the row whose place it joined) of the rows that joined a place through a row of
            their stream's own memory, in seq order.
        closures: the logged closures to retract, in log order: each (id, stream, the row it named).
        visits_pruned_through: the last visit id the log pruned (0: none): the steps learned up to the
            oldest visit kept are not judged (module docstring), so a merge among them is not found.
    """

    window: int
    visits: list[Visit] = field(default_factory=list)
    joins: list[tuple[int, int, str]] = field(default_factory=list)
    closures: list[tuple[int, str, int]] = field(default_factory=list)
    visits_pruned_through: int = 0

    def __bool__(self) -> bool:
        return bool(self.visits or self.joins or self.closures)


def _closures(store: MapStore) -> list[LoopClosure]:
    out: list[LoopClosure] = []
    after = 0
    while page := store.closures(after, _PAGE):
        out.extend(c for c in page if c.retracts is None)
        after = page[-1].id
    return out


def _log(store: MapStore, closures: list[LoopClosure],
         pruned_through: int) -> Iterator[Learned | Named | Pruned]:
    """The store's learned steps and closures in order (module docstring), read once; with visits pruned
    (`pruned_through` > 0), the `Pruned` mark (module docstring)."""
    by_row: dict[int, list[LoopClosure]] = defaultdict(list)
    others: list[LoopClosure] = []
    for c in closures:
        (by_row[c.seq] if c.seq is not None else others).append(c)
    joined = store.joined()  # the place of a row stored before version 5
    first = store.oldest_plain_visit() if pruned_through else None
    marked = not pruned_through
    k = 0
    for step in in_order(learned_rows(store), store.visits()):
        if isinstance(step, Visit) and step.id == first:
            yield Pruned()  # before the closures placed with it: stamped after the row it follows
            marked = True
        # `<=`: a consolidated frame's closure is stamped before its visit, at worst in the same microsecond
        while k < len(others) and others[k].created_at <= step.created_at:
            yield _named(others[k])
            k += 1
        if isinstance(step, Visit) and step.row is not None:  # a row a warm-up join turned into a visit
            yield Learned(step.stream, step.row, step.input_sdr, made=True, ref=step.row,
                          motion=Motion.of(step.metadata))
            continue
        if isinstance(step, Visit):
            yield Learned(step.stream, step.seq, step.input_sdr, made=False, ref=step.id,
                          prev=step.context_prev_seq, motion=Motion.of(step.metadata))
            continue
        mine = by_row.get(step.seq, [])
        motion = Motion.of(step.metadata)
        for c in mine:
            yield Named(c.id, c.stream, c.place_seq, trail=motion.trail)
        yield Learned(step.stream, step.seq, step.input_sdr, made=True, through=_through(step, joined, mine),
                      ref=step.seq, motion=motion)
    for c in others[k:]:
        yield _named(c)
    if not marked:
        yield Pruned()  # no visit of a consolidated frame kept: nothing in the log is judged


def _named(c: LoopClosure) -> Named:
    return Named(c.id, c.stream, c.place_seq, NONE if c.consolidated_into is None else c.consolidated_into)


def _joined(row: Observation, joined: dict[int, int]) -> int | None:
    """The row whose place `row` joined (None: its own)."""
    return row.place if row.place is not None else joined.get(row.seq)


def _through(row: Observation, joined: dict[int, int], mine: list[LoopClosure]) -> tuple[int, ...]:
    """A made row's merge: the row whose place it joined and the rows its revisit named (none: no join)."""
    was = _joined(row, joined)
    return () if was is None else (was, *(c.place_seq for c in mine))


def find(store: MapStore, conf: dict[str, Any] | None, code_width: int) -> Found:
    """The merges of `store` made from a stream's own recent trail that no repair undid yet.

    Args:
        conf: the map's localiser options. code_width: its frame code's bit space.
    """
    repairs = store.repairs()
    split = {r.visit for r in repairs if r.kind == "split"}
    unjoined = {r.seq for r in repairs if r.kind == "unjoin"}
    retracted = store.retracted()
    closures = _closures(store)
    pruned = store.visits_pruned_through()
    merges = own_trail_merges(_log(store, closures, pruned), conf, code_width, pruned=pruned > 0)
    out = Found(window(conf), visits_pruned_through=pruned)
    wanted = set(merges.visits) - split
    if wanted:
        out.visits = [v for v in store.visits() if v.id in wanted]
    joins = [s for s in merges.joins if s not in unjoined]
    if joins:
        joined = store.joined()
        rows = store.get_many(joins)
        out.joins = [(s, int(_joined(rows[s], joined)), rows[s].stream) for s in joins]  # type: ignore[arg-type]
    named = {c.id: c for c in closures}
    out.closures = [(i, named[i].stream, named[i].place_seq) for i in merges.closures if i not in retracted]
    return out


def pruned_below(store: MapStore) -> int:
    """The log ids below this one are gone from the log (the cap pruned them, or a restore's floor skipped
    them): the oldest id kept, else the next to be handed out. 1: none. A closure among them that a repair
    would withdraw cannot be found, so it cannot be retracted in the log (docs/design/service.md §1.2,
    "rewrite")."""
    oldest = store.oldest_closure_id()
    return oldest if oldest is not None else store.next_closure_id()


def listing(catalog: Catalog, record: MapRecord) -> Found:
    """The merges of one map still to undo, read offline (`cortexloc verify`: the store opened read-only,
    nothing changes; a file before schema version 9 has had no repair).

    Raises:
        StorageError, OSError: the store cannot be read. InvalidConfiguration: its options are not this
        version's.
    """
    like = map_model(MapConfig.parse(record.params), max_observations=1)
    with MapStore.open(catalog.layout.map_db(record.map_id), readonly=True) as store:
        return find(store, like.place_map.options, like.tm.n_columns)
