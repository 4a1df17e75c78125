"""The recent answers of one map: a bounded ring in memory, for watching a map work (the viewer at
`/ui`, `GET /v1/maps/{map_id}/recent`; docs/design/service.md §1.7).

It holds each observation's reply as the client received it, whatever that reply holds, with the time it
was answered, and for a map that keeps thumbnails the query frame's small JPEG (a localised frame's image
is stored nowhere else), within a byte budget. It is not durable: a restart, a delete or a restore
starts it empty (after a restore the answers describe a map state that no longer exists: their seqs may
be reused by new observations). The store (docs/design/service.md §4) is the record of what was
learned; this is only a window onto the last answers, localisations included.
"""

from __future__ import annotations

import threading
from collections import OrderedDict, deque
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, Generic, TypeVar

from service.maps.errors import RecentAnswerNotFound

__all__ = ["RECENT_CAPACITY", "RECENT_THUMBNAIL_BYTES", "Recent", "RecentAnswers", "kept_thumbnail"]

#: Answers kept per map: a few minutes of a 1-2 Hz camera, bounded memory (a reply is ~2 KB).
RECENT_CAPACITY = 256
#: Bytes of query thumbnails kept per map: the newest answers' (a 128-pixel JPEG is 2-6 KB, so a ring of
#: ordinary frames keeps all of them; noisy ones lose their oldest thumbnails first).
RECENT_THUMBNAIL_BYTES = 2 * 2**20

R = TypeVar("R")


@dataclass(frozen=True)
class Recent(Generic[R]):
    """One answer: its number in the ring (counted from 1 since the map was opened, never reused
    while the process runs), when it was given (UTC, ISO 8601), its stream, and the reply itself."""

    answer_id: int
    received_at: str
    stream: str
    reply: R


class RecentAnswers(Generic[R]):
    """The last `capacity` answers of a map, oldest first; older ones fall off. Query thumbnails are kept
    for the newest answers within `thumbnail_bytes`."""

    def __init__(self, capacity: int = RECENT_CAPACITY,
                 thumbnail_bytes: int = RECENT_THUMBNAIL_BYTES) -> None:
        self.capacity = capacity
        self.thumbnail_bytes = thumbnail_bytes
        self._ring: deque[Recent[R]] = deque(maxlen=capacity)
        self._thumbs: OrderedDict[int, bytes] = OrderedDict()  # answer_id -> JPEG, oldest first
        self._thumbs_size = 0
        self._count = 0
        # Appends come from the event loop, reads may come from anywhere: a snapshot of the ring is
        # taken under the lock so a reader never iterates a deque that is being appended to.
        self._lock = threading.Lock()

    def add(self, stream: str, reply: R, thumbnail: bytes | None = None) -> None:
        """Keep `reply` (and `thumbnail`, the query frame's JPEG, while the budget allows)."""
        with self._lock:
            self._count += 1
            if len(self._ring) == self.capacity and self._ring:
                self._forget_thumbnail(self._ring[0].answer_id)  # falls off with its answer
            self._ring.append(Recent(self._count, datetime.now(UTC).isoformat(timespec="milliseconds"),
                                     stream, reply))
            if thumbnail is not None and len(thumbnail) <= self.thumbnail_bytes:
                self._thumbs[self._count] = thumbnail
                self._thumbs_size += len(thumbnail)
                while self._thumbs_size > self.thumbnail_bytes:
                    self._forget_thumbnail(next(iter(self._thumbs)))

    def _forget_thumbnail(self, answer_id: int) -> None:
        gone = self._thumbs.pop(answer_id, None)
        self._thumbs_size -= len(gone) if gone is not None else 0

    def last(self, limit: int, stream: str | None = None) -> list[Recent[R]]:
        """The newest `limit` answers (of `stream` if given), oldest first."""
        with self._lock:
            entries = list(self._ring)
        if stream is not None:
            entries = [e for e in entries if e.stream == stream]
        return entries[-limit:] if limit > 0 else []

    def thumbnail(self, answer_id: int) -> bytes | None:
        """The query thumbnail kept with answer `answer_id`, or None (none taken, dropped, or gone)."""
        with self._lock:
            return self._thumbs.get(answer_id)

    def with_thumbnails(self, answer_ids: list[int]) -> set[int]:
        """Which of `answer_ids` have a thumbnail kept."""
        with self._lock:
            return {i for i in answer_ids if i in self._thumbs}

    def clear(self) -> None:
        """Forget every answer (a restore: they may name observations it dropped); numbers go on."""
        with self._lock:
            self._ring.clear()
            self._thumbs.clear()
            self._thumbs_size = 0

    def __len__(self) -> int:
        return len(self._ring)


def kept_thumbnail(map_id: str, ring: RecentAnswers[Any], answer_id: int) -> bytes:
    """The query JPEG kept with answer `answer_id` of `map_id`'s ring.

    Raises:
        RecentAnswerNotFound: none kept (thumbnails off, over the budget, or the answer fell off).
    """
    jpeg = ring.thumbnail(answer_id)
    if jpeg is None:
        raise RecentAnswerNotFound(map_id, answer_id)
    return jpeg
