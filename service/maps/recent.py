"""The recent answers of one map: a bounded ring in memory, for watching a map work (the viewer at
`/ui`, `GET /v1/maps/{map_id}/recent`; docs/design/service.md §1.7).

It holds each observation's reply as the client received it, whatever that reply holds, with the time it
was answered. It is not durable: a restart, a delete or a restore starts it empty (after a restore
the answers describe a map state that no longer exists: their seqs may be reused by new
observations). The store (docs/design/service.md §4) is the record of what was learned; this is
only a window onto the last answers, localisations included.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Generic, TypeVar

__all__ = ["RECENT_CAPACITY", "Recent", "RecentAnswers"]

#: Answers kept per map: a few minutes of a 1-2 Hz camera, bounded memory (a reply is ~2 KB).
RECENT_CAPACITY = 256

R = TypeVar("R")


@dataclass(frozen=True)
class Recent(Generic[R]):
    """One answer: when it was given (UTC, ISO 8601), its stream, and the reply itself."""

    received_at: str
    stream: str
    reply: R


class RecentAnswers(Generic[R]):
    """The last `capacity` answers of a map, oldest first; older ones fall off."""

    def __init__(self, capacity: int = RECENT_CAPACITY) -> None:
        self.capacity = capacity
        self._ring: deque[Recent[R]] = deque(maxlen=capacity)
        # Appends come from the event loop, reads may come from anywhere: a snapshot of the ring is
        # taken under the lock so a reader never iterates a deque that is being appended to.
        self._lock = threading.Lock()

    def add(self, stream: str, reply: R) -> None:
        entry = Recent(datetime.now(UTC).isoformat(timespec="milliseconds"), stream, reply)
        with self._lock:
            self._ring.append(entry)

    def last(self, limit: int, stream: str | None = None) -> list[Recent[R]]:
        """The newest `limit` answers (of `stream` if given), oldest first."""
        with self._lock:
            entries = list(self._ring)
        if stream is not None:
            entries = [e for e in entries if e.stream == stream]
        return entries[-limit:] if limit > 0 else []

    def clear(self) -> None:
        """Forget every answer (a restore: they may name observations it dropped)."""
        with self._lock:
            self._ring.clear()

    def __len__(self) -> int:
        return len(self._ring)
