"""Reading a map's stored observations back (docs/design/service.md §1.2): one by seq, a page in seq order
(the map viewer's trajectories), a thumbnail. Reads only: `MapStore` is safe to read from any thread
while the map's writer appends."""

from __future__ import annotations

from service.maps.errors import ObservationNotFound
from service.maps.results import StoredObservation
from storage.mapschema import JoinedRow
from storage.mapstore import MapStore, Observation

__all__ = ["observation", "page", "thumbnail"]


def _stored(row: Observation, has_thumbnail: bool) -> StoredObservation:
    return StoredObservation(seq=row.seq, observation_id=row.observation_id, stream=row.stream,
                             label=row.label, created_at=row.created_at, image_sha256=row.image_sha256,
                             metadata=row.metadata, has_thumbnail=has_thumbnail)


def _joined(row: JoinedRow) -> StoredObservation:
    return StoredObservation(seq=row.seq, observation_id=row.observation_id, stream=row.stream,
                             label=row.label, created_at=row.created_at, image_sha256=row.image_sha256,
                             metadata=row.metadata, has_thumbnail=False, joined_to=row.place_seq)


def observation(map_id: str, store: MapStore, seq: int) -> StoredObservation:
    """Raises ObservationNotFound. A row a warm-up join turned into a visit (docs/design/science.md
    §11.8) answers with its record as acknowledged, without its thumbnail, and the row it joined."""
    row = store.get(seq)
    if row is None:
        joined = store.joined_row(seq)
        if joined is None:
            raise ObservationNotFound(map_id, seq)
        return _joined(joined)
    return _stored(row, seq in store.with_thumbnails([seq]))


def page(store: MapStore, after_seq: int, limit: int) -> list[StoredObservation]:
    """At most `limit` (<= 500) observations with seq > `after_seq`, in seq order: the rows held and
    the rows a warm-up join turned into visits (`joined_to`), so that within an epoch a page read again
    holds what it held (a join deletes a row after a follower may have read it, §11.8)."""
    rows = store.page(after_seq, limit)
    thumbs = store.with_thumbnails(r.seq for r in rows)
    found = {r.seq: _stored(r, r.seq in thumbs) for r in rows}
    # read after the rows: a join that committed between the two reads shows its row once, as joined
    found.update((j.seq, _joined(j)) for j in store.joined_rows(after_seq, limit))
    return [found[seq] for seq in sorted(found)[:limit]]


def thumbnail(map_id: str, store: MapStore, seq: int) -> bytes:
    """The JPEG kept with `seq`. Raises ObservationNotFound (no such row, or none kept)."""
    jpeg = store.thumbnail(seq)
    if jpeg is None:
        known = store.get(seq) is not None or store.joined_row(seq) is not None
        raise ObservationNotFound(map_id, seq, "thumbnail" if known else "observation")
    return jpeg
