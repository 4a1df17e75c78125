"""One map in memory: its writer thread and the way of an observation through it
(docs/design/service.md §1.2–§1.4, §4.3–§4.4, §6).

Each map owns a Temporal Memory, its sLSBH hasher (its own persisted projection), a `MapStore` (the
system of record) and an inverted index over winner cells. Every change to them runs in the map's
single writer thread, in submission order, so the memory sees frames in arrival order and never two at
once; different maps proceed in parallel.

Which thread runs what:

    event loop     observe (queues the image, awaits the features, then queues the step), run,
                   require_ready
    writer         apply, snapshot, restore, reset_stream, info, memory, snapshots, snapshot_dir
                   (reach them through `run` / `submit`)
    start-up       recover (before the writer takes work; in the writer on the commit-failure path), close
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import dataclasses
import functools
import hashlib
import heapq
import logging
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import numpy as np

import service.maps.runtime.idempotency as idempotency  # the module, not the package: no cycle via __init__
import service.maps.runtime.sizes as sizes
from models import geometry, pipeline
from models.frontend import slsbh
from models.frontend.images import RawFrame
from models.localisation import InvertedIndex, Localisation, forgetting
from models.localisation.graph import NONE
from models.localisation.motion import Motion
from models.memory.temporal_memory import TemporalMemory
from models.pipeline import Stream, eviction_wait, memory_state, touch
from service.maps import keyframes, recovery
from service.maps import repair as repairs
from service.maps.config import MapConfig, map_model
from service.maps.encoding.pool import EncoderPool
from service.maps.errors import (
    ClientGone,
    InsufficientStorage,
    MapFull,
    MapNotFound,
    MapReplaying,
    MapUnavailable,
    StreamLimit,
)
from service.maps.recovery import snapshots as map_snapshots
from service.maps.results import (
    MapInfo,
    Match,
    MemoryInfo,
    ObservationResult,
    PlaceResult,
    PlacesInfo,
    RepairResult,
    RestoreResult,
    Retraction,
    SequenceStats,
    SnapshotInfo,
    SplitVisit,
    StreamReset,
    Unjoin,
)
from service.maps.runtime.budget import MemoryBudget, index_row_bytes
from service.maps.runtime.durability import GroupCommit
from service.maps.runtime.recent import RecentAnswers
from storage import snapshots
from storage.base.dtypes import INDEX_DTYPE
from storage.catalog import Catalog, MapRecord, utc_now
from storage.mapstore import (
    MapStore,
    NewClosure,
    NewObservation,
    NewVisit,
    Observation,
    StorageFull,
    StoreCorrupt,
)

__all__ = ["FORGETTING", "TAIL_BEFORE_SERVING", "MapRuntime"]

#: The forgetting rule as the map resource states it (docs/design/science.md §11.9).
FORGETTING = forgetting.RULE

#: A recovery's tail (rows and visits after its snapshot) of at most this many steps is replayed before the
#: map serves (well under a second at 5-13 ms a step); a longer one while it serves localising frames
#: from the snapshot's memory (docs/design/service.md §4.4).
TAIL_BEFORE_SERVING = 50
#: Stored rows' codes the writer keeps for the own-trail rule and consolidation (`_code_of`), the most
#: recently used: about one read per frame, of a row committed moments before (1.2 MB at 308 columns).
CODES_KEPT = 256

log = logging.getLogger("cortexloc.runtime")
T = TypeVar("T")


class MapRuntime:
    """One map in memory, with its single writer thread; `state` is `ready` | `recovering` | `failed`
    and `state_reason` says why (module docstring: which thread runs which method)."""

    #: The clock of the streams' last posts (the stream window, §1.3); tests set their own.
    clock: Callable[[], float] = staticmethod(time.monotonic)
    #: Steps of a tail replay per turn of the writer: a localising frame waits for at most one turn (§4.4).
    replay_turn_steps = 8

    def __init__(self, record: MapRecord, catalog: Catalog,
                 feature_dim: int, max_streams: int, max_observations: int,
                 snapshot_every: int = 0, snapshot_keep: int = 3, *, max_keys: int | None = None,
                 key_cache: int = 0, budget: MemoryBudget | None = None,
                 stream_keep_seconds: float = 0.0, manual_keep: int = 0, manual_bytes: int = 0,
                 verify_neighbours: int = 2, max_closures: int | None = None,
                 max_visits: int = 100_000) -> None:
        self.record = record
        self.map_id = record.map_id
        # Stored options this version rejects raise InvalidConfiguration: the registry serves a FailedMap.
        self.config = MapConfig.parse(record.params)
        self.layout = catalog.layout  # every path of the map (storage.layout)
        self.catalog = catalog
        self.max_streams = max_streams
        # A stream that posted within this window is never evicted for a new one (§1.3); evictions counted.
        self.stream_keep_seconds = stream_keep_seconds
        self.stream_evictions = 0
        self.forgotten = 0  # rows forgotten since start (the hard cap, docs/design/science.md §11.9)
        self.snapshot_every = snapshot_every
        self.snapshot_keep = snapshot_keep
        self.manual_keep, self.manual_bytes = manual_keep, manual_bytes  # manual snapshots kept (0: no limit)
        # Idempotency keys: those of learned posts in the store (the last `max_keys` seqs), those of
        # localisations in memory (service.maps.runtime.idempotency).
        self.max_keys = max_keys
        self.max_closures = max_closures  # loop closures kept in the store's log (the last N)
        # Visits (consolidated frames, docs/design/science.md §11.8) kept once a snapshot covers them;
        # `covered`: the last visit id the newest snapshot holds (visits after it are replayed).
        self.max_visits = max_visits
        self.covered = 0
        self.since_snapshot = 0  # rows and visits committed since the last automatic snapshot
        self.keys = idempotency.KeyCache(key_cache)
        # The process-wide budget that holds this map's reservation (docs/design/service.md §1.8): each
        # learned row reserves its index bytes first. None: a runtime built alone (tools, tests).
        self.budget = budget
        self.row_bytes = index_row_bytes(self.config)
        self.state = "recovering"
        self.state_reason: str | None = None
        # What the last recovery did (`recover`); the last automatic snapshot's failure, if it failed.
        self.recovery: dict[str, Any] | None = None
        self.snapshot_error: dict[str, Any] | None = None
        self.snapshot_failures = 0
        self.streams: OrderedDict[str, Stream] = OrderedDict()
        # A tail replaying while the map localises (`state` "replaying", §4.4): the recovery begun, when its
        # replay started, and the streams localised or reset meanwhile (theirs are the live states).
        self._tail: recovery.Tail | None = None
        self._tail_started = 0.0
        self._localised: set[str] = set()
        self._writer = ThreadPoolExecutor(1, thread_name_prefix=f"map-{self.map_id}")
        # Learned rows are committed by the writer without their fsync and acknowledged once this has
        # synced them, one fsync per group (service.maps.runtime.durability).
        self._commits = GroupCommit(self._sync_store, f"sync-{self.map_id}")
        # The order in which observations reach the writer: each waits for the one before to be queued.
        self._turn = asyncio.Event()
        self._turn.set()
        sha = self.config.projection_sha256
        self.projection_path = self.layout.projection(sha)
        self.hasher: slsbh.Hasher | None = None
        self._projection_error: str | None = None
        # the checksum is verified on load: a map never runs on another matrix (docs/design/science.md §7)
        try:
            projection = slsbh.load_projection(self.projection_path, sha,
                                               shape=(feature_dim, int(self.config.slsbh["k"])))
            self.hasher = slsbh.Hasher(projection, float(self.config.slsbh["s"]))
        except (slsbh.ProjectionError, OSError) as e:
            self._projection_error = str(e)
        # Keyframes (docs/design/science.md §12): how many route neighbours a verification tries, each
        # stream's camera (the options themselves are the config's: keyframes, verify_revisit).
        self.verify_neighbours = verify_neighbours
        self.cameras: dict[str, dict[str, Any]] = {}  # given once per stream (or with each frame)
        # The memory, index and links the pure pipeline steps (models.pipeline); this runtime keeps
        # their order, their persistence and their snapshots.
        self.model = map_model(self.config, max_observations=max_observations)
        self.store: MapStore | None = None
        self._codes: OrderedDict[int, np.ndarray] = OrderedDict()  # seq -> its stored code (`_code_of`)
        self.recent: RecentAnswers[Any] = RecentAnswers()  # the replies as sent (the route fills it)

    @property
    def tm(self) -> TemporalMemory:
        return self.model.tm

    @property
    def index(self) -> InvertedIndex:
        return self.model.index

    @property
    def localisation(self) -> Localisation:
        return self.model.links

    # ------------------------------------------------------------------ writer

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """Event loop: `fn(*args)` in this map's writer thread, after everything submitted before it."""
        return await asyncio.wrap_future(self.submit(fn, *args))

    def submit(self, fn: Callable[..., T], *args: Any) -> Future[T]:
        """Any thread: queue `fn(*args)` on the writer. Raises MapNotFound once the map is deleted."""
        try:
            return self._writer.submit(fn, *args)
        except RuntimeError as e:  # the writer was shut down: the map was deleted meanwhile
            raise MapNotFound(self.map_id) from e

    def close(self, snapshot: bool = True) -> None:
        """Drain the writer; at a clean shutdown take an automatic snapshot if anything is new.

        "New" includes a stream that switched to localisation: that switch is not in the rows, and the
        snapshot carries it (a localisation stream comes back empty, so its next mapping step starts a
        new sequence as it would have without the restart).
        """
        self._writer.shutdown(wait=True)
        self._commits.close()  # the requests still waiting get their sync first
        if self.store is None:
            return
        latest = self.catalog.list_snapshots(self.map_id)
        # Rows or visits the newest snapshot (of any kind) does not hold: a shutdown snapshot shortens
        # the next start; one right after a manual snapshot would only duplicate it.
        new_rows = (self.store.last_seq() > (latest[0].seq if latest else 0)
                    or self.store.visit_stats()[2] > self.covered)
        switched = any(st.learning is False for st in self.streams.values())
        if snapshot and self.state == "ready" and self.snapshot_every and (new_rows or switched):
            try:
                self.snapshot("auto")
                map_snapshots.prune_auto(self.catalog, self.map_id, self.store, self.snapshot_keep)
            except Exception:  # the rows are durable; a snapshot only shortens the next replay
                log.exception("map %s: shutdown snapshot failed", self.map_id)
        self.store.close()

    def _sync_store(self) -> None:
        """Group commit's thread: fsync what the writer committed (the store in use now; one that
        recovery closed was checkpointed and synced by SQLite on close)."""
        store = self.store
        if store is not None:
            store.sync()

    async def durable(self) -> None:
        """Event loop: wait until every row committed so far is durable (an acknowledgement waits for
        it: docs/design/service.md §4.3)."""
        await asyncio.wrap_future(self._commits.durable())

    def require_ready(self, learns: bool = True) -> None:
        """Raises MapUnavailable unless the map is ready or, for what neither learns nor changes stored
        state (`learns=False`: a localising frame, a read), replaying its tail (§4.4); MapReplaying (a
        MapUnavailable with a `retry_after`) for what learns meanwhile."""
        tail = self._tail
        if self.state == "replaying" and tail is not None:
            if learns:
                done = tail.replay.out.replayed + tail.replay.out.visits
                per_step = (time.perf_counter() - self._tail_started) / done if done else 0.0
                raise MapReplaying(self.map_id, tail.steps, done,
                                   max(1, math.ceil((tail.steps - done) * per_step)))
            return
        if self.state != "ready":
            raise MapUnavailable(self.map_id, self.state, self.state_reason)

    # ------------------------------------------------------------------ snapshots

    def snapshots(self) -> list[SnapshotInfo]:
        return map_snapshots.listing(self.catalog, self.map_id)

    def snapshot_dir(self, snapshot_id: str) -> Path:
        return map_snapshots.locate(self.catalog, self.map_id, snapshot_id)[1]

    def delete_snapshot(self, snapshot_id: str) -> None:
        """Writer: delete one snapshot; SnapshotNotFound, SnapshotInUse (the one recovery starts from)."""
        assert self.store is not None
        map_snapshots.delete(self.catalog, self.map_id, snapshot_id, self.store)

    def snapshot(self, kind: str = "manual") -> SnapshotInfo:
        """A consistent cut at the current seq (docs/design/service.md §1.5, §4.4).

        Raises:
            InsufficientStorage: the disk is full (nothing is left behind).
        """
        assert self.store is not None
        cursor = self.store.visit_stats()[2]  # the visits this memory has learned (§11.8)
        memory = {**memory_state(self.tm, self.streams), recovery.VISIT_CURSOR: np.array(cursor, np.int64),
                  recovery.VISIT_MARK: np.array(self.store.visit_mark(cursor) or "")}
        snap = map_snapshots.take(self.store, memory, self.catalog, self.map_id, self.projection_path, kind)
        self.covered = cursor
        if kind == "manual":  # retention (docs/design/service.md §1.5); the new one is never deleted
            map_snapshots.prune_manual(self.catalog, self.map_id, self.store, self.manual_keep,
                                       self.manual_bytes)
        return snap

    def _auto_snapshot(self) -> None:
        """The periodic snapshot after a commit. It only shortens the next recovery, so a failure
        (typically a full disk) is logged, counted and shown in /readyz, never the request's error:
        the row it follows is durable and acknowledged."""
        try:
            self.snapshot("auto")
            self.since_snapshot = 0  # counted from the last automatic one, whatever manual ones came between
            map_snapshots.prune_auto(self.catalog, self.map_id, self.store, self.snapshot_keep)
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
            SnapshotNotFound; SnapshotInvalid (before anything changes); InsufficientStorage.
        """
        assert self.store is not None
        _, path = map_snapshots.locate(self.catalog, self.map_id, snapshot_id)
        snapshots.verify(path)  # refuse a damaged snapshot before touching anything
        before = self.store.count()
        with self._restore_budget(path):
            self.snapshot("pre-restore")
            self.catalog.bump_high_water(self.map_id, self.store.next_seq() - 1)
            self.store.close()
            MapStore.install_copy(path / snapshots.DB_FILE, self.layout.map_db(self.map_id))
            self.recover()
        self.keys.clear()  # answers given before may name the observations the restore dropped
        self.recent.clear()
        after = self.store.count() if self.store is not None else 0
        return RestoreResult(**vars(self.info()), discarded_observations=before - after)

    @contextlib.contextmanager
    def _restore_budget(self, snapshot: Path) -> Iterator[None]:
        """The memory budget of a restore (docs/design/service.md §1.8): while it runs, the new memory and
        index are built beside the old ones (the memory in the budget's recovery room, the old index
        held as transient bytes), and the snapshot's rows must fit (the index estimate, set exactly by
        the recovery). Raises MemoryBudgetExceeded before anything changes."""
        if self.budget is None:
            yield
            return
        with MapStore.open(snapshot / snapshots.DB_FILE, readonly=True) as copy:
            rows = copy.count()
        old_index = len(self.index) * self.row_bytes
        with self.budget.transient(self.map_id, old_index):
            self.budget.grow_index(self.map_id, rows * self.row_bytes - old_index)
            try:
                yield
            finally:  # the index as it is now: the restored one, or the old one if the restore failed
                self.budget.set_index(self.map_id, len(self.index) * self.row_bytes)

    # ------------------------------------------------------------------ recovery

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
        if self.layout.snapshots_dir(self.map_id).is_dir():  # a crash during a snapshot leaves a temp dir
            snapshots.remove_stale_temp(self.layout.snapshots_dir(self.map_id))
        try:
            self.store = MapStore.open(self.layout.map_db(self.map_id), max_keys=self.max_keys,
                                       max_closures=self.max_closures,
                                       seq_floor=self.catalog.get_high_water(self.map_id))
            if not self.store.quick_check():
                raise StoreCorrupt("quick_check failed")
        except (StoreCorrupt, StorageFull) as e:  # full (a migration): the file is whole, a restart recovers
            self._fail("disk-full" if isinstance(e, StorageFull) else "database-corrupt", str(e))
            return
        tail = None
        if serve_during_replay:
            tail = recovery.begin(self.store, self.catalog, self.map_id, self.model)
        if tail is not None and tail.steps > TAIL_BEFORE_SERVING:
            self._serve_during(tail)
            return
        self._install(*recovery.recover(self.store, self.catalog, self.map_id, self.model, begun=tail))

    def _install(self, done: recovery.Rebuilt, note: dict[str, Any]) -> None:
        """The recovered memory in place, its index and links built from the rows (unless they already
        were, for it: a tail replayed while serving); the map is ready."""
        assert self.store is not None
        fresh = done.model is not self.model
        self.model, self.streams = done.model, done.streams
        while len(self.streams) > self.max_streams:  # a replay meets every stream that ever learned
            self.streams.popitem(last=False)  # the least recently used go, as `touch` evicts them live
        self.covered, self.since_snapshot = done.covered, 0
        if fresh:
            self._rebuild_index()
        self.recovery = note
        self.state, self.state_reason = "ready", None
        log.info("map %s ready: %s", self.map_id, note)

    def _serve_during(self, tail: recovery.Tail) -> None:
        """Serve localising frames from the tail's start while the writer replays it (`_replay_tail`)."""
        out = tail.replay.out
        self.model = out.model
        self._rebuild_index()  # every stored row is in the index at once: the replay reproduces them
        # The live streams are copies: the replay steps its own, and a localising frame never moves them.
        self.streams = copy.deepcopy(out.streams)
        while len(self.streams) > self.max_streams:
            self.streams.popitem(last=False)
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
        self.model.links.rebuild(rows(), dropped, self.store.joined(), visits, self.store.recency(),
                                 remade={r.seq for r in done if r.kind == "split"},
                                 unjoined={r.seq for r in done if r.kind == "unjoin"},
                                 folded=self.store.joins())
        self.model.index.rebuild(held)
        if self.budget is not None:
            self.budget.set_index(self.map_id, len(self.index) * self.row_bytes)

    def _fail(self, reason: str, detail: str) -> None:
        self.state, self.state_reason = "failed", reason
        self.catalog.set_state(self.map_id, "failed", reason)
        log.error("map %s failed (%s): %s", self.map_id, reason, detail)

    # ------------------------------------------------------------------ streams

    def _admit(self, name: str) -> None:
        """Raises StreamLimit while a new stream `name` would evict one that posted within the window
        (docs/design/service.md §1.3)."""
        wait = eviction_wait(self.streams, name, self.max_streams, self.stream_keep_seconds, self.clock())
        if wait > 0:
            raise StreamLimit(self.max_streams, self.stream_keep_seconds, max(1, math.ceil(wait)))

    def reset_stream(self, name: str) -> StreamReset:
        """Break the stream's sequence (the next frame starts a new one); its adaptation is kept,
        because it describes the camera and the conditions, not where the robot is."""
        st = self.streams.get(name)
        if self._tail is not None:  # the live state is the stream's from now on (`_replay_tail`)
            self._localised.add(name)
        had = st is not None and st.context.active_cells.size > 0
        if st is not None:
            st.break_sequence()
        return StreamReset(stream=name, had_context=bool(had))

    # ------------------------------------------------------------------ observations

    async def observe(self, pool: EncoderPool, extractions: keyframes.Extractions, body: bytes | RawFrame, *,
                      learn: bool, stream: str, top_k: int, label: str | None,
                      metadata: dict[str, Any] | None = None, post: idempotency.IdempotentPost | None = None,
                      gone: threading.Event | None = None) -> ObservationResult | idempotency.Reply:
        """Event loop: one checked image through the map (docs/design/service.md §1.2, §6).

        The pool encodes and projects it with this map's matrix, batched with other requests; the step
        (`apply`) is then queued on the writer, after the steps of the requests that arrived before
        this one, so the memory sees frames in arrival order while the writer never waits for an
        encoding.

        With a `post` (an Idempotency-Key) the answer is its `Reply`: the earlier one for a repeated
        key, else the sealed reply of this step (service.maps.runtime.idempotency).

        On a map with keyframes the frame's features are taken in `extractions`, beside the encoding.
        `gone` is set once the client went away: an extraction not yet started is skipped, and a post
        whose client is gone by the time its turn comes is not handed to the writer; one the writer has
        is never aborted.

        Raises:
            MapUnavailable, StreamLimit, Overloaded (nothing queued); ImageError (the decode failed, nothing
            changed); ClientGone, InvalidCamera (nothing changed); MapFull, InsufficientStorage (from
            `apply`); IdempotencyKeyReused.
        """
        gone = gone or threading.Event()
        self.require_ready(learn)
        # Refused before its encoding too; `apply` checks again in the writer, where it is exact (here
        # the writer may be changing the streams: a look that meets it is left to that check).
        with contextlib.suppress(RuntimeError):
            self._admit(stream)
        t0 = time.perf_counter()
        # Localised frames too: their thumbnail is kept in the recent ring only (never stored).
        encoding = pool.submit(body, hasher=self.hasher, backbone=self.config.backbone,
                               thumbnail=self.config.thumbnails, resize=self.config.resize)
        # Local features in native pixels, while the backbone encodes (docs/design/science.md §12.1).
        # The stream's camera: this frame's, else the last.
        given = (metadata or {}).get("camera")
        camera = given or self.cameras.get(stream)
        try:
            frame = None if self.config.keyframes is None else asyncio.wrap_future(extractions.submit(
                pool.encoders.get(self.config.backbone).decode, body, self.config.keyframes, camera,
                given is not None, gone))
        except BaseException:
            encoding.cancel()  # refused (Overloaded): the pool skips the encoding where it has not started
            raise
        # The digest stored with the row, off the event loop (a 10 MB raw frame takes ~20 ms to hash)
        # and beside the encoding.
        digest = asyncio.ensure_future(asyncio.to_thread(_sha256, getattr(body, "data", body)))
        before, mine = self._turn, asyncio.Event()
        self._turn = mine
        try:
            encoded = await asyncio.wrap_future(encoding)
            query = None if frame is None else await frame
            image_sha256 = await digest
            t_encoded = time.perf_counter()
            await before.wait()
            if gone.is_set():  # nobody waits for the answer: the writer never gets it (nothing changes)
                raise ClientGone("the client went away before its post reached the map's writer")
            assert encoded.projected is not None  # the pool projects when given a hasher
            front = {"decode": encoded.timings_ms["decode"], "encode": (t_encoded - t0) * 1e3,
                     **({} if query is None else {"features": query.ms})}
            thumb = encoded.thumbnails[0] if encoded.thumbnails else None
            apply = functools.partial(
                self.apply, encoded.projected[0], image_sha256,
                learn=learn, stream=stream, top_k=top_k, label=label, metadata=metadata,
                thumbnail=thumb if learn else None, post=post, query=query,
                contrast=None if encoded.contrast is None else float(encoded.contrast[0]), durable=False)
            if post is not None:
                post.front_ms = front
                assert self.store is not None  # a ready map has its store
                once = self.submit(idempotency.apply_once, self.store, self.keys, post, learn, apply)
            else:
                step = self.submit(apply)
        finally:
            mine.set()
        # A learned row (and the earlier reply of a repeated key, whose row may be in the same group) is
        # acknowledged only once durable: the writer committed it without its fsync (group commit).
        if post is not None:
            answer = await asyncio.wrap_future(once)
            if learn:
                await self.durable()
            return answer if answer.replayed else dataclasses.replace(answer, thumbnail=thumb)
        result = await asyncio.wrap_future(step)
        t_step = time.perf_counter()
        if learn:
            await self.durable()
        sync = {"sync": (time.perf_counter() - t_step) * 1e3} if learn else {}
        return dataclasses.replace(result, timings_ms={**front, **result.timings_ms, **sync}, thumbnail=thumb)

    def apply(self, projected: np.ndarray, image_sha256: str, *, learn: bool, stream: str, top_k: int,
              label: str | None, metadata: dict[str, Any] | None = None, thumbnail: bytes | None = None,
              post: idempotency.IdempotentPost | None = None,
              query: keyframes.QueryFrame | None = None, contrast: float | None = None,
              durable: bool = True) -> ObservationResult:
        """Writer: one frame's TM step on the stream's context, ranking, and for learning the commit.

        Args:
            projected: (k,) the frame's features · this map's projection (docs/design/science.md §7).
            image_sha256: hex digest of the image bytes (stored, never the image).
            metadata, thumbnail: stored with a learned row (docs/design/service.md §4.2).
            post: an idempotent post: a learned row commits with its sealed reply.
            query: the frame's local features and camera (maps with keyframes): a learned row stores
                them; a revisit candidate is verified with them (docs/design/science.md §12).
            contrast: the decoded frame's contrast (`models.frontend.images.contrast`; None: not
                measured): a frame too flat to say where it is is no revisit (docs/design/science.md §11.7).
            durable: False: the row is committed without its fsync; the caller acknowledges it only
                after `durable()` (group commit, docs/design/service.md §4.3).

        Returns:
            The result; `timings_ms` holds hash, tm, search (of which localiser), store and, for a
            learned row, commit (its durable write, within store).

        Raises:
            ValueError: `projected` is not (k,) (before any state change). MapUnavailable, MapFull,
            StreamLimit, MemoryBudgetExceeded (nothing changed).
            InsufficientStorage: the disk is full; the memory was rebuilt from the store, nothing learned.
        """
        self.require_ready(learn)
        assert self.store is not None and self.hasher is not None  # a map without them is never ready
        if projected.shape != (self.hasher.k,):
            raise ValueError(f"projection has shape {projected.shape}, this map's are ({self.hasher.k},)")
        self._admit(stream)
        if learn and (gone := forgetting.to_forget(self.index, self.localisation)):
            self._forget(gone)
        if learn and self.budget is not None:  # the row's index bytes, before the step (a failed one is
            self.budget.grow_index(self.map_id, self.row_bytes)  # set right by the recovery it causes)
        try:
            return self._step(projected, image_sha256, learn=learn, stream=stream, top_k=top_k, label=label,
                              metadata=metadata, thumbnail=thumbnail, post=post, query=query,
                              contrast=contrast, durable=durable)
        except Exception as e:
            if not learn:  # a localisation learns nothing: the memory and the store still agree
                if isinstance(e, StorageFull):  # its loop closure could not be logged: no answer either
                    raise InsufficientStorage("the loop closure could not be logged: the disk is full") from e
                raise
            # The TM may hold a learned step the store does not (a failed commit, or a failure anywhere
            # between the step and the commit): rebuild from the store before anything else runs, so
            # no later row is learned on a memory that replay cannot reproduce (docs/design/service.md §4.3).
            assert self.store is not None
            self.state, self.state_reason = "recovering", "step-failed"
            self.store.close()
            self.recover()
            if isinstance(e, StorageFull):
                raise InsufficientStorage("the observation could not be stored: the disk is full; nothing "
                                          "was learned") from e
            raise

    def _step(self, projected: np.ndarray, image_sha256: str, *, learn: bool, stream: str, top_k: int,
              label: str | None, metadata: dict[str, Any] | None, thumbnail: bytes | None,
              post: idempotency.IdempotentPost | None,
              query: keyframes.QueryFrame | None = None, contrast: float | None = None,
              durable: bool = True) -> ObservationResult:
        """Writer: `apply` after its checks: the pure step (`models.pipeline.observe`), then the reply
        from the stored rows it names and, for learning, the row on disk. An exception here while
        learning is rebuilt from by `apply` (the step already holds the row in the index and links)."""
        assert self.store is not None
        st, evicted = touch(self.streams, stream, self.max_streams, self.clock())
        self.stream_evictions += evicted
        if self._tail is not None:  # localising while the tail replays (`_replay_tail`)
            self._localised.add(stream)
        seq = self.store.next_seq() if learn else None  # this thread is the store's only writer
        step = pipeline.observe(self.model, st, projected, learn=learn, stream=stream, top_k=top_k, seq=seq,
                                code_of=self._code_of, threshold=self.config.revisit_threshold,
                                contrast=contrast, motion=Motion.of(metadata))
        if step.visit is not None:  # consolidated (§11.8): the memory learned it, no row is made
            seq = None
        # What a replay cannot rebuild of the stream, durable with its step: it resumes after a crash (§4.4).
        resume = pipeline.resume_state(st) if learn else None
        t3 = time.perf_counter()
        place = step.place
        rows = self.store.get_many([*(m.seq for m in step.ranked), *([place.seq] if place else [])])
        if place is not None and place.seq not in rows:  # a path on a row a join turned into a visit:
            place = place._replace(seq=self.store.joined_to(place.seq))  # its place's old row (§11.8)
            rows.update(self.store.get_many([place.seq]))
        if query is not None and query.camera is not None:
            self.cameras[stream] = query.camera
            if len(self.cameras) > self.max_streams:  # bounded: the cameras of the streams held
                self.cameras = {k: v for k, v in self.cameras.items() if k in self.streams}
        kf = None if query is None else (geometry.pack(query.features), query.camera)
        row = NewObservation(stream=stream, image_sha256=image_sha256, input_sdr=step.code,
                             winner_cells=step.winners, context_prev_seq=step.prev_seq, label=label,
                             metadata=metadata, thumbnail=thumbnail, keyframe=kf,
                             place=step.joined if step.joined >= 0 else None,
                             drops=step.dropped, touched=step.touched, joins=step.joins,
                             resume=resume) if seq is not None else None
        answer = None if place is None else self._verified(
            PlaceResult.of(place, rows[place.seq], self.config.revisit_threshold), query, stream)
        # The answer is whole before the commit, so an idempotent post's reply commits with its row.
        result = ObservationResult(
            map_id=self.map_id, stream=stream, learned=learn, observation_id=row and row.observation_id,
            seq=seq, sequence=SequenceStats.of(step.step, step.stats),
            matches=[Match.of(i + 1, rows[m.seq], m.overlap, m.score) for i, m in enumerate(step.ranked)],
            timings_ms=step.timings_ms, map_seq=seq or self.store.last_seq(),
            projection_sha256=self.config.projection_sha256, backbone=self.config.backbone, metadata=metadata,
            encoder=self.config.encoder_id, resize=self.config.resize, place=answer,
            consolidated_into=step.visit)
        # A revisit is a loop closure, logged durably: with the learned row in its transaction, or alone
        # for a localising stream (it stores no observation and changes no memory; §11.6). It carries
        # the place's geometric verification where there is one (docs/design/science.md §12).
        verified = None if answer is None or answer.verification is None else dataclasses.asdict(
            answer.verification)
        closure = None if result.place is None or not result.place.revisit else NewClosure(
            stream=stream, place_seq=result.place.seq, confidence=result.place.confidence,
            support=result.place.support, metadata=metadata, key=post.key if post is not None else None,
            verification=verified, span=result.place.span, span_seqs=tuple(result.place.span_seqs))
        if step.visit is not None:  # durable before the reply: the replay needs it (service.md §4.4)
            self.store.add_visit(NewVisit(
                stream=stream, seq=step.visit, context_prev_seq=step.prev_seq, input_sdr=step.code,
                winner_cells=step.winners, metadata=metadata, closure=closure, touched=step.touched,
                key=None if post is None else post.record(result), resume=resume, joins=step.joins))
            self._committed()
        elif row is None and closure is not None:
            self.store.add_closure(closure)
        if row is not None:
            if post is not None:
                row = dataclasses.replace(row, key=post.record(result))
            t_commit = time.perf_counter()
            committed = self.store.append(dataclasses.replace(row, closure=closure), durable=durable)
            commit_ms = (time.perf_counter() - t_commit) * 1e3
            assert committed == seq  # this thread is the store's only writer
            self._keep_code(seq, step.code.astype(INDEX_DTYPE))  # as the store gives it back
            self._committed()
        if learn and self.budget is not None and (step.visit is not None or step.dropped or step.joins):
            # the row reserved before the step was not made, or its place dropped rows (§11.9), or
            # warm-up rows were joined and are held no more (§11.8)
            self.budget.set_index(self.map_id, len(self.index) * self.row_bytes)
        t4 = time.perf_counter()
        # store: the reply's stored rows, verification and the durable write; commit: the write alone.
        stored = {"store": (t4 - t3) * 1e3, **({"commit": commit_ms} if row is not None else {})}
        return dataclasses.replace(result, timings_ms={**result.timings_ms, **stored})

    def _committed(self) -> None:
        """Writer: after a row or a visit is durable. Every `snapshot_every` of them the automatic snapshot
        (the stream's step is recorded first, so it holds the stream as it is after this frame); then the
        visits it covers beyond the last `max_visits` are pruned (docs/design/science.md §11.8), and the
        stream states it holds (docs/design/service.md §4.4)."""
        assert self.store is not None
        self.since_snapshot += 1
        if self.snapshot_every and self.since_snapshot >= self.snapshot_every:
            self._auto_snapshot()
            if self.since_snapshot == 0:  # it was taken
                self.store.prune_visits(self.covered, self.max_visits)
                self.store.prune_stream_states(self.store.last_seq())

    def _forget(self, gone: list[int]) -> None:
        """Writer: the hard cap binds (`max_observations` rows held): forget `gone`, the rows the rule
        chose (`forgetting.to_forget`: the least recently used places, whole, at least 1 % of the cap),
        durably before the row that needed the room (docs/design/science.md §11.9). Their rows stay in
        map.sqlite (the replay and snapshots read them) but leave the index, the places and every answer."""
        assert self.store is not None
        self.store.drop(gone, "forgotten")
        pipeline.drop(self.model, gone)
        self.forgotten += len(gone)
        if self.budget is not None:
            self.budget.set_index(self.map_id, len(self.index) * self.row_bytes)
        log.info("map %s: the row cap binds; forgot %d rows of the least recently used places",
                 self.map_id, len(gone))

    def _verified(self, place: PlaceResult, query: keyframes.QueryFrame | None, stream: str) -> PlaceResult:
        """Writer: a revisit candidate's geometric verification (docs/design/science.md §12.2), on maps
        with keyframes only; with `verify_revisit` an unverified candidate is no revisit."""
        if not place.revisit or self.config.keyframes is None or self.store is None:
            return place
        v = keyframes.verify_candidate(self.store, self.localisation.graph, place.seq, place.stream, query,
                                       stream=stream, neighbours=self.verify_neighbours)
        revisit = keyframes.revisit_stands(place.revisit, v, self.config.verify_revisit)
        return dataclasses.replace(place, verification=v, revisit=revisit)

    def _code_of(self, seq: int) -> np.ndarray:
        """Writer: a stored row's frame code (its sLSBH input SDR), for the own-trail rule (§11.6) and
        consolidation (§11.8): kept from its commit (`CODES_KEPT`), else read from the store (the same
        values: the code is stored exactly)."""
        code = self._codes.get(seq)
        if code is not None:
            self._codes.move_to_end(seq)
            return code
        assert self.store is not None
        code = self.store.code(seq)  # (a joined row's from its visit, §11.8)
        assert code is not None  # the rule walks the stream's committed rows
        self._keep_code(seq, code)
        return code

    def _keep_code(self, seq: int, code: np.ndarray) -> None:
        self._codes[seq] = code
        if len(self._codes) > CODES_KEPT:
            self._codes.popitem(last=False)

    # ------------------------------------------------------------------ repair

    def own_trail_merges(self) -> RepairResult:
        """Writer: the merges made from a stream's own recent trail that no repair undid yet, listed
        (docs/design/science.md §11.6; `service.maps.repair.find`)."""
        self.require_ready(learns=False)
        assert self.store is not None
        return self._repair_result(self._find(), None)

    def repair(self) -> RepairResult:
        """Writer: undo the merges made from a stream's own recent trail (docs/design/science.md §11.6,
        docs/design/service.md §1.2): each visit re-made as a row of its own, each row that joined a place
        through its stream's recent row given back its own place, each closure that named such a row
        retracted, in one transaction (`MapStore.repair`); then the index and places are rebuilt from
        the store, as a recovery builds them. A second repair finds nothing. The memory is not touched:
        it learned each frame once, with its visit, and the replay keeps taking it so.

        Raises:
            MapUnavailable (not ready). MapFull: the re-made rows would pass `max_observations`;
            MemoryBudgetExceeded: their index bytes do not fit the budget (nothing changed: a repair
            forgets nothing to make room). InsufficientStorage: the disk is full (nothing changed).
        """
        self.require_ready()
        assert self.store is not None
        found = self._find()
        if not found:
            return self._repair_result(found, [])
        added = len(found.visits)
        if len(self.index) + added > self.index.max_observations:
            raise MapFull(self.map_id, self.index.max_observations)
        if self.budget is not None:
            self.budget.grow_index(self.map_id, added * self.row_bytes)
        try:
            seqs = self.store.repair(found.visits, [(s, was) for s, was, _ in found.joins],
                                     [c[0] for c in found.closures])
        except BaseException as e:
            if self.budget is not None:  # nothing was stored: the index holds what it held
                self.budget.set_index(self.map_id, len(self.index) * self.row_bytes)
            if isinstance(e, StorageFull):
                raise InsufficientStorage("the repair could not be stored: the disk is full; nothing "
                                          "changed") from e
            raise
        self._rebuild_index()  # sets the budget's index bytes to the index rebuilt
        log.info("map %s repaired: %d visits re-made as rows, %d rows given back their place, %d loop "
                 "closures retracted", self.map_id, len(seqs), len(found.joins), len(found.closures))
        return self._repair_result(found, seqs)

    def _find(self) -> repairs.Found:
        assert self.store is not None
        return repairs.find(self.store, self.localisation.localiser.conf, self.tm.n_columns)

    def _repair_result(self, found: repairs.Found, seqs: list[int] | None) -> RepairResult:
        made = seqs or [None] * len(found.visits)
        return RepairResult(
            map_id=self.map_id, window=found.window, repaired=seqs is not None,
            splits=[SplitVisit(visit=v.id, stream=v.stream, into=v.seq, seq=s)
                    for v, s in zip(found.visits, made, strict=True)],
            unjoins=[Unjoin(seq=s, stream=st, joined=was) for s, was, st in found.joins],
            retractions=[Retraction(closure=i, stream=st, place_seq=p) for i, st, p in found.closures],
            rows_added=len(seqs or []))

    # ------------------------------------------------------------------ resources

    def info(self) -> MapInfo:
        return MapInfo.of(self.config, self.record, state=self.state, state_reason=self.state_reason,
                          observations=len(self.index),
                          last_seq=self.store.last_seq() if self.store else 0, streams=list(self.streams),
                          recovery=self.recovery, snapshot_error=self.snapshot_error,
                          places=(self.places() if self.store is not None
                                  and self.state in ("ready", "replaying") else None),
                          **map_snapshots.disk_use(self.catalog, self.map_id))

    def places(self) -> PlacesInfo:
        """Writer: the map's places, appearances and visits (docs/design/science.md §11.8, §11.9)."""
        assert self.store is not None
        dropped = self.store.dropped()
        conf = self.localisation.localiser.conf
        return PlacesInfo(
            places=self.localisation.places(), appearances=len(self.index), rows_stored=self.store.count(),
            dropped=len(dropped), forgotten=sum(1 for r in dropped.values() if r == "forgotten"),
            visits_logged=self.store.visit_stats()[0], max_appearances=int(conf["appearances"]),
            max_rows=self.index.max_observations, consolidate=float(conf["consolidate"]),
            forgetting=FORGETTING)

    def set_revisit_threshold(self, value: float) -> MapInfo:
        """Writer: the map's revisit threshold (`patch`)."""
        return self.patch(revisit_threshold=value)

    def patch(self, *, revisit_threshold: float | None = None, verify_revisit: bool | None = None) -> MapInfo:
        """Writer: the options that may change after creation, durable in the catalog in one update
        (docs/design/service.md §1.2): the revisit threshold, and whether a revisit needs a verified
        keyframe. InvalidConfiguration (nothing changes): a threshold outside [0, 1], verify_revisit on a
        map without keyframes."""
        changes = {k: v for k, v in (("revisit_threshold", revisit_threshold),
                                     ("verify_revisit", verify_revisit)) if v is not None}
        if changes:
            config = self.config.with_changes(**changes)
            self.record = self.catalog.update_params(
                self.map_id, **{k: getattr(config, k) for k in changes})
            self.config = config
        return self.info()

    def memory(self) -> MemoryInfo:
        return sizes.memory_info(self.model, self.streams, tm_params=self.config.tm,
                                 max_streams=self.max_streams, projection=self.projection_path,
                                 store=self.store, snapshots_bytes=self.catalog.snapshots_bytes(self.map_id))


class _Held(NamedTuple):
    """What the index is rebuilt from of a row held (`InvertedIndex.rebuild`)."""

    seq: int
    winner_cells: np.ndarray
    stream: str


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()
