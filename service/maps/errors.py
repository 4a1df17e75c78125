"""What can go wrong with a map, in domain words (docs/design/service.md §2).

Nothing here knows HTTP: `service.errors.DOMAIN_PROBLEMS` maps each class to its status, slug and the
attributes it shows as problem members, in one table. The message is the problem's `detail`.
"""

from __future__ import annotations

from typing import Any

# Two refusals of the storage layer reach the client as they are, so the domain names them as its own
# (the HTTP layer imports no storage): a snapshot that does not verify (409 snapshot-invalid) and a
# store a restore or a deletion has closed under a reader (503 map-unavailable, retry).
from storage.mapstore import StoreClosed
from storage.snapshots import SnapshotInvalid

__all__ = ["READ_ONLY_REASON", "REMEDIES", "EncoderUnavailable", "IdempotencyKeyReused",
           "InsufficientStorage", "InvalidConfiguration", "InvalidMapId", "MapAlreadyExists", "MapError",
           "MapFull", "MapLimit", "MapNotFound", "MapReadOnly", "MapReplaying", "MapRestored", "MapTooLarge",
           "MapUnavailable", "MemoryBudgetExceeded", "ObservationNotFound", "Overloaded",
           "RecentAnswerNotFound", "RowsOverCap", "ShardUnavailable", "SnapshotInUse", "SnapshotInvalid",
           "SnapshotNotFound", "StoreClosed", "StreamLimit"]


class MapError(Exception):
    """A refused map operation; nothing stored changed."""


class MapNotFound(MapError):  # noqa: N818 - named after the problem slug
    def __init__(self, map_id: str) -> None:
        super().__init__(f"no map {map_id!r}")
        self.map_id = map_id


#: What an operator does about a map failed for this reason, said in its 503's detail (docs/design/
#: service.md §4.4). A corrupt map is not restored over: its snapshots are imported as a new map file.
REMEDIES: dict[str, str] = {
    "database-corrupt": "its map.sqlite fails SQLite's check; to recover it from a snapshot: download its "
                        "newest one (GET /v1/maps/{id}/snapshots/{snapshot_id}/download, verified as it is "
                        "sent), DELETE the map, stop the service, `cortexloc import` the file and start "
                        "the service again",
    "memory-budget": "it did not fit the memory budget when the service started (GET /v1/memory lists what "
                     "it asks under `maps`); nothing is lost: raise CORTEXLOC_MEMORY_BUDGET_BYTES, or delete "
                     "maps you do not need, and restart the service",
    "unopenable": "its map.sqlite could not be opened (a permission, a read-only file or directory: the "
                  "log has the OS's words); nothing says it is damaged: give the service read and write "
                  "access to maps/{id}/ and restart it",
}

#: The `state_reason` of a map whose storage refuses writes (state `read-only`).
READ_ONLY_REASON = "storage-read-only"


class MapUnavailable(MapError):  # noqa: N818
    """The map is `recovering`, `read-only` or `failed` (docs/design/service.md §4.4); a failed map's
    reason with a known remedy (`REMEDIES`) says it."""

    def __init__(self, map_id: str, state: str, state_reason: str | None) -> None:
        remedy = REMEDIES.get(state_reason or "")
        super().__init__(f"map {map_id!r} is {state}" + (f" ({state_reason})" if state_reason else "")
                         + (f": {remedy.replace('{id}', map_id)}" if remedy else ""))
        self.state, self.state_reason = state, state_reason


class MapReadOnly(MapUnavailable):
    """The map's `map.sqlite` refuses writes (an immutable or read-only file, a read-only mount: SQLite
    opens it read-only without a word): the map is `read-only`; `refused` was not stored, nothing changed.
    Localising frames and reads are still answered."""

    def __init__(self, map_id: str, refused: str = "the change") -> None:
        super().__init__(map_id, "read-only", READ_ONLY_REASON)
        self.args = (f"map {map_id!r} is read-only: its storage (maps/{map_id}/map.sqlite) refuses writes, "
                     f"so {refused} was not stored; localising frames are still answered. Make the file "
                     "writable by the service (chattr -i, chmod, a read-write mount) and restart it",)
        self.map_id = map_id


class MapReplaying(MapUnavailable):
    """The map is `replaying` the rows and visits after its snapshot at a start (docs/design/service.md
    §4.4): localising frames are answered meanwhile; what learns is refused until about `retry_after`
    seconds from now (the steps left at the pace so far)."""

    def __init__(self, map_id: str, steps: int, replayed: int, retry_after: int) -> None:
        super().__init__(map_id, "replaying", None)
        self.args = (f"map {map_id!r} is replaying the {steps} rows and visits after its last snapshot "
                     f"({replayed} done): localising frames are answered, learning resumes in about "
                     f"{retry_after} s",)
        self.steps, self.replayed, self.retry_after = steps, replayed, retry_after


