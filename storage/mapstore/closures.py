"""`map.sqlite`'s loop-closure log and repairs (docs/design/service.md §4.2; docs/design/science.md §11.6,
§11.11, §12): every revisit a stream was told of (bounded: the oldest pruned), logged with its learned
row, its visit or alone; a repair's transaction (visits re-made as rows, rows given back their place,
closures retracted) and its log.
"""

from __future__ import annotations

import json
import sqlite3
import uuid
from collections.abc import Iterable
from typing import Any

from storage._common import StorageError, transaction, utc_now
from storage.mapschema import (
    COLUMNS,
    INPUT_DTYPE,
    Holds,
    LoopClosure,
    NewClosure,
    Repair,
    Visit,
    encode,
    load_json,
)

__all__ = ["Closures", "closure_columns", "closure_params"]


def closure_columns(holds: Holds) -> str:
    """What `closures` reads of a logged closure's later columns (NULL for those the file lacks)."""
    return ", ".join([
        "c.verification" if holds.closure_verification else "NULL",
        "c.consolidated_into" if holds.closure_consolidated_into else "NULL",
        "c.retracts" if holds.closure_retracts else "NULL",
        "c.span, c.span_seqs" if holds.closure_span else "NULL, NULL"])


class Closures:
    """`MapStore`'s loop closures and repairs (module docstring). It owns how many closures are kept
    and what its reads select (`closure_columns`, fixed at open)."""

    max_closures: int | None
    _closure_columns: str
    _closure_floor: int

    def add_closure(self, closure: NewClosure) -> int:
        """Log a localising stream's loop closure alone (it stores no observation) and COMMIT.

        Returns:
            Its log id; where its idempotency key is already logged (nothing written), that entry's. A key
            whose entry the log's cap pruned is logged anew.

        Raises:
            StorageFull: no room to write; nothing was written.
        """
        with self._lock:
            conn = self._db()
            with transaction(conn):
                if not self._log_closures(conn, [closure_params(closure, None)]):  # its key's entry
                    return int(conn.execute("SELECT id FROM loop_closures WHERE idempotency_key = ?",
                                            (closure.key,)).fetchone()[0])
                return int(conn.execute("SELECT max(id) FROM loop_closures").fetchone()[0])

    def _log_closures(self, conn: sqlite3.Connection, params: list[tuple[Any, ...]]) -> int:
        """In a transaction: insert (a repeated key inserts nothing), then keep the last `max_closures`."""
        if not params:
            return 0
        before, first = conn.total_changes, self._next_closure_id(conn)
        # ids given, not SQLite's max + 1: after a restore they continue above the closure floor (a
        # repeated key's id is skipped: ids increase, with gaps)
        conn.executemany("INSERT OR IGNORE INTO loop_closures (id, stream, seq, place_seq, confidence, "
                         "support, metadata, idempotency_key, created_at, verification, consolidated_into, "
                         "span, span_seqs) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                         [(first + i, *p) for i, p in enumerate(params)])
        added = conn.total_changes - before
        if added:
            self._prune_closures(conn)
        return added

    def _next_closure_id(self, conn: sqlite3.Connection) -> int:
        """The next log id: above every id in the log and above the closure floor (`MapStore.open`)."""
        last = int(conn.execute("SELECT coalesce(max(id), 0) FROM loop_closures").fetchone()[0])
        return max(last, self._closure_floor) + 1

    def next_closure_id(self) -> int:
        """The id the next logged closure gets: the writer, the log's only writer, tells a revisit's
        reply its entry before the transaction that logs it (an idempotent reply is sealed into it)."""
        if not self.holds.loop_closures:
            return self._closure_floor + 1
        with self._lock:
            return self._next_closure_id(self._db())

    def last_closure_id(self) -> int:
        """The newest log id handed out (the closure floor where the log holds none above it)."""
        return self.next_closure_id() - 1

    def _prune_closures(self, conn: sqlite3.Connection) -> None:
        """In a transaction: keep the last `max_closures` entries of the loop-closure log. Ids have gaps
        (those a restore rolled back stay handed out; a batch's repeated key skips one), so the cut is
        counted in entries; only where the ids span more than the cap can there be more entries than it
        (the span check is two index look-ups, the count walks the cap's entries)."""
        if self.max_closures is None:
            return
        low, high = conn.execute("SELECT min(id), max(id) FROM loop_closures").fetchone()
        if low is None or high - low + 1 <= self.max_closures:
            return
        conn.execute("DELETE FROM loop_closures WHERE id <= (SELECT id FROM loop_closures ORDER BY id DESC "
                     "LIMIT 1 OFFSET ?)", (self.max_closures,))

    def closures(self, after: int, limit: int) -> list[LoopClosure]:
        """At most `limit` logged loop closures with id > `after`, oldest first, with both rows."""
        if not self.holds.loop_closures:
            return []
        with self._lock:
            found = self._db().execute(
                "SELECT c.id, c.stream, c.seq, o.observation_id, c.metadata, c.place_seq, p.observation_id, "
                "p.stream, p.label, p.metadata, c.confidence, c.support, c.created_at, "
                f"{self._closure_columns} "
                "FROM loop_closures c JOIN observations p ON p.seq = c.place_seq "
                "LEFT JOIN observations o ON o.seq = c.seq WHERE c.id > ? ORDER BY c.id LIMIT ?",
                (int(after), int(limit))).fetchall()
        return [LoopClosure(id=int(r[0]), stream=r[1], seq=None if r[2] is None else int(r[2]),
                            observation_id=r[3], metadata=load_json(r[4]), place_seq=int(r[5]),
                            place_observation_id=r[6], place_stream=r[7], place_label=r[8],
                            place_metadata=load_json(r[9]), confidence=float(r[10]), support=int(r[11]),
                            created_at=r[12], verification=load_json(r[13]),
                            consolidated_into=None if r[14] is None else int(r[14]),
                            retracts=None if r[15] is None else int(r[15]),
                            span=None if r[16] is None else int(r[16]),
                            span_seqs=None if r[17] is None else tuple(load_json(r[17]))) for r in found]

    def oldest_closure_id(self) -> int | None:
        """The oldest log id still kept (None: the log is empty): a reader past `after` below it - 1 may
        have missed entries the cap pruned."""
        if not self.holds.loop_closures:
            return None
        with self._lock:
            low = self._db().execute("SELECT min(id) FROM loop_closures").fetchone()[0]
        return None if low is None else int(low)

    def closure_count(self) -> int:
        """Loop closures in the log."""
        if not self.holds.loop_closures:
            return 0
        with self._lock:
            return int(self._db().execute("SELECT count(*) FROM loop_closures").fetchone()[0])

    def joined(self) -> dict[int, int]:
        """Learned row -> the row its loop closure named, from the log (the place of a row stored before
        version 5, docs/design/science.md §11.8)."""
        if not self.holds.loop_closures:
            return {}
        # a retraction joins nothing
        retraction = " AND retracts IS NULL" if self.holds.closure_retracts else ""
        with self._lock:
            return {int(r[0]): int(r[1]) for r in self._db().execute(
                f"SELECT seq, place_seq FROM loop_closures WHERE seq IS NOT NULL{retraction}")}

    def repair(self, splits: Iterable[Visit], unjoins: Iterable[tuple[int, int]],
               retracts: Iterable[int]) -> list[int]:
        """Undo merges in one transaction (docs/design/science.md §11.6, service.md §4.2): each visit of
        `splits` re-made as a row of its own (appended: its stream, code, winner cells, metadata, clock
        and the row its stream continued; no image digest, a visit keeps none), each (row, the row whose
        place it joined) of `unjoins` given back its own place, and for each closure id of `retracts` a
        retraction entry (its pair, confidence and support 0, `retracts` = that id) in the loop-closure
        log; all logged in `repairs`. Durable when this returns; all or nothing.

        Returns:
            The seqs of the re-made rows, in the order of `splits`.

        Raises:
            StorageError: a file before schema version 9 (opened read-only). StorageFull: nothing
            was written.
        """
        splits, unjoins, retracts = list(splits), list(unjoins), list(retracts)
        with self._lock:
            conn = self._db()
            if not self.holds.repairs:
                raise StorageError(f"{self.path}: schema version {self.meta.schema_version} has no repairs")
            first = max(self._last_seq, self._seq_floor) + 1
            now = utc_now()
            rows = [(first + i, str(uuid.uuid4()), v.stream, v.context_prev_seq, None, v.created_at, "",
                     encode(v.input_sdr, INPUT_DTYPE, "input_sdr"),
                     encode(v.winner_cells, self._cell_dtype, "winner_cells"),
                     None if v.metadata is None else json.dumps(v.metadata, separators=(",", ":")), None)
                    for i, v in enumerate(splits)]
            logged = [("split", first + i, v.id, v.seq, now) for i, v in enumerate(splits)]
            logged += [("unjoin", int(seq), None, int(was), now) for seq, was in unjoins]
            with transaction(conn):
                conn.executemany(f"INSERT INTO observations ({COLUMNS}) VALUES (?,?,?,?,?,?,?,?,?,?,?)",
                                 rows)
                conn.executemany("INSERT INTO repairs (kind, seq, visit, was, created_at) "
                                 "VALUES (?, ?, ?, ?, ?)", logged)
                following = self._next_closure_id(conn)  # (a closure already retracted skips its id)
                conn.executemany(
                    "INSERT INTO loop_closures (id, stream, seq, place_seq, confidence, support, metadata, "
                    "created_at, consolidated_into, retracts) SELECT ?, stream, seq, place_seq, 0, 0, "
                    "metadata, ?, consolidated_into, id FROM loop_closures c "
                    "WHERE id = ? AND retracts IS NULL "
                    "AND NOT EXISTS (SELECT 1 FROM loop_closures r WHERE r.retracts = c.id)",
                    [(following + i, now, int(c)) for i, c in enumerate(retracts)])
                if retracts:
                    self._prune_closures(conn)
            if rows:  # only after COMMIT returned, as `append_many`
                self._last_seq = first + len(rows) - 1
                self._count += len(rows)
            return [first + i for i in range(len(rows))]

    def repairs(self) -> list[Repair]:
        """The logged repairs, in log order (empty before schema version 9)."""
        if not self.holds.repairs:
            return []
        with self._lock:
            found = self._db().execute(
                "SELECT id, kind, seq, visit, was, created_at FROM repairs ORDER BY id").fetchall()
        return [Repair(id=int(r[0]), kind=r[1], seq=int(r[2]), visit=None if r[3] is None else int(r[3]),
                       was=int(r[4]), created_at=r[5]) for r in found]

    def retracted(self) -> set[int]:
        """The ids of the closures a retraction entry withdraws (kept while the retraction is logged)."""
        if not self.holds.closure_retracts:
            return set()
        with self._lock:
            return {int(r[0]) for r in self._db().execute(
                "SELECT retracts FROM loop_closures WHERE retracts IS NOT NULL")}


def closure_params(c: NewClosure, seq: int | None, consolidated_into: int | None = None) -> tuple[Any, ...]:
    """A closure as the log's INSERT takes it (`seq`: its learned row, None for a visit's or a localising
    stream's; `consolidated_into`: a visit's row)."""
    meta = None if c.metadata is None else json.dumps(c.metadata, separators=(",", ":"))
    verification = None if c.verification is None else json.dumps(c.verification, separators=(",", ":"))
    span_seqs = None if c.span_seqs is None else json.dumps([int(s) for s in c.span_seqs])
    return (str(c.stream), seq, int(c.place_seq), float(c.confidence), int(c.support), meta, c.key,
            str(c.created_at), verification, consolidated_into, None if c.span is None else int(c.span),
            span_seqs)
