"""A map's recovery as its runtime runs it (docs/design/service.md §4.3–§4.4): the store opened and
checked, the memory rebuilt from the newest usable snapshot and the rows and visits after it
(`service.maps.recovery.recover`), installed with its index and links rebuilt from the store; a long
tail replayed by the writer in turns while the map localises from the snapshot's memory; the map's
state (`ready` | `replaying` | `recovering` | `failed`) and the readiness check every request makes.

Recovery runs at start-up, after a restore (`service.maps.runtime.snapshots`) and after a failed
commit (`service.maps.runtime.writer`).
"""

from __future__ import annotations

import contextlib
import copy
import heapq
import logging
import math
import time
from collections.abc import Iterator
from typing import Any, NamedTuple

import numpy as np

from models.localisation.graph import NONE
from models.localisation.motion import Motion
from service.maps import recovery
from service.maps.errors import READ_ONLY_REASON, MapReadOnly, MapReplaying, MapUnavailable, RowsOverCap
from service.maps.states import serving
from storage import snapshots
from storage.catalog import MapNotFound as CatalogMapNotFound
from storage.mapstore import MapStore, Observation, StorageFull, StoreCorrupt, StoreUnopenable

__all__ = ["TAIL_BEFORE_SERVING", "Recovering"]

#: A recovery's tail (rows and visits after its snapshot) of at most this many steps is replayed before the
#: map serves (well under a second at 5-13 ms a step); a longer one while it serves localising frames
#: from the snapshot's memory (docs/design/service.md §4.4).
TAIL_BEFORE_SERVING = 50

log = logging.getLogger("cortexloc.runtime")


