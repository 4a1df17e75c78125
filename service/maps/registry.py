"""All maps of one data directory: the catalog, the projections, a runtime per map, and the numba
warm-up before the first request (docs/design/service.md §1.1, §4.4)."""

from __future__ import annotations

import contextlib
import logging
import shutil
import sqlite3
import threading
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from models.frontend import slsbh
from models.localisation.index import warm_up as index_warm_up
from models.memory.temporal_memory import TemporalMemory
from models.presets import TmOptions
from service.maps.config import MapConfig, MapOptions, resolve
from service.maps.encoding import projection as map_projection
from service.maps.encoding.embedders import Embedders
from service.maps.errors import (
    DataDirectoryInUse,
    IdempotencyKeyReused,
    InsufficientStorage,
    InvalidConfiguration,
    InvalidMapId,
    MapAlreadyExists,
    MapLimit,
    MapNotFound,
    MapTooLarge,
    MemoryBudgetExceeded,
    UnlistedMaps,
)
from service.maps.failed import FailedMap
from service.maps.ids import key_digest
from service.maps.recovery import snapshots as map_snapshots
from service.maps.results import BudgetInfo, MapReservation
from service.maps.runtime import MapRuntime
from service.maps.runtime import budget as map_budget
from service.maps.runtime.settings import RuntimeSettings
from service.settings import Settings
from storage import snapshots
from storage.base.files import is_no_room
from storage.base.process import rss_bytes
from storage.catalog import MAP_ID_RE, Catalog, MapExists, MapRecord
from storage.layout import Layout
from storage.lock import DataDirInUse, DataDirLock
from storage.mapstore import MapMeta, MapStore, StorageError, StorageFull, cell_dtype_for
from storage.snapshots import Manifest

__all__ = ["MapRegistry", "remove_unused", "warm_up"]

log = logging.getLogger("cortexloc.runtime")


def warm_up() -> None:
    """Compile the TM and index kernels now (numba, cached on disk), not during the first client's request."""
    tm = TemporalMemory(TmOptions(columnDimensions=64, cellsPerColumn=4, maxSegmentsPerCell=2,
                                  maxSynapsesPerSegment=4, activationThreshold=2, minThreshold=1))
    for x in ([1, 2, 3], [4, 5, 6], [1, 2, 3], [4, 5, 6]):
        tm.compute(np.array(x), learn=True)
    tm.compute(np.array([1, 2, 3]), learn=False)
    index_warm_up()


