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

from service.maps import snapshots as map_snapshots
from service.maps.errors import MapUnavailable
from service.maps.params import DEFAULT_REVISIT_THRESHOLD, map_option
from service.maps.recent import RecentAnswers
from service.maps.results import MapInfo, SnapshotInfo
from storage.catalog import Catalog, MapRecord

__all__ = ["FailedMap"]

T = TypeVar("T")


def _as(value: Any, kind: type, default: Any) -> Any:
    """`value` when it is a `kind`, else `default`: stored params may be anything."""
    return value if isinstance(value, kind) else default


class FailedMap:
    """The stand-in of a map that could not be opened (the module docstring says why).

    Args:
        record: the map's catalog row; catalog: the service's catalog (snapshot listing).
        reason: the short `state_reason` (e.g. `open-failed`), shown in the map resource and /readyz.
    """

    def __init__(self, record: MapRecord, catalog: Catalog, reason: str) -> None:
        self.record, self.catalog = record, catalog
        self.map_id, self.params = record.map_id, record.params
        self.state, self.state_reason = "failed", reason
        self.recovery: dict[str, Any] | None = None
        self.snapshot_error: dict[str, Any] | None = None
        self.streams: OrderedDict[str, Any] = OrderedDict()
        self.recent: RecentAnswers[Any] = RecentAnswers()
        self.store = None

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """`fn(*args)` in a worker thread (there is no writer: nothing here changes the map)."""
        return await asyncio.to_thread(fn, *args)

    def require_ready(self) -> None:
        raise MapUnavailable(self.map_id, self.state, self.state_reason)

    def close(self, snapshot: bool = True) -> None:
        """Nothing is open."""

    def info(self) -> MapInfo:
        p = self.params if isinstance(self.params, dict) else {}
        text = {k: _as(map_option(p, k), str, "") for k in ("memory", "projection", "backbone", "resize")}
        return MapInfo(
            map_id=self.map_id, created_at=self.record.created_at, state=self.state,
            state_reason=self.state_reason, preset=self.record.preset,
            params={"tm": _as(p.get("tm"), dict, {}), "slsbh": _as(p.get("slsbh"), dict, {}),
                    "seed": _as(p.get("seed"), int, 0),
                    "memory": text["memory"], "projection": text["projection"],
                    "localiser": _as(map_option(p, "localiser"), dict, {}), "resize": text["resize"],
                    "keyframes": _as(map_option(p, "keyframes"), dict, None)},
            encoder=_as(p.get("encoder_id"), str, ""),
            projection_sha256=_as(p.get("projection_sha256"), str, ""),
            observations=0, last_seq=0, streams=[], warnings=_as(p.get("warnings"), list, []),
            recovery=None, snapshot_error=None, backbone=text["backbone"],
            revisit_threshold=_as(map_option(p, "revisit_threshold"), float, DEFAULT_REVISIT_THRESHOLD),
            verify_revisit=_as(map_option(p, "verify_revisit"), bool, False),
            thumbnails=_as(p.get("thumbnails", False), bool, False),
            **map_snapshots.disk_use(self.catalog, self.map_id))

    def snapshots(self) -> list[SnapshotInfo]:
        return map_snapshots.listing(self.catalog, self.map_id)

    def _unavailable(self, *args: Any, **kwargs: Any) -> Any:
        raise MapUnavailable(self.map_id, self.state, self.state_reason)

    # Everything else needs the memory, the store or the writer.
    memory = reset_stream = patch = snapshot = restore = snapshot_dir = _unavailable
    delete_snapshot = _unavailable