class Recovering:
    """`MapRuntime`'s recovery (module docstring). It owns the map's state and its reason, the store it
    opens, what the last recovery did, and a tail replaying while the map localises: the recovery
    begun, when its replay started, and the streams localised or reset meanwhile (theirs are the live
    states)."""

    #: Steps of a tail replay per turn of the writer: a localising frame waits for at most one turn (§4.4).
    replay_turn_steps = 8

    state: str
    state_reason: str | None
    store: MapStore | None
    epoch: str
    recovery: dict[str, Any] | None
    _tail: recovery.Tail | None
    _tail_started: float
    _localised: set[str]
    _projection_error: str | None
    stream_evictions: int

    def require_ready(self, learns: bool = True) -> None:
        """Raises MapUnavailable unless the map is ready or, for what neither learns nor changes stored
        state (`learns=False`: a localising frame, a read), replaying its tail (§4.4); MapReplaying (a
        MapUnavailable with a `retry_after`) for what learns meanwhile; MapReadOnly for what learns on a
        map whose storage refuses writes (`read-only`: it reads)."""
        serves = serving(self.state)
        if serves.learns:
            return
        tail = self._tail
        if serves.reads and tail is not None:  # what reads is answered from the tail replayed so far
            if learns:
                done = tail.replay.out.replayed + tail.replay.out.visits
                per_step = (time.perf_counter() - self._tail_started) / done if done else 0.0
                raise MapReplaying(self.map_id, tail.steps, done,
                                   max(1, math.ceil((tail.steps - done) * per_step)))
            return
        if serves.read_only:
            if learns:
                raise MapReadOnly(self.map_id)
            return
        raise MapUnavailable(self.map_id, self.state, self.state_reason)

    def recover(self, *, serve_during_replay: bool = False) -> None:
        """Open the store and rebuild the memory from it (`recovery.recover`, docs/design/service.md §4.4):
        at startup, after a restore, and after a failed commit. What happened is in `self.recovery`
        (map resource, /readyz) and the log; only an unreadable store or projection fails the map.

        With `serve_during_replay` (at startup) a tail of more than `TAIL_BEFORE_SERVING` steps after the
        newest usable snapshot is replayed by the writer in turns of `replay_turn_steps`, after this
        returns: the map is `replaying` meanwhile, localising frames are answered from the memory as far
        as it has replayed, and what learns is refused (MapReplaying) until the tail is done."""
        if self.hasher is None:
            self._fail("projection-invalid", self._projection_error or "no projection")
            return
        self._codes.clear()  # a restore's store holds other rows under later seqs
        self.forget_listing()  # (a repair listing of the file before)
        if self.layout.snapshots_dir(self.map_id).is_dir():  # a crash during a snapshot leaves a temp dir
            snapshots.remove_stale_temp(self.layout.snapshots_dir(self.map_id))
        try:
            marks = self.catalog.get_map(self.map_id)
            if marks is None:  # deleted meanwhile: as the catalog says it
                raise CatalogMapNotFound(f"map {self.map_id!r} not found")
            self.store = MapStore.open(self.layout.map_db(self.map_id),
                                       max_keys=self.settings.idempotency_keys,
                                       max_closures=self.settings.loop_closures,
                                       seq_floor=marks.seq_high_water, closure_floor=marks.closure_high_water)
            self.epoch = marks.epoch  # which map, how many restores and rewrites (`MapRecord.epoch`)
            if not self.store.quick_check():
                raise StoreCorrupt("quick_check failed")
        except (StoreCorrupt, StorageFull) as e:  # full (a migration): the file is whole, a restart recovers
            self._fail("disk-full" if isinstance(e, StorageFull) else "database-corrupt", str(e))
            return
        except StoreUnopenable as e:  # a permission or a read-only directory: never called corrupt
            self._fail("unopenable", str(e))
            return
        held, cap = self.store.held(), self.index.max_observations
        if held > cap:  # the setting lowered since: the index cannot hold the rows (§1.4)
            # Refused, not forgotten down to the cap: a setting's typo must not cost a map its places. The
            # reason says it all (map resource, /readyz, one log line): there is no traceback to read.
            over = RowsOverCap(f"map {self.map_id!r}", held, cap, "it is not opened, nothing was forgotten")
            self._fail(str(over))
            return
        tail = None
        try:  # a row the replay reads may be unreadable (a blob or JSON damaged outside the service)
            if serve_during_replay:
                tail = recovery.begin(self.store, self.catalog, self.map_id, self.model)
            if tail is not None and tail.steps > TAIL_BEFORE_SERVING:
                self._serve_during(tail)
                return
            self._install(*recovery.recover(self.store, self.catalog, self.map_id, self.model, begun=tail))
        except StoreCorrupt as e:
            self._fail("database-corrupt", str(e))

    def _install(self, done: recovery.Rebuilt, note: dict[str, Any]) -> None:
        """The recovered memory in place, its index and links built from the rows (unless they already
        were, for it: a tail replayed while serving); the map is ready.

        A failure half way leaves a memory that is neither the old one nor the store's: the map is
        `failed` (`install-failed`, the error in the log), never `ready` on it, and the error is raised
        on (its caller's request or start says so)."""
        try:
            self._install_rebuilt(done, note)
        except Exception as e:
            self._fail("install-failed", str(e) or type(e).__name__)
            raise

    def _install_rebuilt(self, done: recovery.Rebuilt, note: dict[str, Any]) -> None:
        assert self.store is not None
        fresh = done.model is not self.model
        self.model, self.streams = done.model, done.streams
        self._cap_streams()
        self.covered, self.since_snapshot = done.covered, 0
        if fresh:
            self._rebuild_index()
        self.recovery = note
        self.state, self.state_reason = "ready", None
        log.info("map %s ready: %s", self.map_id, note)
        if not self.store.writable:  # checked once per open: SQLite opened it read-only without a word
            self.read_only()

    def read_only(self) -> None:
        """The map's storage refuses writes: it serves reads and refuses what learns (`MapReadOnly`) until
        an operator makes `map.sqlite` writable and restarts the service."""
        self.state, self.state_reason = "read-only", READ_ONLY_REASON
        log.error("map %s: %s refuses writes; it localises, learning is refused until the file is writable "
                  "and the service restarted", self.map_id, self.layout.map_db(self.map_id))

    def _cap_streams(self, say: bool = True) -> None:
        """A replay meets every stream that ever learned, and `CORTEXLOC_MAX_STREAMS` may have been lowered
        since: the least recently used over it go, as `touch` evicts them live (their next learned frame
        starts a new sequence), counted as evictions and said in one log line (`say`; not for the copies
        served while a tail replays: its end caps the replayed streams again, and says it once)."""
        evicted = 0
        while len(self.streams) > self.settings.max_streams:
            self.streams.popitem(last=False)
            evicted += 1
        if evicted and say:
            self.stream_evictions += evicted
            log.info("map %s: the %d least recently used of its learning streams are over "
                     "CORTEXLOC_MAX_STREAMS=%d; they start afresh", self.map_id, evicted,
                     self.settings.max_streams)

    def _serve_during(self, tail: recovery.Tail) -> None:
        """Serve localising frames from the tail's start while the writer replays it (`_replay_tail`)."""
        out = tail.replay.out
        self.model = out.model
        self._rebuild_index()  # every stored row is in the index at once: the replay reproduces them
        # The live streams are copies: the replay steps its own, and a localising frame never moves them.
        self.streams = copy.deepcopy(out.streams)
        self._cap_streams(say=False)
        self._tail, self._tail_started, self._localised = tail, time.perf_counter(), set()
        self.recovery = {"source": "snapshot", "snapshot_id": tail.snapshot_id,
                         "snapshot_seq": tail.snapshot_seq, "tail": tail.steps, "replayed": 0}
        self.state, self.state_reason = "replaying", None
        log.info("map %s localises from snapshot %s while its tail of %d rows and visits replays",
                 self.map_id, tail.snapshot_id, tail.steps)
        self.submit(self._replay_tail)

    def _replay_tail(self) -> None:
        """Writer: one turn of the tail's replay, then the next turn is queued behind the frames that
        arrived meanwhile; at its end the map is ready (its streams as replayed and resumed, but those
        localised or reset meanwhile as they are now: their next learned frame starts a new sequence, as
        after any localisation). A replay that diverges passes the snapshot over as at a start (the map
        `recovering` until an older start is replayed). A crash meanwhile loses nothing: the replay
        writes nothing, the next start replays the same tail."""
        tail = self._tail
        if tail is None:
            return
        try:
            if not tail.replay.run(self.replay_turn_steps):
                # how far it is, for the map resource and /readyz (a new dict: they read it on the loop)
                self.recovery = {**(self.recovery or {}),
                                 "replayed": tail.replay.out.replayed + tail.replay.out.visits}
                with contextlib.suppress(RuntimeError):  # the writer shut down: the map closes replaying
                    self._writer.submit(self._replay_tail)
                return
            assert self.store is not None
            self._tail = None
            if tail.replay.out.mismatches:
                self.state, self.state_reason = "recovering", "replay-diverged"
            live, localised = self.streams, self._localised
            done, note = recovery.recover(self.store, self.catalog, self.map_id, self.model, begun=tail)
            if done.model is self.model:
                for name in localised:
                    if name in live:
                        done.streams[name] = live[name]
                        done.streams.move_to_end(name)
                    else:  # evicted by the live streams meanwhile
                        done.streams.pop(name, None)
            note["replayed_while_serving"] = True
            self._install(done, note)
        except Exception as e:  # anything: the map must not stay replaying for ever
            log.exception("map %s: the tail's replay failed", self.map_id)
            self._tail = None
            self._fail("replay-failed", str(e) or type(e).__name__)

    def _rebuild_index(self) -> None:
        """The index and links from the stored rows (docs/design/service.md §4.4 step 6)."""
        assert self.store is not None
        dropped = self.store.dropped()
        held: list[_Held] = []

        # a row a warm-up join turned into a visit is that row again (docs/design/science.md §11.8)
        joined = [v.as_row() for v in self.store.visits() if v.row is not None]

        def rows() -> Iterator[Observation]:  # the rows read once, for the links and the index (issue 40)
            for r in heapq.merge(self.store.rows(), joined, key=lambda o: o.seq):  # type: ignore[union-attr]
                if r.seq not in dropped:
                    held.append(_Held(r.seq, r.winner_cells, r.stream))
                yield r

        # (a visit's stream and code: the streams' short-term memories, docs/design/science.md §11.6; a
        # visit a repair re-made as a row: its step of the memory only, row NONE)
        done = self.store.repairs()
        split = {r.visit for r in done if r.kind == "split"}
        visits = ((v.context_prev_seq, NONE if v.id in split else v.seq, v.after_seq + 1, v.stream,
                   v.input_sdr, Motion.of(v.metadata)) for v in self.store.visits() if v.row is None)
        self.model.place_map.rebuild(rows(), dropped, self.store.joined(), visits, self.store.recency(),
                                 remade={r.seq for r in done if r.kind == "split"},
                                 unjoined={r.seq for r in done if r.kind == "unjoin"},
                                 folded=self.store.joins(), flat=self.store.flat())
        self.model.index.rebuild(held)
        if self.budget is not None:
            self.budget.set_index(self.map_id, len(self.index) * self.row_bytes)

    def _fail(self, reason: str, detail: str | None = None) -> None:
        """The map `failed`: `reason` is its `state_reason`, `detail` (if any) what the log adds to it."""
        self.state, self.state_reason = "failed", reason
        log.error("map %s failed (%s)%s", self.map_id, reason, f": {detail}" if detail else "")
        try:
            self.catalog.set_state(self.map_id, "failed", reason)
        except StorageFull as e:  # a full disk (often why it failed): served as failed all the same
            log.error("map %s: the catalog could not record its state (%s); it is served as failed",
                      self.map_id, e)


class _Held(NamedTuple):
    """What the index is rebuilt from of a row held (`InvertedIndex.rebuild`)."""

    seq: int
    winner_cells: np.ndarray
    stream: str
