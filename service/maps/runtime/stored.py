"""Reading a map's stored observations back (docs/design/service.md §1.2): one by seq, a page in seq order
(the map viewer's trajectories), a thumbnail. Reads only: `MapStore` is safe to read from any thread
while the map's writer appends."""

from __future__ import annotations

from service.maps.errors import ObservationNotFound
from service.maps.results import StoredObservation
from storage.mapstore import MapStore, Observation

__all__ = ["observation", "page", "thumbnail"]


def _stored(row: Observation, has_thumbnail: bool) -> StoredObservation:
    return StoredObservation(seq=row.seq, observation_id=row.observation_id, stream=row.stream,
                             label=row.label, created_at=row.created_at, image_sha256=row.image_sha256,
                             metadata=row.metadata, has_thumbnail=has_thumbnail)


def observation(map_id: str, store: MapStore, seq: int) -> StoredObservation:
    """Raises ObservationNotFound. A row a warm-up join turned into a visit (docs/design/science.md
    §11.8) answers with its record as acknowledged, without its thumbnail."""
    row = store.get(seq)
    if row is None:
        joined = store.joined_row(seq)
        if joined is None:
            raise ObservationNotFound(map_id, seq)
        return StoredObservation(seq=joined.seq, observation_id=joined.observation_id, stream=joined.stream,
                                 label=joined.label, created_at=joined.created_at,
                                 image_sha256=joined.image_sha256, metadata=joined.metadata,
                                 has_thumbnail=False)
    return _stored(row, seq in store.with_thumbnails([seq]))


def page(store: MapStore, after_seq: int, limit: int) -> list[StoredObservation]:
    """At most `limit` (<= 500) observations with seq > `after_seq`, in seq order."""
    rows = store.page(after_seq, limit)
    thumbs = store.with_thumbnails(r.seq for r in rows)
    return [_stored(r, r.seq in thumbs) for r in rows]


def thumbnail(map_id: str, store: MapStore, seq: int) -> bytes:
    """The JPEG kept with `seq`. Raises ObservationNotFound (no such row, or none kept)."""
    jpeg = store.thumbnail(seq)
    if jpeg is None:
        known = store.get(seq) is not None or store.joined_row(seq) is not None
        raise ObservationNotFound(map_id, seq, "thumbnail" if known else "observation")
    return jpeg