class MapRegistry:
    """All maps of one data directory. Its methods run in a worker thread (they block on disk), never on
    the event loop; `get` may run anywhere.

    Args:
        data_dir: CORTEXLOC_DATA_DIR.
        encoders: the service's encoders by backbone (`service.maps.encoding.embedders.Embedders`; each has
            `identity` and `feature_dim`); a map uses its frozen backbone's.
        settings: the service's settings (map caps, snapshot cadence, default preset).
    """

    def __init__(self, data_dir: Path, encoders: Embedders, settings: Settings) -> None:
        self.data_dir = Path(data_dir)
        self.encoders = encoders
        self.settings = settings
        self.runtime_settings = RuntimeSettings.of(settings)  # what each map's runtime reads of them
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.layout = Layout(data_dir)  # every path of the data directory (storage.layout)
        # one process at a time (storage.lock): before anything of the directory is read or written
        try:
            self._lock = DataDirLock(self.layout.lock).acquire(settings.lock_wait_s)
        except DataDirInUse as e:
            raise DataDirectoryInUse(str(e)) from e
        try:
            self.catalog = Catalog.open(self.layout.catalog)
        except BaseException:
            self._lock.release()
            raise
        self.projections = self.layout.projections
        self.projections.mkdir(parents=True, exist_ok=True)
        self.maps: dict[str, MapRuntime | FailedMap] = {}
        self._create_lock = threading.Lock()
        total = settings.memory_budget_bytes
        total, source = (total, "setting") if total is not None else map_budget.default_total()
        self.budget = map_budget.MemoryBudget(total, source)
        #: Maps left closed at start because they did not fit in the budget: map_id -> bytes asked.
        self.unfitted: dict[str, int] = {}
        #: Map directories the catalog did not list at start (left as they are, not served).
        self.unlisted: list[str] = []

    def _need(self, config: MapConfig, feature_dim: int, rows: int) -> map_budget.MapNeed:
        """The map's share of the budget; the encoders built by now are told to the budget first."""
        self.budget.set_encoders(sum(map_budget.encoder_bytes(e) for e in self.encoders.built().values()))
        return self._need_of(config, rows, map_budget.projection_bytes(
            config.projection, feature_dim, int(config.sections.slsbh.k)))

    def _need_of(self, config: MapConfig, rows: int, projection: int) -> map_budget.MapNeed:
        return map_budget.map_need(config, projection, rows, max_streams=self.settings.max_streams,
                                   key_cache=self.settings.idempotency_cache)

    def _runtime(self, record: MapRecord, feature_dim: int) -> MapRuntime:
        return MapRuntime(record, self.catalog, feature_dim, self.runtime_settings, budget=self.budget)

    def start(self) -> None:
        """Open every map and recover it by replay; create `default` on a fresh install.

        A map that cannot be opened at all (stored parameters this version rejects, anything that
        raises) is `failed` (`open-failed`, the error in the log) and the others still open
        (docs/design/service.md §4.4). A map that does not fit in the memory budget beside those opened
        before it stays closed, `failed` (`memory-budget`), listed in `unfitted` (§1.8); so does a
        fresh install's `default` that does not fit: it is made on disk, not opened, and the service
        starts ready.
        """
        warm_up()
        self._finish_deletes()
        for record in self.catalog.list_maps():
            try:
                self.maps[record.map_id] = self._open(record)
            except MemoryBudgetExceeded as e:
                self._unfit(record, e)
            except Exception:  # anything: one map's failure must not take the others down
                log.exception("map %s cannot be opened; it is served as failed", record.map_id)
                with contextlib.suppress(StorageFull):  # the catalog on a full disk: still served as failed
                    self.catalog.set_state(record.map_id, "failed", "open-failed")
                self.maps[record.map_id] = FailedMap(record, self.catalog, "open-failed")
        self._sweep_discarded()
        self.unlisted = unlisted = self._unlisted()  # /readyz warns of them
        for map_id in unlisted:
            log.error("maps/%s holds a map the catalog does not list; it is left as it is (not served): "
                      "restore catalog.sqlite, or move the directory away", map_id)
        if not self.maps and unlisted:
            # A fresh install has no map directories: this catalog was lost or replaced. Making `default`
            # now would serve an empty map as if the robot's maps had never been.
            raise UnlistedMaps(unlisted)
        if not self.maps:
            try:
                self.create("default")
            except MemoryBudgetExceeded as e:
                # As if it had been made before and did not fit at this start: it opens at one where it does.
                config, encoder = self._encoder_for(self._resolve(None))
                self._unfit(self._make("default", config, encoder)[0], e)

    def _unfit(self, record: MapRecord, e: MemoryBudgetExceeded) -> None:
        """`record` stays closed: it does not fit in the budget (§1.8)."""
        log.error("map %s stays closed: %s", record.map_id, e)
        self.unfitted[record.map_id] = e.asked_bytes
        self.maps[record.map_id] = FailedMap(record, self.catalog, "memory-budget")

    def _open(self, record: MapRecord) -> MapRuntime:
        """A stored map's runtime, recovered, or failed for a reason recovery knows.

        Raises:
            MemoryBudgetExceeded: it does not fit beside the maps opened before it (nothing allocated).
        """
        config = MapConfig.parse(record.params)  # InvalidConfiguration: `start` serves it as failed
        try:
            encoder, unavailable = self.encoders.get(config.backbone), None
        except ValueError as e:
            encoder, unavailable = None, e
        # Reserved before the runtime allocates its memory (its recovery's second memory in the budget's
        # recovery room, as at creation); a map that cannot be opened holds nothing.
        need = self._need(config, encoder.feature_dim if encoder else 0, self._stored_rows(record.map_id))
        self.budget.reserve(record.map_id, need)
        try:
            return self._open_reserved(record, config, encoder, unavailable)
        except BaseException:
            self.budget.release(record.map_id)
            raise

    def _stored_rows(self, map_id: str) -> int:
        """Rows in the map's store (0 when it cannot be read: its recovery says why)."""
        try:
            with MapStore.open(self.layout.map_db(map_id), readonly=True) as store:
                return store.count()
        except (OSError, StorageError, sqlite3.DatabaseError):
            return 0

    def _open_reserved(self, record: MapRecord, config: MapConfig, encoder: Any,
                       unavailable: ValueError | None) -> MapRuntime:
        if encoder is None:
            rt = self._runtime(record, 0)
            rt.state, rt.state_reason = "failed", "encoder-unavailable"
            log.error("map %s: %s", record.map_id, unavailable)
            return rt
        rt = self._runtime(record, encoder.feature_dim)
        if config.encoder_id != encoder.identity_for(config.resize):  # one network serves both modes
            rt.state, rt.state_reason = "failed", "encoder-mismatch"
            log.error("map %s was built with encoder %s, this server runs %s", record.map_id,
                      config.encoder_id, encoder.identity_for(config.resize))
            return rt
        try:
            rt.recover(serve_during_replay=True)  # a long tail replays while the map localises (§4.4)
        except BaseException:
            rt.close(snapshot=False)  # its writer thread and store
            raise
        return rt

    def close(self) -> None:
        try:
            for rt in self.maps.values():
                rt.close()
            self.catalog.close()
        finally:
            self._lock.release()

    def get(self, map_id: str) -> MapRuntime | FailedMap:
        """Raises MapNotFound."""
        rt = self.maps.get(map_id)
        if rt is None:
            raise MapNotFound(map_id)
        return rt

    def create(self, map_id: str, options: MapOptions | None = None) -> MapRuntime:
        """Create a map: resolve and freeze its configuration, persist the projection, then the store
        (docs/design/service.md §1.1).

        Raises:
            InvalidMapId, InvalidConfiguration, MapTooLarge, MapAlreadyExists, MapLimit,
            MemoryBudgetExceeded. InsufficientStorage: no room to write; what the creation made is
            removed (a projection, content-addressed and perhaps shared, stays).
        """
        return self._create(map_id, options)[0]

    def create_or_replay(self, map_id: str, options: MapOptions | None, key: str) -> tuple[MapRuntime, bool]:
        """`create` with an `Idempotency-Key`, for a creation that may be a retry (docs/design/service.md
        §1.1): (the map, whether it was made now). The map keeps the key and the options as asked, by
        their digests (`MapConfig.made_by`); a map of this id made by this key from these options is the
        earlier try's, answered as it is.

        Raises:
            as `create`; MapAlreadyExists where the map of this id was made otherwise (without this key);
            IdempotencyKeyReused where this key made it from other options.
        """
        return self._create(map_id, options, key=key)

    def _create(self, map_id: str, options: MapOptions | None, *, key: str | None = None
                ) -> tuple[MapRuntime, bool]:
        if not MAP_ID_RE.fullmatch(map_id):  # `$` also matches before a last newline
            raise InvalidMapId(map_id, MAP_ID_RE.pattern)
        config = self._resolve(options)
        if key is not None:
            made_by = f"{key_digest(key)}:{(options or MapOptions()).digest()}"
            config = config.model_copy(update={"made_by": made_by})
        with self._create_lock:
            # Refused before a backbone's network is built or loaded.
            if map_id in self.maps:
                made_by = self.maps[map_id].config.made_by
                if key is None or made_by.partition(":")[0] != key_digest(key):
                    raise MapAlreadyExists(map_id)
                if made_by != config.made_by:
                    raise IdempotencyKeyReused(key)
                return self.maps[map_id], False
            if len(self.maps) >= self.settings.max_maps:
                raise MapLimit(self.settings.max_maps)
            config, encoder = self._encoder_for(config)
            # The process-wide budget, before the projection or the memory is allocated (§1.8); the
            # projection counts in full until its checksum says whether another map shares it, and the
            # budget keeps room for the second memory its first recovery builds.
            self.budget.reserve(map_id, self._need(config, encoder.feature_dim, 0))
            try:
                return self._create_reserved(map_id, config, encoder), True
            except BaseException:
                self.budget.release(map_id)
                raise

    def _resolve(self, options: MapOptions | None) -> MapConfig:
        """A new map's configuration, resolved and checked against the map cap.

        Raises:
            InvalidConfiguration, MapTooLarge.
        """
        config = resolve(options or MapOptions(), default_preset=self.settings.default_preset,
                         default_backbone=self.encoders.default)
        need = map_projection.model_bytes(config, self.settings.max_streams)
        if need > self.settings.max_map_bytes:
            raise MapTooLarge(need, self.settings.max_map_bytes)
        return config

    def _encoder_for(self, config: MapConfig) -> tuple[MapConfig, Any]:
        """(the new map's configuration with its projection kind, its encoder), built or loaded now.

        Raises:
            InvalidConfiguration: an unknown or unavailable backbone.
        """
        need = map_projection.model_bytes(config, self.settings.max_streams)
        try:
            encoder = self.encoders.get(config.backbone)
        except ValueError as e:
            raise InvalidConfiguration(str(e), [{"location": "body", "name": "backbone",
                                                 "message": str(e)}]) from e
        # Projection plus memory within the map budget: the very sparse projection where dense breaks it.
        return config.model_copy(update={"projection": map_projection.projection_kind(
            encoder.feature_dim, int(config.sections.slsbh.k), need, self.settings.max_map_bytes)}), encoder

    def _create_reserved(self, map_id: str, config: MapConfig, encoder: Any) -> MapRuntime:
        """`create` after its checks and its reservation (under the creation lock)."""
        try:
            record, config = self._make(map_id, config, encoder)
        except (StorageFull, OSError) as e:
            if not isinstance(e, StorageFull) and not is_no_room(e):  # (the projection's write: the OS's)
                raise
            raise InsufficientStorage(f"map {map_id!r} could not be created: no room to write ({e}); "
                                      "nothing was created") from e
        self.budget.reserve(map_id, self._need(config, encoder.feature_dim, 0))  # shared: less
        rt = self._runtime(record, encoder.feature_dim)
        rt.recover()
        self.maps[map_id] = rt
        return rt

    def _make(self, map_id: str, config: MapConfig, encoder: Any) -> tuple[MapRecord, MapConfig]:
        """A new map on disk, not opened: its projection, its store, its catalog row (§1.1); (the row,
        the configuration as frozen).

        Raises:
            MapAlreadyExists.
        """
        P = map_projection.make(config.projection, encoder.feature_dim, int(config.sections.slsbh.k),
                                int(config.sections.slsbh.seed))
        _, sha = slsbh.save_projection(P, self.projections)
        del P
        # the encoder identity names the backbone, its weights and the map's resize mode
        config = config.model_copy(update={"projection_sha256": sha,
                                           "encoder_id": encoder.identity_for(config.resize)})
        if encoder.identity.split("/")[1].startswith("random"):
            log.warning("map %s is created on RANDOM encoder weights (%s)", map_id, encoder.identity)
        if self.catalog.get_map(map_id) is not None:  # before any file is touched
            raise MapAlreadyExists(map_id)
        map_dir = self.layout.map_dir(map_id)
        if map_dir.exists():
            if self._holds_data(map_id):
                raise UnlistedMaps([map_id])
            shutil.rmtree(map_dir)  # leftovers of a creation that never reached the catalog
        map_dir.mkdir(parents=True)
        params = config.stored()
        try:
            store = MapStore.create(self.layout.map_db(map_id), MapMeta(
                map_id=map_id, params=params, projection_sha256=sha, encoder_id=config.encoder_id,
                cell_dtype=cell_dtype_for(int(config.sections.tm.columnDimensions)
                                          * int(config.sections.tm.cellsPerColumn))))
            store.close()
            return self.catalog.create_map(map_id, params, preset=config.preset, state="ready"), config
        except MapExists as e:  # another map's now: its directory is not ours to remove
            raise MapAlreadyExists(map_id) from e
        except BaseException:
            # nothing lists the directory made above (no catalog row): removed, not left for the next
            # creation of this id to find (a full disk would leave one per try)
            shutil.rmtree(map_dir, ignore_errors=True)
            raise

    def _discard(self, map_id: str) -> None:
        """Delete a map, its catalog entry and its directory: the directory renamed out of the maps' names
        first (an instant), then the entry deleted, then the directory removed. A delete cut short (a
        kill) leaves no directory that looks like a map the catalog does not list (`_unlisted`, which a
        start leaves alone and whose id it refuses for good): killed before the entry went, the entry
        names a map whose directory is a discarded one, and the start finishes the delete
        (`_finish_deletes`); after it, a start removes what is left (`_sweep_discarded`)."""
        gone = self.layout.discarded(map_id, uuid.uuid4().hex)
        moved = True
        try:
            self.layout.map_dir(map_id).rename(gone)
        except FileNotFoundError:
            moved = False
        try:
            self.catalog.delete_map(map_id)
        except BaseException:
            if moved:  # the catalog still lists it: its files stay where they were
                gone.rename(self.layout.map_dir(map_id))
            raise
        shutil.rmtree(gone, ignore_errors=True)

    def _finish_deletes(self) -> None:
        """At a start, before the maps open: a map the catalog lists whose directory is gone and was
        renamed to a discarded one (`_discard` cut short between the two: the delete was never
        answered) is deleted, as it was asked to be."""
        for record in self.catalog.list_maps():
            if not self.layout.map_dir(record.map_id).exists() and self.layout.discarded_of(record.map_id):
                log.warning("map %s: a delete was cut short after its directory was moved away; it is "
                            "finished", record.map_id)
                self.catalog.delete_map(record.map_id)

    def _sweep_discarded(self) -> None:
        """Remove what deletes (`_discard`) and imports (`import_snapshot`) cut short left; at the start,
        under the directory's lock."""
        for d in self.layout.discarded_dirs():
            shutil.rmtree(d, ignore_errors=True)

    def _holds_data(self, map_id: str) -> bool:
        """Whether `maps/<map_id>` holds what a map stored: rows, or snapshots. A creation that never
        reached the catalog leaves an empty store at most (`MapStore.create` writes it whole or not at
        all); a store that cannot be read is taken to hold data: it is never deleted unread."""
        snaps = self.layout.snapshots_dir(map_id)
        if snaps.is_dir() and any(snaps.iterdir()):
            return True
        db = self.layout.map_db(map_id)
        if not db.exists():
            return False
        try:
            with MapStore.open(db, readonly=True) as store:
                return store.count() > 0 or store.closure_count() > 0
        except (StorageError, OSError, sqlite3.Error):
            return True

    def _unlisted(self) -> list[str]:
        """The map directories the catalog does not list that hold data (`_holds_data`), sorted."""
        if not self.layout.maps.is_dir():
            return []
        listed = {r.map_id for r in self.catalog.list_maps()}
        return sorted(d.name for d in self.layout.maps.iterdir()
                      if d.is_dir() and MAP_ID_RE.fullmatch(d.name) and d.name not in listed
                      and self._holds_data(d.name))

    def memory_budget(self) -> BudgetInfo:
        """The budget: total, used, free, the encoders, and every map's reservation (§1.8); a map left
        closed at start shows what it asked."""
        encoders, held = self.budget.report()
        used, reserve = self.budget.held()  # (with a restore's second index, which the parts leave out)
        maps = [MapReservation(map_id, True, None, sum(parts.values()), parts)
                for map_id, parts in held.items()]
        maps += [MapReservation(map_id, False, "memory-budget", asked, {})
                 for map_id, asked in self.unfitted.items()]
        return BudgetInfo(total_bytes=self.budget.total, source=self.budget.source, used_bytes=used,
                          reserve_bytes=reserve, free_bytes=max(0, self.budget.total - used - reserve),
                          encoders_bytes=encoders, maps=maps,
                          process_rss_bytes=rss_bytes())

    def import_snapshot(self, tar_path: Path, max_bytes: int, moved: bool = False) -> str:
        """Create a map from a downloaded snapshot tar (`service.maps.recovery.snapshots.import_snapshot`;
        `moved`: the map itself, moved here, keeping its epoch)."""
        return map_snapshots.import_snapshot(self.data_dir, self.catalog, tar_path, max_bytes,
                                             fits=self._import_fits, moved=moved)

    def _import_fits(self, m: Manifest) -> None:
        """Raises MemoryBudgetExceeded unless the imported map fits beside the maps here, each at its
        stored rows (the server is stopped: no encoder says the feature dimension, so projections count
        by their files' sizes, and the encoders are not counted)."""
        budget = map_budget.MemoryBudget(self.budget.total, self.budget.source)
        for record in self.catalog.list_maps():
            path = self.layout.projection(str(record.params.get("projection_sha256")))
            # A map that cannot be opened, or does not fit, holds nothing at start.
            with contextlib.suppress(MemoryBudgetExceeded, InvalidConfiguration):
                budget.reserve(record.map_id, self._need_of(MapConfig.parse(record.params),
                                                            self._stored_rows(record.map_id),
                                                            path.stat().st_size if path.exists() else 0))
        try:
            config = MapConfig.parse(m.params)
        except InvalidConfiguration as e:  # the same gate as a created map's
            raise snapshots.SnapshotInvalid(f"the snapshot's map configuration: {e}") from e
        projection = m.external.get(snapshots.PROJECTION_FILE)
        budget.reserve(m.map_id, self._need_of(config, m.seq, projection.bytes if projection else 0))

    def delete(self, map_id: str) -> None:
        """Raises MapNotFound."""
        rt = self.get(map_id)
        with self._create_lock:
            self.maps.pop(map_id, None)
            self.budget.release(map_id)
            self.unfitted.pop(map_id, None)
            rt.close(snapshot=False)
            self._discard(map_id)
        del rt
        map_budget.give_back()

    def import_live(self, tar_path: Path, max_bytes: int) -> MapRuntime:
        """Import a snapshot tar into this running registry and open the map: the receiving end of a
        move between shards (service.scaleout; docs/scaling.md). The map recovers from the snapshot
        as it would at a start, and is the same map: its epoch and id marks are the snapshot's lineage's.

        Raises:
            MapLimit, SnapshotInvalid, MemoryBudgetExceeded (nothing of the map is left behind).
        """
        with self._create_lock:
            if len(self.maps) >= self.settings.max_maps:
                raise MapLimit(self.settings.max_maps)
            map_id = self.import_snapshot(tar_path, max_bytes, moved=True)
            record = self.catalog.get_map(map_id)
            assert record is not None
            try:
                rt = self._open(record)
            except BaseException:
                self._discard(map_id)
                raise
            self.maps[map_id] = rt
        return rt


def remove_unused(root: Path) -> None:
    """Remove data directory `root`, which this process made and closed (a refused `cortexloc import`),
    unless another process has taken it since: its lock (`storage.lock`) is held for the removal, so a
    server starting on the same new path keeps what it made."""
    try:
        lock = DataDirLock(Layout(root).lock).acquire()
    except DataDirInUse:
        return
    try:
        shutil.rmtree(root, ignore_errors=True)
    finally:
        lock.release()
