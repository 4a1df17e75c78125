"""A map whose runtime could not be built at startup (docs/design/service.md §4.4): it stays listed,
`failed` with a reason, and answers 503 `map-unavailable`, while the other maps serve.

Why it exists beside `MapRuntime`'s own `failed` state: that state needs a runtime, and a runtime cannot
be built from stored parameters it rejects (an older version's localiser options, a TM section that no
longer validates). This stand-in needs only the catalog row; it shows the stored parameters as they are
and refuses everything that would need the memory, the store or the writer.
"""

from __future__ import annotations

import asyncio
from collections import OrderedDict
from collections.abc import Callable
from typing import Any, TypeVar

from service.maps.config import MapConfig
from service.maps.errors import MapUnavailable
from service.maps.recovery import snapshots as map_snapshots
from service.maps.results import MapInfo, SnapshotInfo
from service.maps.runtime.recent import RecentAnswers
from service.maps.states import serving
from storage.catalog import Catalog, MapRecord

__all__ = ["FailedMap"]

T = TypeVar("T")


class FailedMap:
    """The stand-in of a map that could not be opened (the module docstring says why).

    Args:
        record: the map's catalog row; catalog: the service's catalog (snapshot listing).
        reason: the short `state_reason` (e.g. `open-failed`), shown in the map resource and /readyz.
    """

    def __init__(self, record: MapRecord, catalog: Catalog, reason: str) -> None:
        self.record, self.catalog = record, catalog
        self.map_id, self.params = record.map_id, record.params
        # The stored options as far as they can be read (the map failed because some cannot).
        self.config = MapConfig.salvage(record.params)
        self.state, self.state_reason = "failed", reason
        self.recovery: dict[str, Any] | None = None
        self.snapshot_error: dict[str, Any] | None = None
        self.streams: OrderedDict[str, Any] = OrderedDict()
        self.recent: RecentAnswers[Any] = RecentAnswers()
        self.store = None

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """`fn(*args)` in a worker thread (there is no writer: nothing here changes the map)."""
        return await asyncio.to_thread(fn, *args)

    def require_ready(self, learns: bool = True) -> None:
        """Raises MapUnavailable: a failed map serves nothing (`serving("failed")`)."""
        assert not serving(self.state).reads
        raise MapUnavailable(self.map_id, self.state, self.state_reason)

    def close(self, snapshot: bool = True) -> None:
        """Nothing is open."""

    def info(self) -> MapInfo:
        return MapInfo.of(self.config, self.record, state=self.state, state_reason=self.state_reason,
                          **map_snapshots.disk_use(self.catalog, self.map_id))

    def snapshots(self) -> list[SnapshotInfo]:
        return map_snapshots.listing(self.catalog, self.map_id)

    def _unavailable(self, *args: Any, **kwargs: Any) -> Any:
        raise MapUnavailable(self.map_id, self.state, self.state_reason)

    # Everything else needs the memory, the store or the writer.
    memory = reset_stream = set_revisit_threshold = patch = snapshot = restore = snapshot_dir = _unavailable
    delete_snapshot = own_trail_merges = repair = _unavailable
