"""A map's snapshots as its runtime takes and uses them (docs/design/service.md §1.5, §1.8, §4.4): a
consistent cut at the current seq (manual, automatic after `snapshot_every` commits, pre-restore),
the retention of each kind, the listing, and a restore with its memory budget.

The snapshot files themselves are `storage.snapshots`'; listing, locating, pruning and deleting them is
`service.maps.recovery.snapshots`'. A restore's memory is rebuilt by the runtime's recovery
(`service.maps.runtime.recovering`).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from models.pipeline import memory_state
from service.maps import recovery
from service.maps.errors import RowsOverCap
from service.maps.recovery import snapshots as map_snapshots
from service.maps.results import RestoreResult, SnapshotInfo
from service.maps.runtime import budget as map_budget
from storage import snapshots
from storage.catalog import SnapshotKind, utc_now
from storage.mapstore import MapStore

__all__ = ["Snapshots"]

log = logging.getLogger("cortexloc.runtime")


class Snapshots:
    """`MapRuntime`'s snapshots (module docstring). It owns which visits the newest snapshot covers,
    the commits since the last automatic one and that one's failure."""

    covered: int  # the last visit id the newest snapshot holds (visits after it are replayed)
    since_snapshot: int  # rows and visits committed since the last automatic snapshot
    snapshot_error: dict[str, Any] | None  # the last automatic snapshot's failure, if it failed
    snapshot_failures: int
    restores: int  # restores begun since the runtime started (`Writer._still_held`)

    def snapshots(self) -> list[SnapshotInfo]:
        return map_snapshots.listing(self.catalog, self.map_id)

    def snapshot_dir(self, snapshot_id: str) -> Path:
        return map_snapshots.locate(self.catalog, self.map_id, snapshot_id)[1]

    def delete_snapshot(self, snapshot_id: str) -> None:
        """Writer: delete one snapshot; SnapshotNotFound, SnapshotInUse (the one recovery starts from)."""
        assert self.store is not None
        map_snapshots.delete(self.catalog, self.map_id, snapshot_id, self.store)

    def snapshot(self, kind: SnapshotKind = "manual") -> SnapshotInfo:
        """A consistent cut at the current seq (docs/design/service.md §1.5, §4.4).

        Raises:
            InsufficientStorage: no room to write (nothing is left behind).
        """
        assert self.store is not None
        cursor = self.store.visit_stats()[2]  # the visits this memory has learned (§11.8)
        memory = {**memory_state(self.tm, self.streams), recovery.VISIT_CURSOR: np.array(cursor, np.int64),
                  recovery.VISIT_MARK: np.array(self.store.visit_mark(cursor) or "")}
        snap = map_snapshots.take(self.store, memory, self.catalog, self.map_id, self.projection_path, kind)
        self.covered = cursor
        if kind == "manual":  # retention (docs/design/service.md §1.5); the new one is never deleted
            self._prune_kept("manual")
        return snap

    def _prune_kept(self, kind: SnapshotKind) -> None:
        assert self.store is not None
        keep = self.settings
        map_snapshots.prune_kept(self.catalog, self.map_id, self.store, kind, keep.snapshot_manual_keep,
                                 keep.snapshot_manual_bytes)

    def _auto_snapshot(self) -> None:
        """The periodic snapshot after a commit. It only shortens the next recovery, so a failure
        (typically a full disk) is logged, counted and shown in /readyz, never the request's error:
        the row it follows is durable and acknowledged."""
        try:
            self.snapshot("auto")
            self.since_snapshot = 0  # counted from the last automatic one, whatever manual ones came between
            map_snapshots.prune_auto(self.catalog, self.map_id, self.store, self.settings.snapshot_keep)
        except Exception as e:  # any failure: see the docstring
            self.snapshot_failures += 1
            self.snapshot_error = {"seq": self.store.last_seq() if self.store else 0, "at": utc_now(),
                                   "error": str(e) or type(e).__name__}
            log.exception("map %s: automatic snapshot failed; the rows stay durable", self.map_id)
        else:
            self.snapshot_error = None

    def restore(self, snapshot_id: str) -> RestoreResult:
        """Roll the map back to a snapshot, after keeping the present in a pre-restore snapshot.

        The snapshot's store replaces the map's; the memory is then rebuilt by `recover`, which finds
        that snapshot as the newest on the store's branch (the later ones, the pre-restore one included,
        are on the branch the restore leaves).

        Raises:
            SnapshotNotFound; SnapshotInvalid, RowsOverCap (before anything changes); InsufficientStorage.
        """
        assert self.store is not None
        _, path = map_snapshots.locate(self.catalog, self.map_id, snapshot_id)
        snapshots.verify(path)  # refuse a damaged snapshot before touching anything
        recovery.check_memory(path)  # and one whose memory recovery would refuse
        with MapStore.open(path / snapshots.DB_FILE, readonly=True) as copy:
            rows, held = copy.count(), copy.held()
            if held > self.index.max_observations:  # its index could not be rebuilt (the cap lowered since)
                raise RowsOverCap(f"snapshot {snapshot_id!r} of map {self.map_id!r}", held,
                                  self.index.max_observations, "nothing changed")
            discarded, brought_back = map_snapshots.learned_difference(self.store, copy)
        with self._restore_budget(rows):
            # From here the rows stepped before may go: a post still waiting for its row's fsync is checked
            # against the store the restore leaves (`Writer._still_held`, behind this on the writer), not
            # acknowledged off the count it was stepped at while the file is being replaced.
            self.restores += 1
            self.snapshot("pre-restore")
            self.catalog.mark_restore(self.map_id, self.store.next_seq() - 1, self.store.last_closure_id())
            self.store.close()
            MapStore.install_copy(path / snapshots.DB_FILE, self.layout.map_db(self.map_id))
            self.recover()
        # Pre-restore snapshots are kept to the manual ones' limits, counted apart (a loop of restores
        # wrote one each, a map's size apiece, kept for good). Pruned once the restore is done: the
        # snapshot restored, a pre-restore one perhaps, is then the recovery base, never deleted. The
        # restore stands either way.
        try:
            self._prune_kept("pre-restore")
        except Exception:  # (the next restore prunes again)
            log.exception("map %s: restored, but its older pre-restore snapshots could not be pruned",
                          self.map_id)
        self.keys.clear()  # answers given before may name the observations the restore dropped
        self.recent.clear()
        map_budget.give_back()  # the memory and index the restore replaced
        return RestoreResult(**vars(self.info()), discarded_observations=discarded,
                             restored_observations=brought_back)

    @contextlib.contextmanager
    def _restore_budget(self, rows: int) -> Iterator[None]:
        """The memory budget of a restore (docs/design/service.md §1.8): while it runs, the new memory and
        index are built beside the old ones (the memory in the budget's recovery room, the old index
        held as transient bytes), and the snapshot's `rows` must fit (the index estimate, set exactly by
        the recovery). Raises MemoryBudgetExceeded before anything changes."""
        if self.budget is None:
            yield
            return
        old_index = len(self.index) * self.row_bytes
        with self.budget.transient(self.map_id, old_index):
            self.budget.grow_index(self.map_id, rows * self.row_bytes - old_index)
            try:
                yield
            finally:  # the index as it is now: the restored one, or the old one if the restore failed
                self.budget.set_index(self.map_id, len(self.index) * self.row_bytes)