class MapFull(MapError):  # noqa: N818
    def __init__(self, map_id: str, max_observations: int) -> None:
        super().__init__(f"map {map_id!r} holds its maximum of {max_observations} observations; "
                         "localisation still works")
        self.max_observations = max_observations


class RowsOverCap(MapFull):
    """A map, or the snapshot a restore would install, holds more rows than `CORTEXLOC_MAX_OBSERVATIONS`
    (the setting lowered since they were learned): its index cannot hold them. Nothing is forgotten to
    make room (learning forgets at the cap, docs/design/science.md §11.9; a setting is no reason to
    forget a map's places at a start or a restore): the operator raises the setting back."""

    def __init__(self, what: str, rows_held: int, max_observations: int, outcome: str) -> None:
        MapError.__init__(self, f"{what} holds {rows_held} rows, more than CORTEXLOC_MAX_OBSERVATIONS="
                          f"{max_observations}; {outcome}: raise CORTEXLOC_MAX_OBSERVATIONS to at least "
                          f"{rows_held} and restart the service")
        self.rows_held, self.max_observations = rows_held, max_observations


class MapAlreadyExists(MapError):  # noqa: N818
    def __init__(self, map_id: str) -> None:
        super().__init__(f"map {map_id!r} exists")
        self.map_id = map_id


class DataDirectoryInUse(MapError):  # noqa: N818
    """Another process has the data directory's maps open (`storage.lock`): this one touches nothing."""


class UnlistedMaps(MapAlreadyExists):
    """Map directories hold a map the catalog does not list (a catalog lost or replaced, or another
    process's map): they are never deleted or made anew (docs/design/service.md §4.1)."""

    def __init__(self, map_ids: list[str]) -> None:
        MapError.__init__(self, f"maps/{', maps/'.join(map_ids)} hold(s) a map the catalog does not list; "
                          "it is left as it is: restore catalog.sqlite, or move the directory away")
        self.map_id = map_ids[0]
        self.map_ids = map_ids


class MapLimit(MapError):  # noqa: N818
    def __init__(self, max_maps: int) -> None:
        super().__init__(f"at most {max_maps} maps")
        self.max_maps = max_maps


class MapTooLarge(MapError):  # noqa: N818
    def __init__(self, required_bytes: int, max_bytes: int) -> None:
        super().__init__(f"this configuration preallocates {required_bytes} bytes, more than "
                         f"CORTEXLOC_MAX_MAP_BYTES={max_bytes}")
        self.required_bytes, self.max_bytes = required_bytes, max_bytes


class MemoryBudgetExceeded(MapError):  # noqa: N818
    """What `map_id` asks for does not fit in the process-wide memory budget (docs/design/service.md
    §1.8): `used_bytes` are held (with the room kept for a recovery's second memory), `asked_bytes`
    more were asked, `total_bytes` is the budget."""

    def __init__(self, map_id: str, used_bytes: int, asked_bytes: int, total_bytes: int) -> None:
        super().__init__(f"map {map_id!r} asks for {asked_bytes} bytes of memory; {used_bytes} of the "
                         f"{total_bytes} of CORTEXLOC_MEMORY_BUDGET_BYTES are in use or kept for a "
                         "recovery's second memory, "
                         f"{max(0, total_bytes - used_bytes)} free; delete a map or raise the budget")
        self.map_id = map_id
        self.used_bytes, self.asked_bytes, self.total_bytes = used_bytes, asked_bytes, total_bytes
        self.free_bytes = max(0, total_bytes - used_bytes)


class InvalidMapId(MapError):  # noqa: N818
    def __init__(self, map_id: str, pattern: str) -> None:
        super().__init__(f"map_id {map_id!r} must match {pattern}")
        self.errors = [{"location": "body", "name": "map_id", "message": "invalid identifier"}]


class InvalidConfiguration(MapError):  # noqa: N818
    """Map parameters that cannot be frozen; `errors` names each one ([{location, name, message}])."""

    def __init__(self, message: str, errors: list[dict[str, Any]]) -> None:
        super().__init__(message)
        self.errors = errors


class InvalidCamera(MapError):  # noqa: N818
    """`metadata.camera` makes no geometric sense for the frame it came with (`models.geometry.
    camera_problems`, checked once the frame is decoded); `errors` names each field
    ([{location, name, message}]). Nothing changed."""

    def __init__(self, problems: list[tuple[str, str]]) -> None:
        super().__init__("metadata: " + "; ".join(f"camera.{name}: {why}" for name, why in problems))
        self.errors = [{"location": "query", "name": f"metadata.camera.{name}", "message": why}
                       for name, why in problems]


class SnapshotNotFound(MapError):  # noqa: N818
    def __init__(self, map_id: str, snapshot_id: str) -> None:
        super().__init__(f"no snapshot {snapshot_id!r} of map {map_id!r}")
        self.map_id = map_id


