"""The map's writer and the order of what it does (docs/design/service.md §1.2, §4.3, §6): the single
thread every change of the map runs in, the way of one observation to it (`observe`: encoder pool, then
the writer's turn in arrival order), its checks and the step (`apply`, `_step`), the persistence of
what the step made (a row, a visit, a localising loop closure), the group commit that acknowledges a
row once durable, the periodic snapshot's trigger after a commit (`_committed`), forgetting at the
row cap, made durable before the row that needs the room (`_forget`), a revisit's verification
(`_verified`) and the stored codes the writer keeps (`_code_of`).

What the step builds (the row, the reply, the closure, the visit) is `service.maps.runtime.records`'s;
the step itself is the pure `models.pipeline.observe`.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import hashlib
import json
import logging
import sqlite3
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, TypeVar

import numpy as np

import service.maps.runtime.idempotency as idempotency  # the module, not the package: no cycle via __init__
import service.maps.runtime.records as records
from models import pipeline
from models.frontend import slsbh
from models.frontend.images import RawFrame
from models.localisation import forgetting
from models.localisation.motion import Motion
from models.pipeline import touch
from service.maps import keyframes
from service.maps.departure import Departure
from service.maps.encoding.pool import EmbeddingPool
from service.maps.errors import ClientGone, InsufficientStorage, MapNotFound, MapReadOnly, MapRestored
from service.maps.recovery import snapshots as map_snapshots
from service.maps.results import ObservationResult, PlaceResult
from service.maps.runtime.durability import GroupCommit
from service.maps.runtime.room import ROOM_PROBE_BYTES, Room
from service.maps.states import serving
from storage.base.dtypes import INDEX_DTYPE
from storage.mapstore import MapStore, NewClosure, StorageError, StorageFull, StoreReadOnly

__all__ = ["CODES_KEPT", "Writer"]

#: Stored rows' codes the writer keeps for the own-trail rule and consolidation (`_code_of`), the most
#: recently used: about one read per frame, of a row committed moments before (1.2 MB at 308 columns).
CODES_KEPT = 256

log = logging.getLogger("cortexloc.runtime")
T = TypeVar("T")


class Writer:
    """`MapRuntime`'s writer (module docstring). It owns the writer thread, the group commit, the
    arrival order of observations, the streams' cameras, the kept codes and the count of forgotten rows."""

    _writer: ThreadPoolExecutor
    _commits: GroupCommit
    _turn: asyncio.Event
    hasher: slsbh.Hasher | None
    cameras: dict[str, dict[str, Any]]  # given once per stream (or with each frame)
    _codes: OrderedDict[int, np.ndarray]  # seq -> its stored code (`_code_of`)
    forgotten: int  # rows forgotten since start (the hard cap, docs/design/science.md §11.9)
    _closures_unlogged: bool  # a full disk refused a localising closure, said once (`_log_closure`)
    room: Room  # whether the store has room to learn: a full disk refuses learning before its step
    store: MapStore | None

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
        # a map that is not ready takes no snapshot, and may hold the closed store a failed reopen left
        ready = serving(self.state).learns
        if not (snapshot and ready and self.settings.snapshot_every):
            self.store.close()
            return
        latest = self.catalog.list_snapshots(self.map_id)
        # Rows or visits the newest snapshot (of any kind) does not hold: a shutdown snapshot shortens
        # the next start; one right after a manual snapshot would only duplicate it.
        new_rows = (self.store.last_seq() > (latest[0].seq if latest else 0)
                    or self.store.visit_stats()[2] > self.covered)
        switched = any(st.learning is False for st in self.streams.values())
        if new_rows or switched:
            try:
                self.snapshot("auto")
                map_snapshots.prune_auto(self.catalog, self.map_id, self.store, self.settings.snapshot_keep)
            except Exception:  # the rows are durable; a snapshot only shortens the next replay
                log.exception("map %s: shutdown snapshot failed", self.map_id)
        self.store.close()

    def _has_room(self) -> bool:
        """Writer: `Room`'s probe, on the store in use now (a recovery opens another)."""
        store = self.store
        return store is None or store.has_room(ROOM_PROBE_BYTES)

    @property
    def no_room(self) -> str | None:
        """Why learning is refused for lack of room (storage's words), or None (`Room.full`)."""
        return self.room.full

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

    async def observe(self, pool: EmbeddingPool, extractions: keyframes.Extractions,
                      body: bytes | RawFrame, *, learn: bool, stream: str, top_k: int, label: str | None,
                      metadata: dict[str, Any] | None = None, post: idempotency.IdempotentPost | None = None,
                      gone: Departure | None = None) -> ObservationResult | idempotency.Reply:
        """Event loop: one checked image through the map (docs/design/service.md §1.2, §6).

        The pool encodes and projects it with this map's matrix, batched with other requests; the step
        (`apply`) is then queued on the writer, after the steps of the requests that arrived before
        this one, so the memory sees frames in arrival order while the writer never waits for an
        encoding.

        With a `post` (an Idempotency-Key) the answer is its `Reply`: the earlier one for a repeated
        key, else the sealed reply of this step (service.maps.runtime.idempotency).

        On a map with keyframes the frame's features are taken in `extractions`, beside the encoding.
        `gone` is set once the client went away: its encoding is cancelled where it is not yet in a
        batch, an extraction not yet started is skipped, and a post whose client is gone by the time its
        turn comes is not handed to the writer; one the writer has is never aborted.

        Raises:
            MapUnavailable, StreamLimit, Overloaded (nothing queued); ImageError (the decode failed, nothing
            changed); ClientGone, InvalidCamera (nothing changed); MapFull, InsufficientStorage (from
            `apply`); IdempotencyKeyReused.
        """
        gone = gone or Departure()
        self.require_ready(learn)
        # No room and no probe due: refused before its encoding. Not a keyed post: the route answered a
        # key already stored, but its first post may still be in the writer, which answers the key first.
        if learn and post is None and (refusal := self.room.refused()) is not None:
            raise refusal
        # Refused before its encoding too; `apply` checks again in the writer, where it is exact (here
        # the writer may be changing the streams: a look that meets it is left to that check).
        with contextlib.suppress(RuntimeError):
            self._admit(stream)
        t0 = time.perf_counter()
        # Local features in native pixels, beside the encoding (docs/design/science.md §12.1). Their slot
        # is taken first: a post they refuse takes no encoder slot (which may be taken back from another
        # map's post); one the encoder refuses gives it back unused. Once started, the extraction is
        # skipped where it has not begun when the client is gone or the post failed (`skip`).
        keyed = self.config.keyframes is not None
        if keyed:
            extractions.reserve(self.map_id)
        try:
            # Localised frames too: their thumbnail is kept in the recent ring only (never stored).
            encoding = pool.submit(body, hasher=self.hasher, backbone=self.config.backbone,
                                   thumbnail=self.config.thumbnails, resize=self.config.resize,
                                   key=self.map_id)
        except BaseException:
            if keyed:
                extractions.release(self.map_id)
            raise
        # A client gone before its frame reached a batch: the encoding is cancelled (its decode skipped
        # where not begun, its slot given back) and the post ends as ClientGone, not after the work.
        gone.when_set(encoding.cancel)
        skip = threading.Event()
        gone.when_set(skip.set)
        frame = None
        if keyed:  # the stream's camera: this frame's, else the last
            given = (metadata or {}).get("camera")
            camera = given or self.cameras.get(stream)
            try:
                frame = asyncio.wrap_future(extractions.start(
                    self.map_id, pool.encoders.get(self.config.backbone).decode, body,
                    self.config.sections.keyframes, camera, given is not None, skip))
            except BaseException:  # the extractions shut down: the pool skips the encoding if not begun
                encoding.cancel()
                raise
        # The digest stored with the row, off the event loop (a 10 MB raw frame takes ~20 ms to hash)
        # and beside the encoding.
        digest = asyncio.ensure_future(asyncio.to_thread(_sha256, getattr(body, "data", body)))
        before, mine = self._turn, asyncio.Event()
        self._turn = mine
        handed = False
        try:
            try:
                encoded = await asyncio.wrap_future(encoding)
            except asyncio.CancelledError:
                task = asyncio.current_task()
                if encoding.cancelled() and gone.is_set() and not (task and task.cancelling()):
                    raise ClientGone("the client went away before its frame was encoded") from None
                raise
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
                once = self.submit(self._restamped, self._apply_once, post, learn, apply)
            else:
                step = self.submit(self._restamped, apply)
            handed = True
        finally:
            if not handed:
                skip.set()
                _drop(frame)
            # A post that failed before its turn (its encoding taken back, a bad image) passes the turn on
            # only once the post before it has had its own: the one after it never reaches the writer
            # ahead of an older one still encoding.
            _pass_turn(before, mine)
        # A learned row (and the earlier reply of a repeated key, whose row may be in the same group) is
        # acknowledged only once durable: the writer committed it without its fsync (group commit).
        if post is not None:
            answer, restores = await asyncio.wrap_future(once)
            if learn:
                await self.durable()
                await self._still_held(restores, key=post.key, reply=answer.body)
            return answer if answer.replayed else dataclasses.replace(answer, thumbnail=thumb)
        result, restores = await asyncio.wrap_future(step)
        t_step = time.perf_counter()
        if learn:
            await self.durable()
            await self._still_held(restores, seq=result.seq, observation_id=result.observation_id)
        sync = {"sync": (time.perf_counter() - t_step) * 1e3} if learn else {}
        return dataclasses.replace(result, timings_ms={**front, **result.timings_ms, **sync}, thumbnail=thumb)

    def _restamped(self, fn: Callable[..., T], *args: Any) -> tuple[T, int]:
        """Writer: `fn(*args)` and the map's count of restores when it ran (`_still_held`)."""
        return fn(*args), self.restores

    async def _still_held(self, restores: int, *, key: str | None = None, reply: str | None = None,
                          seq: int | None = None, observation_id: str | None = None) -> None:
        """Event loop, once a learned post is durable: refuse to acknowledge it when a restore began after
        its step and the restored map does not hold it (docs/design/service.md §1.5). Such a restore
        rolled the map back past the post (it is in the pre-restore snapshot only), and a 200 would name
        what the map no longer holds. A restored snapshot taken after the step does hold it: the post's
        key with this `reply` (a keyed post, row or visit; the key alone may be a retry's, learned on the
        restored map), or its row's seq with its observation id (an unkeyed post, or a keyed one whose
        key the store has pruned since: it keeps the newest `idempotency_keys`). An unkeyed post
        consolidated into a visit has nothing to look it up by, so it is refused (posted again, it is
        one more visit of its place). The check runs on the writer, behind a restore still running.

        Raises:
            MapRestored: the post is not in the map; the client may post the frame again.
        """
        if self.restores == restores:
            return
        if not await asyncio.wrap_future(self.submit(self._holds, key, reply, seq, observation_id)):
            raise MapRestored(self.map_id, seq)

    def _holds(self, key: str | None, reply: str | None, seq: int | None, observation_id: str | None) -> bool:
        """Writer: the store holds the learned post stored under `key` with `reply`, or row `seq` as
        `observation_id` (for a keyed post, those its `reply` names)."""
        store = self.store
        if store is None:
            return False
        found = None if key is None else store.key_record(key)
        if found is not None:
            return found.reply == reply
        if reply is not None:  # a keyed post whose key was pruned: its row, as its reply names it
            sealed = json.loads(reply)
            seq, observation_id = sealed.get("seq"), sealed.get("observation_id")
        return seq is not None and store.observation_id(seq) == observation_id

    async def stored_reply(self, post: idempotency.IdempotentPost) -> idempotency.Reply | None:
        """Event loop: the reply of the learned post stored under `post`'s key (a retry), answered before
        any encoding once its row is durable; None when there is none, and `observe` answers it (its
        writer looks again: two posts of one key in flight at once).

        A restore that begins while the reply waits for its fsync may have rolled the post back: the
        key is then looked up again on the restored store (never the reply of a post the map no longer
        holds, docs/design/service.md §1.5).

        Raises:
            IdempotencyKeyReused: the key answered another request.
        """
        for _ in range(3):  # each look again needs a restore to finish meanwhile; past that, `observe`
            restores = self.restores
            store = self.store
            assert store is not None  # a ready map has its store
            earlier = await asyncio.to_thread(idempotency.lookup, store, None, post)
            if earlier is None:
                return None
            await self.durable()  # its row may be in a group not yet synced: a reply waits for it
            if self.restores == restores:
                return earlier
        return None

    def _apply_once(self, post: idempotency.IdempotentPost, learn: bool,
                    apply: Callable[[], ObservationResult]) -> idempotency.Reply:
        """Writer: `idempotency.apply_once` on the store as it is when this runs, not when the post was
        queued: a restore (or a failed commit's recovery) queued ahead closes that store and opens
        another."""
        # a map that failed meanwhile (no store, or the closed one a failed reopen left): refused as `apply`
        # would refuse it, with its state, not a closed store's 503 to retry for ever
        if self.store is None or not serving(self.state).reads:
            self.require_ready(learn)
        assert self.store is not None
        return idempotency.apply_once(self.store, self.keys, post, learn, apply)

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
            InsufficientStorage: no room to write a learning frame; nothing learned. The first such
                commit rebuilds the memory from the store; after it the map refuses learning before its
                step until room is made (`Room`).
            MapReadOnly: the store refuses a learning frame's write; as for InsufficientStorage, and the
                map is `read-only`. A localising frame is answered on either (its closure is not logged:
                `loop_closure_id` null).
        """
        self.require_ready(learn)
        assert self.store is not None and self.hasher is not None  # a map without them is never ready
        if projected.shape != (self.hasher.k,):
            raise ValueError(f"projection has shape {projected.shape}, this map's are ({self.hasher.k},)")
        self._admit(stream)
        if learn:  # a disk known full: refused here, the memory untouched, so no recovery to pay (`Room`)
            self.room.admit()
        if learn and (gone := forgetting.to_forget(self.index, self.place_map)):
            try:
                self._forget(gone)
            except (StorageFull, StoreReadOnly) as e:  # its store write comes first: nothing forgotten
                raise self._unwritten(e, "the rows to forget for this observation") from e
        if learn and self.budget is not None:  # the row's index bytes, before the step (a failed one is
            self.budget.grow_index(self.map_id, self.row_bytes)  # set right by the recovery it causes)
        try:
            result = self._step(projected, image_sha256, learn=learn, stream=stream, top_k=top_k,
                                label=label, metadata=metadata, thumbnail=thumbnail, post=post, query=query,
                                contrast=contrast, durable=durable)
        except Exception as e:
            if not learn:  # a localisation learns nothing: the memory and the store still agree
                raise
            # The TM may hold a learned step the store does not (a failed commit, or a failure anywhere
            # between the step and the commit): rebuild from the store before anything else runs, so
            # no later row is learned on a memory that replay cannot reproduce (docs/design/service.md §4.3).
            assert self.store is not None
            self.state, self.state_reason = "recovering", "step-failed"
            self.store.close()
            self.recover()
            # A file made immutable under the open store fails its write as "disk I/O error", which reads
            # as no room; the reopen asks the OS (`MapStore.writable`) and says read-only: that is the
            # answer, as for every later post, not a 507 that room would cure.
            if isinstance(e, StoreReadOnly | StorageFull) or serving(self.state).read_only:
                raise self._unwritten(e, "the observation") from e
            raise
        if learn:
            self.room.stored()
        return result

    def _unwritten(self, e: Exception, what: str) -> MapReadOnly | InsufficientStorage:
        """Writer: the refusal of a learning frame whose store write `e` failed, nothing learned: read-only
        where SQLite or the OS says the file refuses writes (the map becomes `read-only`; recovery marks it
        too where the OS says so), else no room (`Room`: the next learning posts are refused before their
        step). `what` failed to be stored."""
        if isinstance(e, StoreReadOnly) or serving(self.state).read_only:
            if serving(self.state).learns:
                self.read_only()
            return MapReadOnly(self.map_id, "the observation (nothing was learned)")
        self.room.failed(str(e))
        # (SQLite's own words beside ours: its failed write may be a quota, a file-size limit or a failing
        # disk, which it does not tell apart; storage._common.is_full_error)
        return InsufficientStorage(f"{what} could not be stored: no room to write ({e}); nothing was learned")

    def _log_closure(self, closure: NewClosure) -> int | None:
        """Log a localising stream's loop closure: its log id (a retry's is its first post's entry), None
        where it was not logged. A map whose storage refuses writes, or has no room to write, still
        answers: the frame learned nothing, so only its log entry is lost (docs/design/service.md §4.3).
        A read-only file is not tried again once the map is `read-only` (that lasts until a restart), and
        the map becomes `read-only` once, from the first refusal; a full disk is tried at every closure
        (room may be made) and said once until a closure is logged again. Either way the log says it
        once, not per frame."""
        assert self.store is not None
        if serving(self.state).read_only:
            return None
        try:
            logged = self.store.add_closure(closure)
        except StoreReadOnly:
            self.read_only()
            return None
        except StorageFull as e:
            if not self._closures_unlogged:
                log.error("map %s: no room to log loop closures (%s): localising revisits are answered, "
                          "their closures not logged, until room is made", self.map_id, e)
            self._closures_unlogged = True
            return None
        self._closures_unlogged = False
        return logged

    def _step(self, projected: np.ndarray, image_sha256: str, *, learn: bool, stream: str, top_k: int,
              label: str | None, metadata: dict[str, Any] | None, thumbnail: bytes | None,
              post: idempotency.IdempotentPost | None,
              query: keyframes.QueryFrame | None = None, contrast: float | None = None,
              durable: bool = True) -> ObservationResult:
        """Writer: `apply` after its checks: the pure step (`models.pipeline.observe`), the reply from
        the stored rows it names and what it made (`records`), then, durable before the reply, the
        visit, the row or a localising stream's loop closure. An exception here while learning is
        rebuilt from by `apply` (the step already holds the row in the index and links)."""
        assert self.store is not None
        st, evicted = touch(self.streams, stream, self.settings.max_streams, self.clock())
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
            if len(self.cameras) > self.settings.max_streams:  # bounded: the cameras of the streams held
                self.cameras = {k: v for k, v in self.cameras.items() if k in self.streams}
        row = None if seq is None else records.learned_row(
            step, stream=stream, image_sha256=image_sha256, label=label, metadata=metadata,
            thumbnail=thumbnail, query=query, resume=resume)
        answer = None if place is None else self._verified(
            PlaceResult.of(place, rows[place.seq], self.config.revisit_threshold), query, stream)
        # The answer is whole before the commit, so an idempotent post's reply commits with its row.
        result = records.reply(self.config, self.map_id, step, rows, stream=stream, learn=learn, seq=seq,
                               row=row, place=answer, metadata=metadata,
                               map_seq=seq or self.store.last_seq())
        # A revisit is a loop closure, logged durably: with the learned row in its transaction, or alone
        # for a localising stream (it stores no observation and changes no memory; §11.6), where it can.
        # A localising closure is logged alone, so its key keeps a retry from logging it twice. A learned
        # one commits with its row or visit, whose key answers a retry: keyed too, it would collide with an
        # entry its key logged before (a localising pass of the same keys, or a retry past the kept keys),
        # be dropped, and leave the reply naming an id the next closure gets.
        closure = records.loop_closure(result, stream=stream, metadata=metadata,
                                       key=post.key if post is not None and not learn else None)
        if closure is not None and learn:  # its log id, in the reply (a learned post's is sealed into the
            # commit that logs it, so it is told before: the writer is the log's only writer)
            result = dataclasses.replace(result, loop_closure_id=self.store.next_closure_id())
        if step.visit is not None:  # durable before the reply: the replay needs it (service.md §4.4)
            self.store.add_visit(records.visit(step, stream=stream, metadata=metadata, closure=closure,
                                               key=None if post is None else post.record(result),
                                               resume=resume))
            self._committed()
        elif row is None and closure is not None:
            result = dataclasses.replace(result, loop_closure_id=self._log_closure(closure))
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
        visits it covers beyond the last `visits` kept are pruned (docs/design/science.md §11.8), and the
        stream states it holds (docs/design/service.md §4.4)."""
        assert self.store is not None
        self.since_snapshot += 1
        if self.settings.snapshot_every and self.since_snapshot >= self.settings.snapshot_every:
            self._auto_snapshot()
            if self.since_snapshot == 0:  # it was taken
                # Only room is at stake: the post's row is committed, so a failure here (the snapshot
                # took the disk's last room) must not turn its answer into "nothing was learned" (a
                # review); the next snapshot prunes again.
                try:
                    self.store.prune_visits(self.covered, self.settings.visits)
                    self.store.prune_stream_states(self.store.last_seq())
                except (StorageError, sqlite3.Error) as e:
                    log.warning("map %s: pruning the visit log after a snapshot failed (%s); the rows "
                                "stay durable, the next snapshot prunes", self.map_id, e)

    def _forget(self, gone: list[int]) -> None:
        """Writer: the hard cap binds (`max_observations` rows held): forget `gone`, the rows the rule
        chose (`forgetting.to_forget`: the least recently used places, whole, at least `forget_percent` %),
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
        v = keyframes.verify_candidate(self.store, self.place_map.graph, place.seq, place.stream, query,
                                       stream=stream, neighbours=self.settings.verify_neighbours)
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


def _drop(frame: asyncio.Future | None) -> None:
    """An extraction whose post failed: its outcome is read when it ends, so that nothing logs it as
    never retrieved (left to run: one not yet begun is skipped, and gives its slot back when done)."""
    if frame is not None:
        frame.add_done_callback(lambda f: f.cancelled() or f.exception())


_RELAYS: set[asyncio.Task] = set()  # the pending `_pass_turn` tasks (the loop keeps weak references)


def _pass_turn(before: asyncio.Event, mine: asyncio.Event) -> None:
    """Set `mine` (a post's turn done) now if `before` (the turn before it) is set, else once it is."""
    if before.is_set():
        mine.set()
        return

    async def relay() -> None:
        await before.wait()
        mine.set()

    task = asyncio.ensure_future(relay())
    _RELAYS.add(task)
    task.add_done_callback(_RELAYS.discard)


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()
