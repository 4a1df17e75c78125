"""The scale-out's map -> shard table (`shards.sqlite` on the ingress's volume; docs/scaling.md,
docs/design/service.md §9).

One row per map: the shard that owns it (its only writer) and whether it is `serving` or `moving` (a
move between shards is draining it: requests get 503 + Retry-After). Every change is one committed
transaction (WAL, `synchronous=FULL`, like every storage file), so a restarted ingress routes exactly
as the one before it did.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Literal, NamedTuple

from storage._common import connect, transaction

__all__ = ["ShardRoute", "ShardTable"]

RouteState = Literal["serving", "moving"]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS routes (
    map_id TEXT PRIMARY KEY,
    shard TEXT NOT NULL,
    state TEXT NOT NULL CHECK (state IN ('serving', 'moving'))
)
"""


class ShardRoute(NamedTuple):
    """Where a map lives: its owning shard and its state."""

    map_id: str
    shard: str
    state: RouteState


class ShardTable:
    """map_id -> (shard, state), durable; thread-safe through one lock.

    Args:
        path: the SQLite file (created with its directory when missing).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._conn = connect(self.path)
        with transaction(self._conn):
            self._conn.execute(_SCHEMA)

    def get(self, map_id: str) -> ShardRoute | None:
        with self._lock:
            row = self._conn.execute("SELECT map_id, shard, state FROM routes WHERE map_id = ?",
                                     (map_id,)).fetchone()
        return ShardRoute(*row) if row else None

    def all(self) -> list[ShardRoute]:
        with self._lock:
            rows = self._conn.execute("SELECT map_id, shard, state FROM routes ORDER BY map_id").fetchall()
        return [ShardRoute(*r) for r in rows]

    def set(self, map_id: str, shard: str, state: RouteState = "serving") -> None:
        """Insert or replace the map's route (committed when it returns)."""
        with self._lock, transaction(self._conn):
            self._conn.execute("INSERT INTO routes (map_id, shard, state) VALUES (?, ?, ?) ON CONFLICT "
                               "(map_id) DO UPDATE SET shard = excluded.shard, state = excluded.state",
                               (map_id, shard, state))

    def add_missing(self, map_id: str, shard: str) -> bool:
        """Route `map_id` to `shard` unless it already has a route; True when it was added."""
        with self._lock, transaction(self._conn):
            cur = self._conn.execute("INSERT OR IGNORE INTO routes (map_id, shard, state) "
                                     "VALUES (?, ?, 'serving')", (map_id, shard))
            return cur.rowcount == 1

    def delete(self, map_id: str) -> None:
        with self._lock, transaction(self._conn):
            self._conn.execute("DELETE FROM routes WHERE map_id = ?", (map_id,))

    def close(self) -> None:
        with self._lock:
            self._conn.close()
