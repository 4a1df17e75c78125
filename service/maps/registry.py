"""All maps of one data directory: the catalog, the projections, a runtime per map, and the numba
warm-up before the first request (docs/design/service.md §1.1, §4.4)."""

from __future__ import annotations

import logging
import shutil
import threading
from pathlib import Path
from typing import Any

import numpy as np

from models.frontend import slsbh
from models.localisation.index import warm_up as index_warm_up
from models.memory.temporal_memory import TemporalMemory
from service.maps import projection as map_projection
from service.maps import snapshots as map_snapshots
from service.maps.encoders import Encoders
from service.maps.errors import (
    InvalidConfiguration,
    InvalidMapId,
    MapAlreadyExists,
    MapLimit,
    MapNotFound,
    MapTooLarge,
)
from service.maps.failed import FailedMap
from service.maps.params import map_option, resolve_params
from service.maps.runtime import MapRuntime
from storage.catalog import MAP_ID_RE, Catalog, MapExists, MapRecord
from storage.layout import Layout
from storage.mapstore import MapMeta, MapStore, cell_dtype_for

__all__ = ["MapRegistry", "warm_up"]

log = logging.getLogger("cortexloc.runtime")


def warm_up() -> None:
    """Compile the TM and index kernels now (numba, cached on disk), not during the first client's request."""
    tm = TemporalMemory({"columnDimensions": 64, "cellsPerColumn": 4, "maxSegmentsPerCell": 2,
                         "maxSynapsesPerSegment": 4, "activationThreshold": 2, "minThreshold": 1})
    for x in ([1, 2, 3], [4, 5, 6], [1, 2, 3], [4, 5, 6]):
        tm.compute(np.array(x), learn=True)
    tm.compute(np.array([1, 2, 3]), learn=False)
    index_warm_up()


