"""The id rules of maps and snapshots (docs/design/service.md §1.1, §1.5): storage's, because an id is
also a directory name, named here for the HTTP layer's path and body patterns; and the id a map created
without one is given."""

from __future__ import annotations

import hashlib
import uuid

from storage.catalog import MAP_ID_RE, SNAPSHOT_ID_RE

__all__ = ["MAP_ID_RE", "SNAPSHOT_ID_RE", "key_digest", "new_map_id"]


def key_digest(idempotency_key: str) -> str:
    """An `Idempotency-Key`'s SHA-256 (64 hex digits): what a map keeps of the key that made it (§1.1)."""
    return hashlib.sha256(idempotency_key.encode()).hexdigest()


def new_map_id(idempotency_key: str | None = None) -> str:
    """The id of a map created without one (docs/design/service.md §1.1): `map-` and 12 hex digits, random;
    with an `Idempotency-Key`, the key's SHA-256, so a retry of the creation names the map the first made
    (the service and the scale-out ingress, which picks the id before a shard sees the body, agree)."""
    if idempotency_key is None:
        return f"map-{uuid.uuid4().hex[:12]}"
    return f"map-{key_digest(idempotency_key)[:12]}"
