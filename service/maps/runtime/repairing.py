"""Repairing a map's merges as its runtime runs it (docs/design/science.md §11.6, docs/design/service.md
§1.2): the merges made from a stream's own recent trail listed (`own_trail_merges`) or undone (`repair`)
in one transaction, then the index and places rebuilt from the store. Which merges those are is
`service.maps.repair.find`'s; the transaction is `MapStore.repair`'s.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
from concurrent.futures import Future

from service.maps import repair as repairs
from service.maps.errors import InsufficientStorage, MapFull, MapNotFound, MapUnavailable
from service.maps.results import RepairResult, Retraction, SplitVisit, Unjoin
from storage.mapstore import MapStore, StorageError, StorageFull

__all__ = ["Repairing"]

log = logging.getLogger("cortexloc.runtime")


class Repairing:
    """`MapRuntime`'s repair (module docstring); its one state, the listing in flight, is the runtime's
    (`_listing`, `_listing_lock`)."""

    def own_trail_merges(self) -> Future[RepairResult]:
        """Any thread, not the writer: the merges made from a stream's own recent trail that no repair
        undid yet, listed (docs/design/science.md §11.6; `service.maps.repair.find`), and whether a repair
        now would be a rewrite. A listing replays the whole log (seconds on a large map): it runs in a
        thread of its own on a connection of its own (`MapStore.reader`), as of one moment of the file,
        so it never holds the writer nor the posts behind it; one runs per map at a time, and the
        requests that come meanwhile share it (a client gone does not stop it, a thousand cost one).

        Raises:
            MapUnavailable (not ready); the listing's future: MapUnavailable where the file went from
            under it (a restore, a deletion), MapNotFound where the map was deleted while it read (another
            made under its id meanwhile or not).
        """
        self.require_ready(learns=False)
        with self._listing_lock:
            if self._listing is None or self._listing.done():  # else: share the one in flight
                self._listing = Future()
                threading.Thread(target=self._list_merges, args=(self._listing,), daemon=True,
                                 name=f"repair-listing-{self.map_id}").start()
            return self._listing

    def forget_listing(self) -> None:
        """Any thread: the next listing reads the file again, not sharing one begun before a change that
        a client reads after (its repair, a restore): the one in flight still answers those waiting."""
        with self._listing_lock:
            self._listing = None

    def _list_merges(self, out: Future[RepairResult]) -> None:
        out.set_running_or_notify_cancel()  # running: no waiter can cancel it for the others
        store = self.store
        try:
            if store is None:
                raise MapUnavailable(self.map_id, self.state, self.state_reason)
            with store.reader() as reader:
                found, rewrite = self._find(reader), self._rewrite_due(reader)
            out.set_result(self._repair_result(found, None, rewrite=rewrite))
        except (StorageError, OSError, sqlite3.Error) as e:  # the file replaced or removed meanwhile
            log.warning("map %s: the repair listing could not read the file: %s", self.map_id, e)
            out.set_exception(MapUnavailable(self.map_id, self.state, self.state_reason))
        except BaseException as e:
            out.set_exception(e)

    def repair(self) -> RepairResult:
        """Writer: undo the merges made from a stream's own recent trail (docs/design/science.md §11.6,
        docs/design/service.md §1.2): each visit re-made as a row of its own, each row that joined a place
        through its stream's recent row given back its own place, each closure that named such a row
        retracted, in one transaction (`MapStore.repair`); then the index and places are rebuilt from
        the store, as a recovery builds them. A second repair finds nothing. The memory is not touched:
        it learned each frame once, with its visit, and the replay keeps taking it so.

        Where the log's cap pruned entries logged since the last repair, a closure among them that this
        repair withdraws can be neither found nor retracted, so the repair is a rewrite first: the log's
        epoch changes and a follower rebuilds its edges, even when nothing is found. Afterwards every id
        logged so far counts as judged (`Catalog.mark_repaired`).

        Raises:
            MapUnavailable (not ready). MapFull: the re-made rows would pass `max_observations`;
            MemoryBudgetExceeded: their index bytes do not fit the budget (nothing changed: a repair
            forgets nothing to make room). InsufficientStorage: no room to write (nothing changed, but
            a rewrite counted before the failure stands: one rebuild too many, never an edge kept).
        """
        self.require_ready()
        assert self.store is not None
        found, rewrite = self._find(self.store), self._rewrite_due(self.store)
        added = len(found.visits)
        if len(self.index) + added > self.index.max_observations:
            raise MapFull(self.map_id, self.index.max_observations)
        if self.budget is not None:
            self.budget.grow_index(self.map_id, added * self.row_bytes)
        try:
            if rewrite:  # before the repair: a failed one then costs a follower a rebuild, never an edge
                self.epoch = self.catalog.mark_rewrite(self.map_id).epoch
                log.warning("map %s: the loop-closure log's cap pruned entries logged since the last repair, "
                            "which it may withdraw without a retraction: the log's epoch changes, so a "
                            "follower rebuilds its edges from the export", self.map_id)
            seqs = self.store.repair(found.visits, [(s, was) for s, was, _ in found.joins],
                                     [c[0] for c in found.closures]) if found else []
        except BaseException as e:
            if self.budget is not None:  # nothing was stored: the index holds what it held
                self.budget.set_index(self.map_id, len(self.index) * self.row_bytes)
            if isinstance(e, StorageFull):
                raise InsufficientStorage("the repair could not be stored: no room to write; nothing "
                                          "changed") from e
            raise
        self.forget_listing()
        if found:
            self._rebuild_index()  # sets the budget's index bytes to the index rebuilt
        try:
            self.catalog.mark_repaired(self.map_id, self.store.next_closure_id())
        except StorageError as e:  # the repair stands; the next one may be a rewrite it need not be
            log.warning("map %s: the repair is done, but the catalog could not record it (%s)",
                        self.map_id, e)
        if found:
            log.info("map %s repaired: %d visits re-made as rows, %d rows given back their place, %d loop "
                     "closures retracted", self.map_id, len(seqs), len(found.joins), len(found.closures))
        return self._repair_result(found, seqs, rewrite=rewrite)

    def _rewrite_due(self, store: MapStore) -> bool:
        """Whether the log's cap pruned entries logged since the last repair judged the log (docs/design/
        service.md §1.2, "rewrite"): over-cautious where those were closures no repair would withdraw."""
        marks = self.catalog.get_map(self.map_id)
        # A listing's thread reads on while the map may be deleted, and another made under its id: the
        # map it was asked about is gone either way, and the other's marks are not its own.
        if marks is None or marks.created_at != self.record.created_at:
            raise MapNotFound(self.map_id)
        return repairs.pruned_below(store) > max(1, marks.repaired_below)

    def _find(self, store: MapStore) -> repairs.Found:
        return repairs.find(store, self.place_map.options, self.tm.n_columns)

    def _repair_result(self, found: repairs.Found, seqs: list[int] | None, *, rewrite: bool) -> RepairResult:
        made = seqs or [None] * len(found.visits)
        return RepairResult(
            map_id=self.map_id, window=found.window, repaired=seqs is not None,
            splits=[SplitVisit(visit=v.id, stream=v.stream, into=v.seq, seq=s)
                    for v, s in zip(found.visits, made, strict=True)],
            unjoins=[Unjoin(seq=s, stream=st, joined=was) for s, was, st in found.joins],
            retractions=[Retraction(closure=i, stream=st, place_seq=p) for i, st, p in found.closures],
            rows_added=len(found.visits) if seqs is None else len(seqs), rewrite=rewrite,
            visits_pruned_through=found.visits_pruned_through)