class MapRegistry:
    """All maps of one data directory. Its methods run in a worker thread (they block on disk), never on
    the event loop; `get` may run anywhere.

    Args:
        data_dir: CORTEXLOC_DATA_DIR.
        encoders: the service's encoders by backbone (`service.maps.encoders.Encoders`; each has
            `identity` and `feature_dim`); a map uses its frozen backbone's.
        settings: the service's settings (map caps, snapshot cadence, default preset).
    """

    def __init__(self, data_dir: Path, encoders: Encoders, settings: Any) -> None:
        self.data_dir = Path(data_dir)
        self.encoders = encoders
        self.settings = settings
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.layout = Layout(data_dir)  # every path of the data directory (storage.layout)
        self.catalog = Catalog.open(self.layout.catalog)
        self.projections = self.layout.projections
        self.projections.mkdir(parents=True, exist_ok=True)
        self.maps: dict[str, MapRuntime | FailedMap] = {}
        self._create_lock = threading.Lock()

    def _runtime(self, record: MapRecord, feature_dim: int) -> MapRuntime:
        s = self.settings
        return MapRuntime(record, self.catalog, feature_dim, s.max_streams, s.max_observations,
                          s.snapshot_every, s.snapshot_keep, max_keys=s.idempotency_keys,
                          key_cache=s.idempotency_cache, max_closures=s.loop_closures)

    def start(self) -> None:
        """Open every map and recover it by replay; create `default` on a fresh install.

        A map that cannot be opened at all (stored parameters this version rejects, anything that
        raises) is `failed` (`open-failed`, the error in the log) and the others still open
        (docs/design/service.md §4.4).
        """
        warm_up()
        for record in self.catalog.list_maps():
            try:
                self.maps[record.map_id] = self._open(record)
            except Exception:  # anything: one map's failure must not take the others down
                log.exception("map %s cannot be opened; it is served as failed", record.map_id)
                self.catalog.set_state(record.map_id, "failed", "open-failed")
                self.maps[record.map_id] = FailedMap(record, self.catalog, "open-failed")
        if not self.maps:
            self.create("default", preset=self.settings.default_preset)

    def _open(self, record: MapRecord) -> MapRuntime:
        """A stored map's runtime, recovered, or failed for a reason recovery knows."""
        backbone = map_option(record.params, "backbone")
        try:
            encoder = self.encoders.get(backbone)
        except ValueError as e:
            rt = self._runtime(record, 0)
            rt.state, rt.state_reason = "failed", "encoder-unavailable"
            log.error("map %s: %s", record.map_id, e)
            return rt
        rt = self._runtime(record, encoder.feature_dim)
        if record.params.get("encoder_id") != encoder.identity:
            rt.state, rt.state_reason = "failed", "encoder-mismatch"
            log.error("map %s was built with encoder %s, this server runs %s", record.map_id,
                      record.params.get("encoder_id"), encoder.identity)
            return rt
        try:
            rt.recover()
        except BaseException:
            rt.close(snapshot=False)  # its writer thread and store
            raise
        return rt

    def close(self) -> None:
        for rt in self.maps.values():
            rt.close()
        self.catalog.close()

    def get(self, map_id: str) -> MapRuntime | FailedMap:
        """Raises MapNotFound."""
        rt = self.maps.get(map_id)
        if rt is None:
            raise MapNotFound(map_id)
        return rt

    def create(self, map_id: str, *, preset: str, seed: int | None = None, tm: dict[str, Any] | None = None,
               slsbh_conf: dict[str, Any] | None = None,
               backbone: str | None = None, memory: str = "tm", revisit_threshold: float | None = None,
               localiser: dict[str, Any] | None = None, thumbnails: bool = False) -> MapRuntime:
        """Create a map: resolve and freeze parameters, persist the projection, then the store (§1.1).

        Raises:
            InvalidMapId, InvalidConfiguration, MapTooLarge, MapAlreadyExists, MapLimit.
        """
        if not MAP_ID_RE.match(map_id):
            raise InvalidMapId(map_id, MAP_ID_RE.pattern)
        params = resolve_params(
            preset, seed=seed, tm=tm, slsbh_conf=slsbh_conf,
            backbone=backbone or self.encoders.default, memory=memory, localiser=localiser,
            **({} if revisit_threshold is None else {"revisit_threshold": revisit_threshold}))
        need = map_projection.model_bytes(params, self.settings.max_streams)
        if need > self.settings.max_map_bytes:
            raise MapTooLarge(need, self.settings.max_map_bytes)
        with self._create_lock:
            # Refused before a backbone's network is built or loaded.
            if map_id in self.maps:
                raise MapAlreadyExists(map_id)
            if len(self.maps) >= self.settings.max_maps:
                raise MapLimit(self.settings.max_maps)
            try:
                encoder = self.encoders.get(params["backbone"])
            except ValueError as e:
                raise InvalidConfiguration(str(e), [{"location": "body", "name": "backbone",
                                                     "message": str(e)}]) from e
            # Projection plus memory within the map budget: the very sparse projection where dense breaks it.
            params["projection"], P = map_projection.for_map(params, encoder.feature_dim,
                                                             self.settings.max_streams)
            _, sha = slsbh.save_projection(P, self.projections)
            del P
            params["projection_sha256"] = sha
            params["encoder_id"] = encoder.identity
            params["thumbnails"] = bool(thumbnails)  # frozen like the rest (docs/design/service.md §1.1)
            if encoder.identity.split("/")[1].startswith("random"):
                log.warning("map %s is created on RANDOM encoder weights (%s)", map_id, encoder.identity)
            map_dir = self.layout.map_dir(map_id)
            if map_dir.exists():
                shutil.rmtree(map_dir)  # leftovers of a creation that never reached the catalog
            map_dir.mkdir(parents=True)
            store = MapStore.create(self.layout.map_db(map_id), MapMeta(
                map_id=map_id, params=params, projection_sha256=sha, encoder_id=encoder.identity,
                cell_dtype=cell_dtype_for(int(params["tm"]["columnDimensions"])
                                          * int(params["tm"]["cellsPerColumn"]))))
            store.close()
            try:
                record = self.catalog.create_map(map_id, params, preset=preset, state="ready")
            except MapExists as e:
                raise MapAlreadyExists(map_id) from e
            rt = self._runtime(record, encoder.feature_dim)
            rt.recover()
            self.maps[map_id] = rt
            return rt

    def import_snapshot(self, tar_path: Path, max_bytes: int) -> str:
        """Create a map from a downloaded snapshot tar (`service.maps.snapshots.import_snapshot`)."""
        return map_snapshots.import_snapshot(self.data_dir, self.catalog, tar_path, max_bytes)

    def delete(self, map_id: str) -> None:
        """Raises MapNotFound."""
        rt = self.get(map_id)
        with self._create_lock:
            self.maps.pop(map_id, None)
            rt.close(snapshot=False)
            self.catalog.delete_map(map_id)
            shutil.rmtree(self.layout.map_dir(map_id), ignore_errors=True)
