"""Map runtimes: one writer per map, the TM step, ranking, the commit, and recovery by replay.

docs/design/service.md §1.2–§1.4, §4.3–§4.4, §6. Each map owns a Temporal Memory, its sLSBH hasher (its own
persisted projection), a `MapStore` (system of record) and an inverted index over winner cells. All
work on a map runs in that map's single writer thread, in submission order, so the memory sees frames
in arrival order and never two at once; different maps proceed in parallel.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import logging
import re
import shutil
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from models import presets
from models.frontend import slsbh
from models.frontend.adaptation import RunningMean
from models.memory.temporal_memory import TemporalMemory, planned_bytes, validate
from service import recovery
from service.errors import Problem
from service.recovery import Stream
from storage import snapshots
from storage._common import StorageFull, utc_now
from storage.catalog import MAP_ID_RE, Catalog, MapExists, MapRecord, SnapshotRecord
from storage.index import IndexFull, InvertedIndex
from storage.index import warm_up as index_warm_up
from storage.mapstore import MapMeta, MapStore, NewObservation, StoreCorrupt, cell_dtype_for

log = logging.getLogger("cortexloc.runtime")
T = TypeVar("T")

STREAM_RE = re.compile(r"^[A-Za-z0-9._-]{1,64}$")
_LISTED = 20  # divergent seqs listed in a recovery note (the count says how many there are)


def resolve_params(preset: str, *, seed: int | None = None, tm: dict[str, Any] | None = None,
                   slsbh_conf: dict[str, Any] | None = None, exclude_recent: int = 0) -> dict[str, Any]:
    """Freeze a map's parameters: preset <- overrides (docs/design/service.md §1.1), every value checked
    against the section models (`presets.TmParams`, `presets.SlsbhParams`: names, types, ranges) and the rules
    between them, before anything is converted or allocated.

    Args:
        preset: a preset name with a `tm` section.
        seed: overrides `tm.seed` (and so the projection's seed unless `slsbh.seed` is given).
        tm, slsbh_conf: the request's overrides, as sent.
        exclude_recent: frozen into the map.

    Returns:
        {"preset", "tm", "slsbh", "seed", "exclude_recent", "warnings"}.

    Raises:
        Problem: 422 invalid-configuration with `errors` [{location, name, message}] naming each
            offending parameter (`tm.<name>`, `slsbh.<name>`), or the unknown preset.
    """
    errors: list[dict[str, str]] = []

    def collect(e: presets.ParamsError) -> None:
        errors.extend({"location": "body", "name": f"{e.section}.{name}", "message": message}
                      for name, message in e.errors)

    warnings: list[str] = []
    tm_params: dict[str, Any] = {}
    try:
        base = presets.get(preset)
        tm_params = presets.tm_params(preset, {**(tm or {}), **({} if seed is None else {"seed": seed})})
        warnings = validate(tm_params)
    except presets.ParamsError as e:
        collect(e)
    except (KeyError, ValueError) as e:  # no such preset, or one without a TM
        msg = str(e).strip("'\"")
        raise Problem(422, "invalid-configuration", msg,
                      errors=[{"location": "body", "name": "preset", "message": msg}]) from e
    s_conf = {**presets.SlsbhParams().model_dump(), **base.get("slsbh", {}), **(slsbh_conf or {})}
    try:
        presets.check_section(presets.SlsbhParams, "slsbh", s_conf)
    except presets.ParamsError as e:
        collect(e)
    if errors:
        raise Problem(422, "invalid-configuration", "; ".join(f"{e['name']}: {e['message']}" for e in errors),
                      errors=errors)
    if s_conf["seed"] is None:
        s_conf["seed"] = tm_params["seed"]
    try:
        slsbh.n_ones(s_conf["k"], s_conf["s"])
    except ValueError as e:
        errors.append({"location": "body", "name": "slsbh.s", "message": str(e)})
    if s_conf["k"] * 2 != tm_params["columnDimensions"]:
        errors.append({"location": "body", "name": "slsbh.k",
                       "message": f"2k must equal columnDimensions ({tm_params['columnDimensions']})"})
    if errors:
        raise Problem(422, "invalid-configuration", "; ".join(e["message"] for e in errors), errors=errors)
    return {"preset": preset, "tm": tm_params, "slsbh": s_conf, "seed": tm_params["seed"],
            "exclude_recent": int(exclude_recent), "warnings": warnings}


def snapshot_resource(rec: SnapshotRecord) -> dict[str, Any]:
    return {"snapshot_id": rec.snapshot_id, "seq": rec.seq, "kind": rec.kind, "created_at": rec.created_at,
            "bytes": rec.bytes, "manifest_sha256": rec.manifest_sha256}


class MapRuntime:
    """One map in memory, with its single writer thread.

    Public methods run in the writer thread through `run`; the state lives in
    `state` (`ready` | `recovering` | `failed`) and `state_reason`.
    """

    def __init__(self, record: MapRecord, map_dir: Path, projections_dir: Path, catalog: Catalog,
                 feature_dim: int, max_streams: int, max_observations: int,
                 snapshot_every: int = 0, snapshot_keep: int = 3) -> None:
        self.record = record
        self.map_id = record.map_id
        self.params = record.params
        self.dir = map_dir
        self.catalog = catalog
        self.max_streams = max_streams
        self.snapshot_every = snapshot_every
        self.snapshot_keep = snapshot_keep
        self.state = "recovering"
        self.state_reason: str | None = None
        # What the last recovery did (`recover`); the last automatic snapshot's failure, if it failed.
        self.recovery: dict[str, Any] | None = None
        self.snapshot_error: dict[str, Any] | None = None
        self.snapshot_failures = 0
        self.streams: OrderedDict[str, Stream] = OrderedDict()
        self._writer = ThreadPoolExecutor(1, thread_name_prefix=f"map-{self.map_id}")
        sha = self.params["projection_sha256"]
        self.projection_path = projections_dir / f"{sha}.npy"
        self.hasher: slsbh.Hasher | None = None
        self.adapt_tau = int(self.params["slsbh"].get("adapt_tau", 0))  # maps made before it: none
        self._projection_error: str | None = None
        # the checksum is verified on load: a map never runs on another matrix (docs/design/science.md §7)
        try:
            projection = slsbh.load_projection(self.projection_path, sha,
                                               shape=(feature_dim, int(self.params["slsbh"]["k"])))
            self.hasher = slsbh.Hasher(projection, float(self.params["slsbh"]["s"]))
        except (slsbh.ProjectionError, OSError) as e:
            self._projection_error = str(e)
        self.tm = TemporalMemory(self.params["tm"])
        self.index = InvertedIndex(self.tm.n_cells, max_observations)
        self.store: MapStore | None = None

    # ------------------------------------------------------------------ writer

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """Run `fn(*args)` in this map's writer thread, after everything submitted before it."""
        return await asyncio.wrap_future(self.submit(fn, *args))

    def submit(self, fn: Callable[..., T], *args: Any) -> Future[T]:
        try:
            return self._writer.submit(fn, *args)
        except RuntimeError as e:  # the writer was shut down: the map was deleted meanwhile
            raise Problem(404, "map-not-found", f"no map {self.map_id!r}", map_id=self.map_id) from e

    def close(self, snapshot: bool = True) -> None:
        """Drain the writer; at a clean shutdown take an automatic snapshot if anything is new.

        "New" includes a stream that switched to localisation: that switch is not in the rows, and the
        snapshot carries it (a localisation stream comes back empty, so its next mapping step starts a
        new sequence as it would have without the restart).
        """
        self._writer.shutdown(wait=True)
        if self.store is None:
            return
        latest = self.catalog.list_snapshots(self.map_id)
        new_rows = self.store.last_seq() > (latest[0].seq if latest else 0)
        switched = any(st.learning is False for st in self.streams.values())
        if snapshot and self.state == "ready" and self.snapshot_every and (new_rows or switched):
            try:
                self.snapshot("auto")
                self._prune_auto(self.snapshot_keep)
            except Exception:  # the rows are durable; a snapshot only shortens the next replay
                log.exception("map %s: shutdown snapshot failed", self.map_id)
        self.store.close()

    def snapshots(self) -> list[dict[str, Any]]:
        return [snapshot_resource(r) for r in self.catalog.list_snapshots(self.map_id)]

    def snapshot_dir(self, snapshot_id: str) -> Path:
        rec = self.catalog.get_snapshot(self.map_id, snapshot_id)
        if rec is None:
            raise Problem(404, "snapshot-not-found", f"no snapshot {snapshot_id!r} of map {self.map_id!r}",
                          map_id=self.map_id)
        return self.catalog.snapshot_dir(rec)

    # ------------------------------------------------------------------ memory state

    def memory_state(self) -> dict[str, np.ndarray]:
        """The whole memory as arrays: TM, generator, every stream's context and bookkeeping."""
        return recovery.memory_state(self.tm, self.streams)

    # ------------------------------------------------------------------ snapshots

    def snapshot(self, kind: str = "manual") -> dict[str, Any]:
        """A consistent cut at the current seq, taken by the writer (docs/design/service.md §1.5, §4.4).

        Raises:
            Problem: 507 insufficient-storage when the disk is full (nothing is left behind).
        """
        assert self.store is not None
        sid = snapshots.new_snapshot_id()
        dest = self.dir / "snapshots" / sid
        dest.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        try:
            m = snapshots.create_snapshot(self.store, self.memory_state(), dest, kind=kind,
                                          external={"projection.npy": self.projection_path})
        except StorageFull as e:
            raise Problem(507, "insufficient-storage", f"the {kind} snapshot could not be written: the "
                          "disk is full; the map is unchanged") from e
        rec = self.catalog.register_snapshot(SnapshotRecord(
            snapshot_id=m.snapshot_id, map_id=self.map_id, seq=m.seq, kind=kind, created_at=m.created_at,
            bytes=m.bytes, manifest_sha256=m.manifest_sha256, path=str(dest)))
        log.info("map %s: %s snapshot %s at seq %d in %.2f s", self.map_id, kind, sid, m.seq,
                 time.perf_counter() - t0)
        return snapshot_resource(rec)

    def _auto_snapshot(self) -> None:
        """The periodic snapshot after a commit. It only shortens the next recovery, so a failure
        (typically a full disk) is logged, counted and shown in /readyz, never the request's error:
        the row it follows is durable and acknowledged."""
        try:
            self.snapshot("auto")
            self._prune_auto(self.snapshot_keep)
        except Exception as e:  # any failure: see the docstring
            self.snapshot_failures += 1
            self.snapshot_error = {"seq": self.store.last_seq() if self.store else 0, "at": utc_now(),
                                   "error": getattr(e, "detail", None) or str(e) or type(e).__name__}
            log.exception("map %s: automatic snapshot failed; the rows stay durable", self.map_id)
        else:
            self.snapshot_error = None

    def _prune_auto(self, keep: int) -> None:
        for rec in self.catalog.list_snapshots(self.map_id, kind="auto")[keep:]:
            self.catalog.delete_snapshot(self.map_id, rec.snapshot_id)
            shutil.rmtree(self.catalog.snapshot_dir(rec), ignore_errors=True)

    def restore(self, snapshot_id: str) -> dict[str, Any]:
        """Roll the map back to a snapshot, after keeping the present in a pre-restore snapshot."""
        assert self.store is not None
        rec = self.catalog.get_snapshot(self.map_id, snapshot_id)
        if rec is None:
            raise Problem(404, "snapshot-not-found", f"no snapshot {snapshot_id!r} of map {self.map_id!r}",
                          map_id=self.map_id)
        path = self.catalog.snapshot_dir(rec)
        m = snapshots.verify(path)  # refuse a damaged snapshot before touching anything
        before = self.store.count()
        self.snapshot("pre-restore")
        self.catalog.bump_high_water(self.map_id, self.store.next_seq() - 1)
        self.store.close()
        MapStore.install_copy(path / snapshots.DB_FILE, self.dir / "map.sqlite")
        self.store = MapStore.open(self.dir / "map.sqlite",
                                   seq_floor=self.catalog.get_high_water(self.map_id))
        self._install(recovery.rebuild(snapshots.load_memory(path), self.store.rows(after_seq=m.seq),
                                       adapt_tau=self.adapt_tau))
        out = self.resource()
        out["discarded_observations"] = before - self.store.count()
        return out

    # ------------------------------------------------------------------ recovery

    def recover(self) -> None:
        """Open the store and rebuild the memory: the newest usable snapshot, then a verified replay of
        the rows after it (docs/design/service.md §4.4).

        A snapshot that does not verify, cannot be loaded, or whose replay does not reproduce the
        stored winner cells is passed over for the next older one (one from a branch a restore
        abandoned is skipped silently). The last resort is a replay from the first row on the fresh
        `self.tm` (as `__init__` and the commit-failure path leave it); it serves the memory it
        rebuilds and lists the rows whose stored winner cells it did not reproduce. What happened is
        in `self.recovery` (map resource, /readyz) and the log; only an unreadable store or
        projection fails the map.
        """
        if self.hasher is None:
            self._fail("projection-invalid", self._projection_error or "no projection")
            return
        if (self.dir / "snapshots").is_dir():  # a crash during a snapshot leaves only a temporary dir
            snapshots.remove_stale_temp(self.dir / "snapshots")
        try:
            self.store = MapStore.open(self.dir / "map.sqlite",
                                       seq_floor=self.catalog.get_high_water(self.map_id))
            if not self.store.quick_check():
                raise StoreCorrupt("quick_check failed")
        except StoreCorrupt as e:
            self._fail("database-corrupt", str(e))
            return
        t0 = time.perf_counter()
        skipped: list[dict[str, str]] = []
        for rec in self.catalog.list_snapshots(self.map_id):
            path = self.catalog.snapshot_dir(rec)
            try:
                m = snapshots.verify(path)
                if m.seq > 0:
                    row = self.store.get(m.seq)
                    if row is None or row.observation_id != m.last_observation_id:
                        continue  # from a branch a restore abandoned
                done = recovery.rebuild(snapshots.load_memory(path), self.store.rows(after_seq=m.seq),
                                        adapt_tau=self.adapt_tau)
            except Exception as e:  # an unusable snapshot is passed over, never fatal
                reason = str(e) or type(e).__name__
            else:
                if not done.mismatches:
                    note: dict[str, Any] = {"source": "snapshot", "snapshot_id": rec.snapshot_id,
                                            "snapshot_seq": m.seq}
                    break
                reason = f"the replay after it diverged at seq {done.mismatches[0]}"
                del done  # its memory is as large as the map's: free it before the next attempt
            skipped.append({"snapshot_id": rec.snapshot_id, "reason": reason})
            log.warning("map %s: snapshot %s passed over: %s", self.map_id, rec.snapshot_id, reason)
        else:
            done = recovery.rebuild(self.tm, self.store.rows(), stop_at_mismatch=False)
            note = {"source": "replay", "mismatches": len(done.mismatches),
                    "mismatched_seqs": done.mismatches[:_LISTED]}
            if done.mismatches:
                log.error("map %s: the replay from the first row did not reproduce the stored winner cells "
                          "of %d row(s), first seq %d; serving the replayed memory (run `cortexloc verify`)",
                          self.map_id, len(done.mismatches), done.mismatches[0])
        self._install(done)
        note.update(replayed=done.replayed, skipped_snapshots=skipped,
                    seconds=round(time.perf_counter() - t0, 3))
        self.recovery = note
        self.state, self.state_reason = "ready", None
        log.info("map %s ready: %s", self.map_id, note)

    def _install(self, done: recovery.Rebuilt) -> None:
        """Serve a rebuilt memory: its TM and streams, and the index rebuilt from the store."""
        assert self.store is not None
        self.tm, self.streams = done.tm, done.streams
        self.index = InvertedIndex(self.tm.n_cells, self.index.max_observations)
        self.index.rebuild(self.store.rows())

    def _fail(self, reason: str, detail: str) -> None:
        self.state, self.state_reason = "failed", reason
        self.catalog.set_state(self.map_id, "failed", reason)
        log.error("map %s failed (%s): %s", self.map_id, reason, detail)

    def require_ready(self) -> None:
        if self.state != "ready":
            raise Problem(503, "map-unavailable", f"map {self.map_id!r} is {self.state}"
                          + (f" ({self.state_reason})" if self.state_reason else ""),
                          state=self.state, state_reason=self.state_reason)

    # ------------------------------------------------------------------ streams

    def _stream(self, name: str) -> Stream:
        st = self.streams.get(name)
        if st is None:
            st = Stream()
            self.streams[name] = st
            while len(self.streams) > self.max_streams:
                self.streams.popitem(last=False)  # the least recently used context is dropped (a reset)
        self.streams.move_to_end(name)
        return st

    def reset_stream(self, name: str) -> dict[str, Any]:
        """Break the stream's sequence (the next frame starts a new one); its adaptation is kept,
        because it describes the camera and the conditions, not where the robot is."""
        st = self.streams.get(name)
        had = st is not None and st.context.active_cells.size > 0
        if st is not None:
            st.context.reset()
            st.step, st.last_learned_seq = 0, None
        return {"stream": name, "had_context": bool(had)}

    # ------------------------------------------------------------------ observations

    def observe(self, features: np.ndarray, image_sha256: str, *, learn: bool, stream: str, top_k: int,
                label: str | None, projected: np.ndarray | None = None) -> dict[str, Any]:
        """One frame: TM step on the stream's context, ranking, and for learning the durable commit.

        Args:
            features: (D,) L2-normalised backbone features of the frame.
            projected: (k,) features · this map's projection, when already computed (the encoder pool
                projects batches, `service.encoding`); None: projected here.

        Returns:
            The observation part of the response (docs/design/service.md §1.2).
        """
        self.require_ready()
        assert self.store is not None
        if learn and len(self.index) >= self.index.max_observations:
            raise Problem(409, "map-full", f"map {self.map_id!r} holds its maximum of "
                          f"{self.index.max_observations} observations; localisation still works",
                          max_observations=self.index.max_observations)
        t0 = time.perf_counter()
        assert self.hasher is not None  # a map without its projection is failed, never ready
        if projected is None:
            projected = self.hasher.project(features)
        elif projected.shape != (self.hasher.k,):
            raise ValueError(f"projection has shape {projected.shape}, this map's are ({self.hasher.k},)")
        st = self._stream(stream)
        if self.adapt_tau:
            # The adapted stream's code; a crash loses the means since the last snapshot (they are
            # not in the store), which costs about tau frames of weaker codes, never a stored row.
            st.adapt = st.adapt or RunningMean(self.adapt_tau)
            projected = st.adapt.subtract(projected)
        code = slsbh.hash_projected(projected[None, :], self.hasher.s)[0]
        t1 = time.perf_counter()
        if learn and st.learning is False:
            st.context.reset()  # a switch to mapping starts a new sequence: replay relies on it
            st.step, st.last_learned_seq = 0, None
        if st.context.active_cells.size == 0:
            st.step, st.last_learned_seq = 0, None
        winners = self.tm.compute(code, learn=learn, context=st.context)
        stats = st.context.stats.as_dict()
        t2 = time.perf_counter()
        exclude_recent = int(self.params.get("exclude_recent", 0))
        matches = self.index.rank(winners, top_k, exclude_recent_stream=stream if exclude_recent else None,
                                  exclude_recent=exclude_recent) if top_k > 0 else []
        t3 = time.perf_counter()
        seq = obs_id = None
        if learn:
            row = NewObservation(stream=stream, image_sha256=image_sha256,
                                 input_sdr=code.astype(np.int64), winner_cells=winners,
                                 context_prev_seq=st.last_learned_seq, label=label)
            try:
                seq = self.store.append(row)
            except Exception as e:
                # The TM learned a step that is not on disk: rebuild from the store before any other.
                self.state, self.state_reason = "recovering", "commit-failed"
                self.store.close()
                self.tm = TemporalMemory(self.params["tm"])
                self.index = InvertedIndex(self.tm.n_cells, self.index.max_observations)
                self.streams.clear()
                self.recover()
                if isinstance(e, StorageFull):
                    raise Problem(507, "insufficient-storage", "the observation could not be stored: the "
                                  "disk is full; nothing was learned") from e
                raise
            obs_id = row.observation_id
            with contextlib.suppress(IndexFull):  # checked above; the row is durable either way
                self.index.add(seq, winners, stream)
            st.last_learned_seq = seq
        # The step is recorded before the automatic snapshot, so the snapshot holds the stream as it
        # is after this frame (a snapshot taken before would hold a stream that just switched back to
        # mapping as localising, and recovery would drop the context the next row continues).
        st.learning = learn
        st.step += 1
        if learn and self.snapshot_every and seq is not None and seq % self.snapshot_every == 0:
            self._auto_snapshot()
        t4 = time.perf_counter()
        rows = self.store.get_many(m.seq for m in matches) if matches else {}
        return {
            "learned": learn, "observation_id": obs_id, "seq": seq,
            "sequence": {"step": st.step - 1, "active_columns": stats["active_columns"],
                         "predicted_columns": stats["predicted_columns"],
                         "bursting_columns": stats["bursting_columns"],
                         "winner_cells": stats["winner_cells"]},
            "matches": [{"rank": i + 1, "observation_id": rows[m.seq].observation_id, "seq": m.seq,
                         "stream": rows[m.seq].stream, "label": rows[m.seq].label,
                         "created_at": rows[m.seq].created_at, "overlap": int(m.overlap),
                         "score": float(m.score)} for i, m in enumerate(matches)],
            "timings_ms": {"hash": (t1 - t0) * 1e3, "tm": (t2 - t1) * 1e3, "search": (t3 - t2) * 1e3,
                           "store": (t4 - t3) * 1e3},
            "map_seq": self.store.last_seq(),
        }

    # ------------------------------------------------------------------ resources

    def resource(self) -> dict[str, Any]:
        p = self.params
        return {"map_id": self.map_id, "created_at": self.record.created_at, "state": self.state,
                "state_reason": self.state_reason, "preset": p["preset"],
                "params": {"tm": p["tm"], "slsbh": p["slsbh"], "seed": p["seed"],
                           "exclude_recent": p["exclude_recent"]},
                "encoder": p["encoder_id"], "projection_sha256": p["projection_sha256"],
                "observations": len(self.index), "last_seq": self.store.last_seq() if self.store else 0,
                "streams": list(self.streams), "warnings": p.get("warnings", []),
                "recovery": self.recovery, "snapshot_error": self.snapshot_error}

    def memory(self) -> dict[str, Any]:
        size = self.tm.size()
        store = self.store
        return {
            "tm": {"columns": size["columns"], "cells_per_column": self.tm.cells_per_column,
                   "cells": size["cells"],
                   "max_segments_per_cell": int(self.params["tm"]["maxSegmentsPerCell"]),
                   "max_synapses_per_segment": int(self.params["tm"]["maxSynapsesPerSegment"]),
                   "segments": size["segments"], "segment_capacity": size["segment_capacity"],
                   "synapses": size["synapses"], "synapse_capacity": size["synapse_capacity"],
                   "allocated_bytes": size["bytes"], "evicted_segments_total": size["evictions"],
                   "overrun_synapses_total": size["overrun_destroyed"]},
            "index": {"observations": len(self.index), "max_observations": self.index.max_observations,
                      "postings": self.index.postings(), "bytes": self.index.nbytes()},
            "streams": {"count": len(self.streams), "max": self.max_streams,
                        "bytes": sum(sum(v.nbytes for v in s.context.state_dict().values())
                                     for s in self.streams.values())},
            "projection_bytes": self.projection_path.stat().st_size if self.projection_path.exists() else 0,
            "storage": {"db_bytes": store.db_bytes() if store else 0,
                        "wal_bytes": store.wal_bytes() if store else 0,
                        "snapshots_bytes": self.catalog.snapshots_bytes(self.map_id)},
        }

    def tm_digest(self) -> str:
        """SHA-256 over the learned arrays and generator state (tests: 'nothing changed')."""
        h = hashlib.sha256()
        for k, v in sorted(self.tm.state_dict().items()):
            if not k.startswith("ctx."):
                h.update(k.encode())
                h.update(np.ascontiguousarray(v).tobytes())
        return h.hexdigest()


def _warm_up() -> None:
    """Compile the TM and index kernels now (numba, cached on disk), not during the first client's request."""
    tm = TemporalMemory({"columnDimensions": 64, "cellsPerColumn": 4, "maxSegmentsPerCell": 2,
                         "maxSynapsesPerSegment": 4, "activationThreshold": 2, "minThreshold": 1})
    for x in ([1, 2, 3], [4, 5, 6], [1, 2, 3], [4, 5, 6]):
        tm.compute(np.array(x), learn=True)
    tm.compute(np.array([1, 2, 3]), learn=False)
    index_warm_up()


class MapRegistry:
    """All maps of one data directory: the catalog, the projections, and a runtime per map."""

    def __init__(self, data_dir: Path, encoder: Any, settings: Any) -> None:
        self.data_dir = Path(data_dir)
        self.encoder = encoder
        self.settings = settings
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.catalog = Catalog.open(self.data_dir / "catalog.sqlite")
        self.projections = self.data_dir / "projections"
        self.projections.mkdir(parents=True, exist_ok=True)
        self.maps: dict[str, MapRuntime] = {}
        self._create_lock = threading.Lock()

    def _runtime(self, record: MapRecord) -> MapRuntime:
        s = self.settings
        return MapRuntime(record, self.data_dir / "maps" / record.map_id, self.projections, self.catalog,
                          self.encoder.feature_dim, s.max_streams, s.max_observations,
                          s.snapshot_every, s.snapshot_keep)

    def start(self) -> None:
        """Open every map and recover it by replay; create `default` on a fresh install."""
        _warm_up()
        for record in self.catalog.list_maps():
            rt = self._runtime(record)
            self.maps[record.map_id] = rt
            if record.params.get("encoder_id") != self.encoder.identity:
                rt.state, rt.state_reason = "failed", "encoder-mismatch"
                log.error("map %s was built with encoder %s, this server runs %s", record.map_id,
                          record.params.get("encoder_id"), self.encoder.identity)
                continue
            rt.recover()
        if not self.maps:
            self.create("default", preset=self.settings.default_preset)

    def close(self) -> None:
        for rt in self.maps.values():
            rt.close()
        self.catalog.close()

    def get(self, map_id: str) -> MapRuntime:
        rt = self.maps.get(map_id)
        if rt is None:
            raise Problem(404, "map-not-found", f"no map {map_id!r}", map_id=map_id)
        return rt

    def create(self, map_id: str, *, preset: str, seed: int | None = None, tm: dict[str, Any] | None = None,
               slsbh_conf: dict[str, Any] | None = None, exclude_recent: int = 0) -> MapRuntime:
        """Create a map: resolve and freeze parameters, persist the projection, then the store (§1.1)."""
        if not MAP_ID_RE.match(map_id):
            raise Problem(400, "invalid-parameter", f"map_id {map_id!r} must match {MAP_ID_RE.pattern}",
                          errors=[{"location": "body", "name": "map_id", "message": "invalid identifier"}])
        params = resolve_params(preset, seed=seed, tm=tm, slsbh_conf=slsbh_conf,
                                exclude_recent=exclude_recent)
        need = planned_bytes(params["tm"])
        if need > self.settings.max_map_bytes:
            raise Problem(422, "map-too-large", f"this configuration preallocates {need} bytes, more than "
                          f"CORTEXLOC_MAX_MAP_BYTES={self.settings.max_map_bytes}",
                          required_bytes=need, max_bytes=self.settings.max_map_bytes)
        with self._create_lock:
            if map_id in self.maps:
                raise Problem(409, "map-exists", f"map {map_id!r} exists", map_id=map_id)
            if len(self.maps) >= self.settings.max_maps:
                raise Problem(409, "map-limit", f"at most {self.settings.max_maps} maps",
                              max_maps=self.settings.max_maps)
            s_conf = params["slsbh"]
            P = slsbh.make_projection(self.encoder.feature_dim, int(s_conf["k"]), int(s_conf["seed"]))
            _, sha = slsbh.save_projection(P, self.projections)
            del P
            params["projection_sha256"] = sha
            params["encoder_id"] = self.encoder.identity
            if self.encoder.identity.split("/")[1].startswith("random"):
                log.warning("map %s is created on RANDOM encoder weights (%s)", map_id, self.encoder.identity)
            map_dir = self.data_dir / "maps" / map_id
            if map_dir.exists():
                shutil.rmtree(map_dir)  # leftovers of a creation that never reached the catalog
            map_dir.mkdir(parents=True)
            store = MapStore.create(map_dir / "map.sqlite", MapMeta(
                map_id=map_id, params=params, projection_sha256=sha, encoder_id=self.encoder.identity,
                cell_dtype=cell_dtype_for(int(params["tm"]["columnDimensions"])
                                          * int(params["tm"]["cellsPerColumn"]))))
            store.close()
            try:
                record = self.catalog.create_map(map_id, params, preset=preset, state="ready")
            except MapExists as e:
                raise Problem(409, "map-exists", f"map {map_id!r} exists", map_id=map_id) from e
            rt = self._runtime(record)
            rt.recover()
            self.maps[map_id] = rt
            return rt

    def import_snapshot(self, tar_path: Path, max_bytes: int) -> str:
        """Create a map from a downloaded snapshot tar (`cortexloc import`, server stopped).

        The manifest (the tar's first member) is checked before anything is written: its ids follow
        the API's rules (`storage.snapshots`), the map is new here, and the files it declares fit in
        `max_bytes` and in the free space of the data directory. Every checksum is then verified (the
        snapshot's files, and the projection against the map's recorded SHA-256) before anything is
        registered; the map recovers from that snapshot when the server starts.

        Returns:
            The imported map's id.

        Raises:
            SnapshotInvalid: a bad or too large tar. ValueError: the map exists, or no projection.
        """
        maps_dir = self.data_dir / "maps"

        def acceptable(m: snapshots.Manifest) -> None:
            if self.catalog.get_map(m.map_id) is not None:
                raise ValueError(f"map {m.map_id!r} exists here already")
            need = sum(e.bytes for e in (*m.files.values(), *m.external.values()))
            free = shutil.disk_usage(self.data_dir).free
            if need > free:
                raise ValueError(f"the snapshot needs {need} bytes, {self.data_dir} has {free} free")

        staging = maps_dir / f".import-{snapshots.new_snapshot_id()}"
        with tar_path.open("rb") as f:
            manifest = snapshots.import_tar(f, staging, max_bytes=max_bytes, check=acceptable)
        try:
            map_id = manifest.map_id
            sha = manifest.projection_sha256
            target = self.projections / f"{sha}.npy"
            if (staging / "projection.npy").exists():
                slsbh.load_projection(staging / "projection.npy", sha)  # refuses another matrix
                if not target.exists():
                    (staging / "projection.npy").replace(target)
                else:
                    (staging / "projection.npy").unlink()
            if not target.exists():
                raise ValueError(f"the tar holds no projection and {target} is missing")
            map_dir = maps_dir / map_id
            map_dir.mkdir(parents=True)
            MapStore.install_copy(staging / "map.sqlite", map_dir / "map.sqlite")
            snap_dir = map_dir / "snapshots" / manifest.snapshot_id
            snap_dir.parent.mkdir(parents=True)
            staging.replace(snap_dir)
            self.catalog.create_map(map_id, manifest.params, preset=manifest.params.get("preset"),
                                    state="ready")
            self.catalog.register_snapshot(SnapshotRecord(
                snapshot_id=manifest.snapshot_id, map_id=map_id, seq=manifest.seq, kind=manifest.kind,
                created_at=manifest.created_at, bytes=manifest.bytes,
                manifest_sha256=manifest.manifest_sha256, path=str(snap_dir)))
            return map_id
        finally:
            shutil.rmtree(staging, ignore_errors=True)

    def delete(self, map_id: str) -> None:
        rt = self.get(map_id)
        with self._create_lock:
            self.maps.pop(map_id, None)
            rt.close(snapshot=False)
            self.catalog.delete_map(map_id)
            shutil.rmtree(self.data_dir / "maps" / map_id, ignore_errors=True)
