"""Merges made from a stream's own recent trail, read from a map's store (docs/design/science.md §11.6,
"Repairing a map"; docs/design/service.md §1.2, §4.2): what `cortexloc verify` and
`GET /v1/maps/{id}/repair` list and `POST /v1/maps/{id}/repair` undoes.

The store's log is read in the order it was learned (rows by seq, visits after the row before them, as
the replay takes them: `recovery.in_order`), each loop closure placed among them: a learned row's just
before its row, any other (a consolidated frame's, a localising stream's) before the first step logged
at or after it (`created_at`, microseconds, one writer; a wall clock stepped back misplaces it).
`models.localisation.repair.own_trail_merges` judges them; what an earlier repair already undid
(`MapStore.repairs`, the closures a retraction withdraws) is left out, so a second repair finds
nothing. Visits pruned from the log (a snapshot covers them, `max_visits`) are past repair: their codes
are gone (`Found.past_repair` names the retracted closures whose frames stay merged).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from models.localisation.graph import NONE
from models.localisation.motion import Motion
from models.localisation.repair import Learned, Named, own_trail_merges, window
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
        past_repair: the ids among `closures` logged with a consolidated frame whose visit the log has
            pruned: retracted, but the frame stays merged (its code is gone).
        visits_pruned_through: the last visit id the log pruned (0: none): a merge among those visits is
            past repair, and one without a closure is not found at all.
    """

    window: int
    visits: list[Visit] = field(default_factory=list)
    joins: list[tuple[int, int, str]] = field(default_factory=list)
    closures: list[tuple[int, str, int]] = field(default_factory=list)
    past_repair: list[int] = field(default_factory=list)
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


def _log(store: MapStore, closures: list[LoopClosure]) -> Iterator[Learned | Named]:
    """The store's learned steps and closures in order (module docstring), read once."""
    by_row: dict[int, list[LoopClosure]] = defaultdict(list)
    others: list[LoopClosure] = []
    for c in closures:
        (by_row[c.seq] if c.seq is not None else others).append(c)
    joined = store.joined()  # the place of a row stored before version 5
    k = 0
    for step in in_order(learned_rows(store), store.visits()):
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
        for c in mine:
            yield Named(c.id, c.stream, c.place_seq)
        yield Learned(step.stream, step.seq, step.input_sdr, made=True, through=_through(step, joined, mine),
                      ref=step.seq, motion=Motion.of(step.metadata))
    for c in others[k:]:
        yield _named(c)


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
    merges = own_trail_merges(_log(store, closures), conf, code_width)
    out = Found(window(conf), visits_pruned_through=store.visits_pruned_through())
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
    # Only a closure stamped no later than the oldest visit kept can have lost its visit (its visit is
    # stamped after it, and one writer stamps nothing between them): this keeps most closures a clock
    # stepped back misplaced in the log from calling a kept visit's frame past repair.
    kept = store.visit_mark(out.visits_pruned_through + 1) if out.visits_pruned_through else None
    oldest = None if kept is None else kept.rsplit("|", 1)[1]
    out.past_repair = [i for i in merges.past_repair if i not in retracted and out.visits_pruned_through
                       and (oldest is None or named[i].created_at <= oldest)]
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
