"""`map.sqlite`'s per-stream and per-row state written with each learned step (docs/design/service.md
§4.2, §4.4; docs/design/science.md §11.9): each stream's resume state (`stream_states`, what a replay
cannot give back; pruned once a snapshot holds it) and each row's recency (`recency`, the clock of its
last use).
"""

from __future__ import annotations

import sqlite3

from storage._common import transaction

__all__ = ["Streams"]


class Streams:
    """`MapStore`'s stream states and recency (module docstring); no state of its own."""

    def _touch(self, conn: sqlite3.Connection, touches: list[tuple[int, int]]) -> None:
        """Within the caller's transaction: rows used at a clock (`recency`, kept at the latest)."""
        if touches and self.holds.recency:
            conn.executemany("INSERT INTO recency (seq, used) VALUES (?, ?) ON CONFLICT (seq) DO UPDATE "
                             "SET used = max(used, excluded.used)", touches)

    def _resume(self, conn: sqlite3.Connection, states: list[tuple[str, int, bytes]]) -> None:
        """Within the caller's transaction: streams' states after their learned steps (`stream_states`)."""
        if states and self.holds.stream_states:
            conn.executemany("INSERT INTO stream_states (stream, clock, state) VALUES (?, ?, ?) ON CONFLICT "
                             "(stream) DO UPDATE SET clock = excluded.clock, state = excluded.state", states)

    def save_stream_state(self, stream: str, state: bytes) -> None:
        """Store `stream`'s state on its own, at the clock of the last row stored, and COMMIT (a stream's
        reset, which no row records: docs/design/service.md §1.3, §4.4). A file before version 7 keeps
        none.

        Raises:
            StorageFull, StoreReadOnly: nothing was written.
        """
        if not self.holds.stream_states:
            return
        with self._lock:
            conn = self._db()
            with transaction(conn):
                self._resume(conn, [(str(stream), int(self._last_seq), bytes(state))])

    def stream_states(self) -> dict[str, bytes]:
        """Stream -> its state after its last learned step, as written with that step
        (`NewObservation.resume`); those a snapshot holds may have been pruned (`prune_stream_states`)."""
        if not self.holds.stream_states:
            return {}
        with self._lock:
            return {r[0]: bytes(r[1]) for r in self._db().execute("SELECT stream, state FROM stream_states")}

    def prune_stream_states(self, through: int) -> int:
        """Delete the stream states written at a clock <= `through` (a snapshot at that seq holds them:
        the replay after it meets none of their steps). Returns how many."""
        if not self.holds.stream_states:
            return 0
        with self._lock:
            conn = self._db()
            with transaction(conn):
                cur = conn.execute("DELETE FROM stream_states WHERE clock <= ?", (int(through),))
            return int(cur.rowcount)

    def recency(self) -> dict[int, int]:
        """Row -> the clock of its last use by a later step (a row's own making is its seq; not here),
        docs/design/science.md §11.9. Empty for a file before version 6."""
        if not self.holds.recency:
            return {}
        with self._lock:
            return {int(r[0]): int(r[1]) for r in self._db().execute("SELECT seq, used FROM recency")}
