"""Idempotent observation posts (docs/design/service.md §1.2, §4.2): a repeat of a post with the same
`Idempotency-Key` is answered with the first reply and changes nothing.

Where the first reply is kept:

- a learned post: in `map.sqlite`'s `idempotency_keys`, in the transaction that commits its row
  (`storage.mapschema.KeyRecord` on the `NewObservation`), so a reply is on disk exactly when its row
  is, across restarts, and a restore that drops the row drops its key with it (a snapshot is a copy of
  the file);
- a localisation post (learn=false) learns nothing, so its reply is kept in memory only (`KeyCache`,
  bounded, lost at a restart): a repeat after a restart runs again, as a fresh localisation would.

Both are looked up in the map's writer, before the step, so two posts with one key in flight at once
never both step: the second finds the first's reply.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from service.maps.errors import IdempotencyKeyReused
from service.maps.results import ObservationResult
from storage.mapschema import KeyRecord
from storage.mapstore import MapStore

__all__ = ["KEY_PATTERN", "IdempotentPost", "KeyCache", "Reply", "apply_once", "fingerprint", "lookup"]

#: What an Idempotency-Key may be: a UUID, a hash, a ULID, ... (the one home of this rule).
KEY_PATTERN = r"^[A-Za-z0-9._:-]{8,128}$"


def fingerprint(body_sha256: str, **params: Any) -> str:
    """SHA-256 of what a post asks: its body's digest and every parameter that changes the answer."""
    return hashlib.sha256(json.dumps({"body": body_sha256, **params}, sort_keys=True,
                                     separators=(",", ":")).encode()).hexdigest()


@dataclass
class IdempotentPost:
    """One post with a key. `seal` turns the result into the reply's JSON (the route's, with what only
    HTTP knows); the writer seals once and keeps the text in `body`.

    Attributes:
        front_ms: the timings measured before the writer (decode, encode), added when sealing.
    """

    key: str
    fingerprint: str
    seal: Callable[[ObservationResult], str]
    front_ms: dict[str, float] = field(default_factory=dict)
    body: str | None = None

    def record(self, result: ObservationResult) -> KeyRecord:
        """Writer: seal the reply (its timings are those measured so far) and return it as stored."""
        self.body = self.seal(dataclasses.replace(result, timings_ms={**self.front_ms, **result.timings_ms}))
        return KeyRecord(self.key, self.fingerprint, self.body)


@dataclass(frozen=True)
class Reply:
    """An idempotent post's answer: the reply's JSON; `replayed` when it is an earlier post's;
    `thumbnail` as `ObservationResult.thumbnail` (None for a replay)."""

    body: str
    replayed: bool
    thumbnail: bytes | None = None


#: The most reply text a map's cache holds: a reply with 100 matches of 4 KiB metadata each is ~400 KB,
#: so a count alone would let 1,024 of them hold 400 MB per map.
CACHE_MAX_CHARS = 32 * 2**20


class KeyCache:
    """The replies of the last `size` localisation posts with a key, at most `CACHE_MAX_CHARS` of reply
    text in all (writer only; 0 keeps none)."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._records: OrderedDict[str, KeyRecord] = OrderedDict()
        self._chars = 0

    def get(self, key: str) -> KeyRecord | None:
        return self._records.get(key)

    def put(self, record: KeyRecord) -> None:
        old = self._records.pop(record.key, None)
        self._chars -= len(old.reply) if old is not None else 0
        self._records[record.key] = record
        self._chars += len(record.reply)
        while self._records and (len(self._records) > self.size or self._chars > CACHE_MAX_CHARS):
            self._chars -= len(self._records.popitem(last=False)[1].reply)

    def clear(self) -> None:
        """Forget every reply (a restore: they may name observations it dropped)."""
        self._records.clear()
        self._chars = 0


def lookup(store: MapStore, cache: KeyCache | None, post: IdempotentPost) -> Reply | None:
    """The earlier reply to `post`'s key in the store or `cache` (None: the store only), or None.

    Raises:
        IdempotencyKeyReused: the key answered another request (another fingerprint).
    """
    found = store.key_record(post.key) or (cache.get(post.key) if cache is not None else None)
    if found is None:
        return None
    if found.fingerprint != post.fingerprint:
        raise IdempotencyKeyReused(post.key)
    return Reply(found.reply, replayed=True)


def apply_once(store: MapStore, cache: KeyCache, post: IdempotentPost, learn: bool,
               apply: Callable[[], ObservationResult]) -> Reply:
    """Writer: the earlier reply to `post`, else `apply()` (which seals a learned post into its row's
    transaction) and its sealed reply; a localisation's reply goes to the cache."""
    earlier = lookup(store, cache, post)
    if earlier is not None:
        return earlier
    result = apply()
    if not learn:
        cache.put(post.record(result))
    assert post.body is not None
    return Reply(post.body, replayed=False)