class SnapshotInUse(MapError):  # noqa: N818
    """The snapshot the map's next recovery starts from (the newest on its branch): deleting it before
    a newer one exists would make that recovery replay from an older one (docs/design/service.md §1.5)."""

    def __init__(self, map_id: str, snapshot_id: str) -> None:
        super().__init__(f"snapshot {snapshot_id!r} is the one map {map_id!r} recovers from (the newest on "
                         "its branch); take a newer snapshot first")
        self.map_id, self.snapshot_id = map_id, snapshot_id


class MapRestored(MapError):  # noqa: N818
    """A learned post's row was stepped, then a restore rolled the map back past it before the row was
    durable: the row is not in the map (only in the pre-restore snapshot), so the post is not
    acknowledged. Posting the frame again learns it on the restored map."""

    def __init__(self, map_id: str, seq: int | None) -> None:
        row = "" if seq is None else f" (seq {seq})"
        super().__init__(f"map {map_id!r} was restored to a snapshot while this frame's row{row} was being "
                         "stored: the row is not in the map; post the frame again to learn it")
        self.map_id = map_id


class InsufficientStorage(MapError):  # noqa: N818
    """No room to write (a full disk, a quota, the file-size limit: `storage._common.is_full_error`); what
    the message names was not written and the map is unchanged."""


class Overloaded(MapError):  # noqa: N818
    """`what` (the encoder pool, the keyframe extractions) has `limit` requests in flight; retry after
    `retry_after` seconds."""

    def __init__(self, limit: int, retry_after: int = 1, what: str = "the encoder queue") -> None:
        super().__init__(f"{what} is full ({limit} requests in flight)")
        self.retry_after = retry_after


class ClientGone(Exception):  # noqa: N818
    """The client went away before its post reached the map's writer: the work not yet started was
    skipped and nothing changed (docs/design/service.md §6). No `MapError`: no problem+json answers it,
    nobody is left to read one (the HTTP layer records 499, as for a client gone mid-upload)."""


class ShardUnavailable(MapError):  # noqa: N818
    """The scale-out's shard that owns the map is restarting, or the map is moving between shards
    (service.scaleout; docs/scaling.md): retry after `retry_after` seconds, with the same
    Idempotency-Key (a post the shard committed before it died is replayed, not learned twice).

    `outcome_unknown`: the request was handed to the shard, which did not answer (its replica died with
    it, or it passed the ingress's `call_timeout_s`): it may have been done. Unlike the service's other
    503s (refused before anything was done), a client sends it again only where a repeat is safe."""

    def __init__(self, map_id: str, shard: str, why: str, retry_after: int = 2,
                 outcome_unknown: bool = False) -> None:
        super().__init__(f"map {map_id!r} is unavailable: {why}"
                         + ("; the request reached it, and may have been done" if outcome_unknown else ""))
        self.map_id, self.shard, self.retry_after = map_id, shard, retry_after
        self.outcome_unknown = outcome_unknown


class EncoderUnavailable(MapError):  # noqa: N818
    """The scale-out's encoder replica died or is being replaced while it held this frame
    (service.scaleout; docs/scaling.md): nothing was stored; retry after `retry_after` seconds with the
    same Idempotency-Key."""

    def __init__(self, why: str, retry_after: int = 2) -> None:
        super().__init__(f"the encoder deployment did not answer ({why}); it is being replaced")
        self.retry_after = retry_after


class StreamLimit(MapError):  # noqa: N818
    """A new stream, while each of the map's `max_streams` streams posted within `keep_seconds`: none may
    be evicted yet; `retry_after` seconds until the least recently used one may."""

    def __init__(self, max_streams: int, keep_seconds: float, retry_after: int) -> None:
        super().__init__(f"this map holds its maximum of {max_streams} streams and each posted within the "
                         f"last {keep_seconds:g} s (CORTEXLOC_STREAM_KEEP_SECONDS); a new stream may "
                         f"replace the least recently used one in {retry_after} s")
        self.max_streams, self.keep_seconds, self.retry_after = max_streams, keep_seconds, retry_after


class ObservationNotFound(MapError):  # noqa: N818
    def __init__(self, map_id: str, seq: int, what: str = "observation") -> None:
        super().__init__(f"map {map_id!r} has no {what} with seq {seq}")
        self.map_id, self.seq = map_id, seq


class RecentAnswerNotFound(MapError):  # noqa: N818
    """No query thumbnail kept with that recent answer (none taken, over the ring's budget, or fallen off
    the ring)."""

    def __init__(self, map_id: str, answer_id: int) -> None:
        super().__init__(f"map {map_id!r} keeps no thumbnail of recent answer {answer_id}")
        self.map_id, self.answer_id = map_id, answer_id


class IdempotencyKeyReused(MapError):  # noqa: N818
    """An Idempotency-Key seen before with another request (body or parameters); nothing was done."""

    def __init__(self, key: str) -> None:
        super().__init__(f"Idempotency-Key {key!r} was used for another request on this map; a retry must "
                         "send the same body and parameters, a new request a new key")
        self.key = key
