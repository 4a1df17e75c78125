"""What a map's runtime answers about itself (docs/design/service.md §1.2, §1.4): the map resource
(`info`), its places (`places`, docs/design/science.md §11.8–§11.9), the options that may change after
creation (`patch`) and the memory resource (`memory`, whose sizes are `service.maps.runtime.sizes`').
"""

from __future__ import annotations

import service.maps.runtime.sizes as sizes  # the module, not the package: no cycle via __init__
from models.localisation import forgetting
from service.maps.errors import InsufficientStorage
from service.maps.recovery import snapshots as map_snapshots
from service.maps.results import MapInfo, MemoryInfo, PlacesInfo
from service.maps.states import serving
from storage.mapstore import StorageFull

__all__ = ["Resources"]


class Resources:
    """`MapRuntime`'s own resources (module docstring); it holds no state of its own."""

    def info(self) -> MapInfo:
        return MapInfo.of(self.config, self.record, state=self.state, state_reason=self.state_reason,
                          observations=len(self.index),
                          last_seq=self.store.last_seq() if self.store else 0, streams=list(self.streams),
                          recovery=self.recovery, snapshot_error=self.snapshot_error,
                          places=(self.places() if self.store is not None
                                  and serving(self.state).reads else None),
                          **map_snapshots.disk_use(self.catalog, self.map_id))

    def places(self) -> PlacesInfo:
        """Writer: the map's places, appearances and visits (docs/design/science.md §11.8, §11.9)."""
        assert self.store is not None
        dropped = self.store.dropped()
        conf = self.place_map.options
        return PlacesInfo(
            places=self.place_map.places(), appearances=len(self.index), rows_stored=self.store.count(),
            dropped=len(dropped), forgotten=sum(1 for r in dropped.values() if r == "forgotten"),
            visits_logged=self.store.visit_stats()[0], max_appearances=conf.appearances,
            max_rows=self.index.max_observations, consolidate=float(conf.consolidate),
            forgetting=forgetting.rule(conf.forget_percent))

    def set_revisit_threshold(self, value: float) -> MapInfo:
        """Writer: the map's revisit threshold (`patch`)."""
        return self.patch(revisit_threshold=value)

    def patch(self, *, revisit_threshold: float | None = None, verify_revisit: bool | None = None) -> MapInfo:
        """Writer: the options that may change after creation, durable in the catalog in one update
        (docs/design/service.md §1.2): the revisit threshold, and whether a revisit needs a verified
        keyframe. InvalidConfiguration (nothing changes): a threshold outside [0, 1], verify_revisit on a
        map without keyframes. InsufficientStorage: no room to write the catalog (nothing changes).
        MapUnavailable: the map serves nothing (`failed`, `recovering`): a change stored now would be
        read by the map it is once repaired, unseen by its operator."""
        self.require_ready(learns=False)
        changes = {k: v for k, v in (("revisit_threshold", revisit_threshold),
                                     ("verify_revisit", verify_revisit)) if v is not None}
        if changes:
            config = self.config.with_changes(**changes)
            try:
                self.record = self.catalog.update_params(
                    self.map_id, **{k: getattr(config, k) for k in changes})
            except StorageFull as e:
                raise InsufficientStorage(f"the change could not be stored: no room to write ({e}); "
                                          "nothing changed") from e
            self.config = config
        return self.info()

    def memory(self) -> MemoryInfo:
        """Writer: the map's sizes. MapUnavailable where it serves nothing (its memory is not built)."""
        self.require_ready(learns=False)
        return sizes.memory_info(self.model, self.streams, tm_params=self.config.sections.tm,
                                 max_streams=self.settings.max_streams, projection=self.projection_path,
                                 store=self.store, snapshots_bytes=self.catalog.snapshots_bytes(self.map_id))
