"""`map.sqlite`: one map's frozen metadata and its append-only observations (docs/design/service.md §4.2,
§4.3).

One SQLite file per map, so maps never contend for SQLite's single writer and a map moves between
servers as one directory. The file is the system of record: the in-memory TM and index are rebuilt
from it (snapshot + replay, §4.4), so a row, once committed, is never changed or removed — triggers
refuse UPDATE and DELETE on `observations`, and a restore replaces the whole file instead
(`MapStore.install_copy`). The one exception (schema 12): a warm-up join turns the row it joins into a
visit, which replays it, and deletes the row in the same transaction (docs/design/science.md §11.8).

Sequence numbers: `seq` is assigned here, strictly increasing and never reused. SQLite's own choice
(max(rowid)+1) would reuse seqs after a restore rolls the file back, so the caller passes the
catalog's high-water mark as `seq_floor` and the next seq is `max(last_seq, seq_floor) + 1`.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sqlite3
import threading
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from storage._common import (
    StorageError,
    StorageFull,
    StoreClosed,
    connect,
    is_full_error,
    transaction,
    utc_now,
)
from storage.base.files import atomic_write, fsync_dir
from storage.mapschema import (
    CELL_DTYPES,
    COLUMNS,
    COLUMNS_V1,
    COLUMNS_V4,
    INPUT_DTYPE,
    SCHEMA_VERSION,
    DuplicateObservation,
    KeyRecord,
    LoopClosure,
    MapMeta,
    NewClosure,
    NewObservation,
    NewVisit,
    Observation,
    Repair,
    StoreCorrupt,
    Visit,
    cell_dtype_for,
    create_file,
    decode,
    encode,
    migrate,
    read_meta,
)

__all__ = [
    "CELL_DTYPES",
    "INPUT_DTYPE",
    "SCHEMA_VERSION",
    "DuplicateObservation",
    "KeyRecord",
    "LoopClosure",
    "MapMeta",
    "MapStore",
    "NewClosure",
    "NewObservation",
    "NewVisit",
    "Observation",
    "Repair",
    "StorageError",
    "StorageFull",
    "StoreClosed",
    "StoreCorrupt",
    "Visit",
    "cell_dtype_for",
]


_PAGE = 1024  # rows per SELECT in `rows()`: bounded memory, and no read transaction held between pages


class MapStore:
    """One map's `map.sqlite`: frozen meta + append-only observations.

    Thread-safe: every method takes the store's lock, so the map's writer thread and readers such as
    `GET /v1/maps/{id}` (request threads) can share one store. Count and last seq are cached in memory:
    this object is the file's only writer (docs/design/service.md §6: one writer per map).

    Plain `sqlite3`, not `sqlite_utils` (which the catalog uses): the append path is the service's
    durability contract (§4.3), and each of its steps is spelled out here: an explicit `BEGIN
    IMMEDIATE` ... `COMMIT` per group, seqs assigned before the INSERT and counted only after COMMIT
    returns, the file's triggers' errors and SQLITE_FULL mapped to our errors. A helper that opens
    its own transactions or retries would blur exactly that.
    """

    def __init__(self, path: Path, conn: sqlite3.Connection, meta: MapMeta, seq_floor: int,
                 max_keys: int | None = None, max_closures: int | None = None) -> None:
        """Use `MapStore.create` or `MapStore.open`."""
        self.path = path
        self.meta = meta
        self.max_keys = max_keys
        self.max_closures = max_closures
        # A version 1 file opened read-only is not migrated: its rows read with metadata NULL, and it
        # has no thumbnails or keys.
        self._v2 = meta.schema_version >= 2
        self._v5 = meta.schema_version >= 5  # places: a row's place, visits, dropped rows
        self._v6 = meta.schema_version >= 6  # rows' recency
        self._v7 = meta.schema_version >= 7  # visit keys apart from the visit log
        self._v9 = meta.schema_version >= 9  # repairs, retraction entries in the loop-closure log
        self._v10 = meta.schema_version >= 10  # warm-up joins
        self._v11 = meta.schema_version >= 11  # the loop closures' span
        self._v12 = meta.schema_version >= 12  # joined rows turned into visits
        self._cols = COLUMNS if self._v5 else COLUMNS_V4 if self._v2 else COLUMNS_V1
        self._v3 = meta.schema_version >= 3  # a version 2 file opened read-only has no loop-closure log
        self._conn: sqlite3.Connection | None = conn
        self._lock = threading.RLock()
        self._cell_dtype = meta.cell_dtype
        last, count = conn.execute("SELECT coalesce(max(seq), 0), count(*) FROM observations").fetchone()
        if self._v12:  # a joined row turned into a visit was deleted: its seq is still handed out (§11.8)
            last = max(int(last), int(conn.execute("SELECT coalesce(max(seq), 0) FROM joins").fetchone()[0]))
        self._last_seq = int(last)
        self._count = int(count)
        self._seq_floor = max(0, int(seq_floor))
        self._synced_wal: int | None = None  # the inode of the WAL file whose directory entry `sync` synced

    # ------------------------------------------------------------------ lifecycle

    @classmethod
    def create(cls, path: str | os.PathLike[str], meta: MapMeta, *, seq_floor: int = 0,
               max_keys: int | None = None, max_closures: int | None = None) -> MapStore:
        """Create a new `map.sqlite` atomically (`storage.mapschema.create_file`: a crash leaves no map
        file or a complete one) and open it.

        Args:
            path: the file to create; its directory must exist.
            meta: what is frozen into the map.
            seq_floor, max_keys, max_closures: see `open`.

        Raises:
            FileExistsError: `path` exists.
        """
        create_file(Path(path), meta)
        return cls.open(path, seq_floor=seq_floor, max_keys=max_keys, max_closures=max_closures)

    @classmethod
    def open(cls, path: str | os.PathLike[str], *, seq_floor: int = 0, readonly: bool = False,
             max_keys: int | None = None, max_closures: int | None = None) -> MapStore:
        """Open an existing `map.sqlite`.

        Args:
            path: the file.
            seq_floor: the lowest seq that counts as used (the catalog's high-water mark): the next
                append gets `max(last_seq, seq_floor) + 1`, so a restored (older) file never hands out a
                seq again.
            readonly: inspect only (`cortexloc verify`): nothing on disk changes, appends fail. An
                older file is migrated (`storage.mapschema.migrate`) unless opened read-only.
            max_keys: idempotency keys kept: those of the last `max_keys` seqs (None: all).
            max_closures: loop closures kept: the last `max_closures` (None: all).

        Raises:
            FileNotFoundError: no such file (SQLite would silently create an empty one).
            StoreCorrupt: not a map database.
            StorageError: written by a newer schema version.
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path} does not exist")
        try:
            conn = connect(path, readonly=readonly)
        except sqlite3.DatabaseError as exc:
            raise StoreCorrupt(f"{path}: {exc}") from exc
        try:
            meta = read_meta(conn, path)
            if meta.schema_version > SCHEMA_VERSION:
                raise StorageError(f"{path}: schema version {meta.schema_version} is newer than "
                                   f"this code's {SCHEMA_VERSION}")
            if not readonly:
                meta = migrate(conn, meta)
            return cls(path, conn, meta, seq_floor, max_keys, max_closures)
        except sqlite3.DatabaseError as exc:
            conn.close()
            if is_full_error(exc):  # the migration found no room: the file is whole, the disk is not
                raise StorageFull(f"{path}: no room to migrate to schema {SCHEMA_VERSION}") from exc
            raise StoreCorrupt(f"{path}: {exc}") from exc
        except BaseException:
            conn.close()
            raise

    def close(self) -> None:
        """Close the connection (idempotent). SQLite checkpoints and removes the WAL on the last close."""
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    def __enter__(self) -> MapStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        """True after `close`."""
        return self._conn is None

    def _db(self) -> sqlite3.Connection:
        if self._conn is None:
            raise StoreClosed(f"{self.path}: store is closed")
        return self._conn

    # ------------------------------------------------------------------ writes

    @property
    def seq_floor(self) -> int:
        """The high-water mark below or at which no seq is handed out."""
        return self._seq_floor

    def raise_seq_floor(self, seq: int) -> None:
        """Raise (never lower) the seq floor, e.g. after the catalog's high-water mark moved."""
        with self._lock:
            self._seq_floor = max(self._seq_floor, int(seq))

    def next_seq(self) -> int:
        """The seq the next `append` will assign."""
        with self._lock:
            return max(self._last_seq, self._seq_floor) + 1

    def append(self, row: NewObservation, *, durable: bool = True) -> int:
        """INSERT one observation and COMMIT; durable (WAL, synchronous=FULL) when this returns.

        Args:
            durable: False: COMMIT without its fsync (synchronous=NORMAL for this transaction): the row
                is visible and survives a crash of the process, and is durable once a later `sync`
                returns (group commit, docs/design/service.md §4.3): acknowledge it only then.

        Returns:
            Its seq.

        Raises:
            ValueError: arrays not sorted/distinct/in range, or a context_prev_seq that is not earlier.
            DuplicateObservation: the observation_id is already stored.
            StorageFull: the disk is full; nothing was written and the seq is not consumed.
        """
        return self.append_many([row], durable=durable)[0]

    def append_many(self, rows: Iterable[NewObservation], *, durable: bool = True) -> list[int]:
        """INSERT several observations in one transaction (all or none); `durable` as in `append`.

        Each reply of the service must still wait for this commit (docs/design/service.md §4.3).

        Returns:
            Their seqs, in order.
        """
        rows = list(rows)
        with self._lock:
            conn = self._db()
            first = max(self._last_seq, self._seq_floor) + 1
            params = []
            for i, r in enumerate(rows):
                seq = first + i
                prev = r.context_prev_seq
                if prev is not None and not 0 < int(prev) < seq:
                    raise ValueError(f"context_prev_seq {prev} must be in [1, {seq})")
                params.append((seq, str(r.observation_id), str(r.stream),
                               None if prev is None else int(prev), r.label, str(r.created_at),
                               str(r.image_sha256), encode(r.input_sdr, INPUT_DTYPE, "input_sdr"),
                               encode(r.winner_cells, self._cell_dtype, "winner_cells"),
                               None if r.metadata is None else json.dumps(r.metadata, separators=(",", ":")),
                               None if r.place is None else int(r.place)))
            if not params:
                return []
            thumbs = [(first + i, r.thumbnail) for i, r in enumerate(rows) if r.thumbnail is not None]
            keys = [(r.key.key, r.key.fingerprint, first + i, r.key.reply, str(r.created_at))
                    for i, r in enumerate(rows) if r.key is not None]
            frames = [(first + i, r.keyframe[0], None if r.keyframe[1] is None
                       else json.dumps(r.keyframe[1], separators=(",", ":")))
                      for i, r in enumerate(rows) if r.keyframe is not None]
            closures = [_closure_params(r.closure, first + i)
                        for i, r in enumerate(rows) if r.closure is not None]
            drops = [(int(d), "appearance-cap", first + i) for i, r in enumerate(rows) for d in r.drops]
            resumes = [(str(r.stream), first + i, r.resume)
                       for i, r in enumerate(rows) if r.resume is not None]
            touches = [(int(t), first + i) for i, r in enumerate(rows) for t in r.touched]
            joins = [(str(r.stream), j, first + i - 1) for i, r in enumerate(rows) for j in r.joins]
            if not durable:  # per connection, outside a transaction: this commit alone skips its fsync
                conn.execute("PRAGMA synchronous=NORMAL")
            try:
                with transaction(conn):
                    conn.executemany(f"INSERT INTO observations ({COLUMNS}) VALUES (?,?,?,?,?,?,?,?,?,?,?)",
                                     params)
                    self._drop(conn, drops)
                    gone = self._join(conn, joins)
                    self._touch(conn, touches)
                    self._resume(conn, resumes)
                    # The row's thumbnail and idempotency key commit with it, or nothing does.
                    conn.executemany("INSERT INTO thumbnails (seq, jpeg) VALUES (?, ?)", thumbs)
                    conn.executemany("INSERT INTO keyframes (seq, features, camera) VALUES (?, ?, ?)", frames)
                    conn.executemany("INSERT INTO idempotency_keys (key, fingerprint, seq, reply, created_at)"
                                     " VALUES (?, ?, ?, ?, ?)", keys)
                    if keys and self.max_keys is not None:  # the keys of the last max_keys seqs stay
                        conn.execute("DELETE FROM idempotency_keys WHERE seq <= ?",
                                     (first + len(params) - 1 - self.max_keys,))
                    self._log_closures(conn, closures)
            except sqlite3.IntegrityError as exc:
                if "observation_id" in str(exc) or "idempotency_keys.key" in str(exc):
                    raise DuplicateObservation(str(exc)) from exc
                raise
            finally:
                if not durable:
                    conn.execute("PRAGMA synchronous=FULL")
            # Only after COMMIT returned: a failed commit consumes no seq and changes no counter.
            self._last_seq = first + len(params) - 1
            self._count += len(params) - gone
            return list(range(first, first + len(params)))

    def add_visit(self, visit: NewVisit) -> int:
        """Log a consolidated frame (docs/design/science.md §11.8) with its loop closure and idempotency
        key, and COMMIT: durable when this returns, before its reply (docs/design/service.md §4.3).

        Returns:
            Its id (the visits' log order).

        Raises:
            DuplicateObservation: its idempotency key is already stored. StorageFull: nothing was written.
        """
        meta = None if visit.metadata is None else json.dumps(visit.metadata, separators=(",", ":"))
        key = visit.key
        with self._lock:
            conn = self._db()
            if key is not None and conn.execute("SELECT 1 FROM idempotency_keys WHERE key = ?",
                                                (key.key,)).fetchone():
                raise DuplicateObservation(f"idempotency key {key.key} is already stored")
            try:
                with transaction(conn):
                    cur = conn.execute(
                        "INSERT INTO visits (after_seq, stream, seq, context_prev_seq, input_sdr, "
                        "winner_cells, metadata, created_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                        (self._last_seq, str(visit.stream), int(visit.seq),
                         None if visit.context_prev_seq is None else int(visit.context_prev_seq),
                         encode(visit.input_sdr, INPUT_DTYPE, "input_sdr"),
                         encode(visit.winner_cells, self._cell_dtype, "winner_cells"), meta,
                         str(visit.created_at)))
                    visit_id = int(cur.lastrowid or 0)
                    if key is not None:  # kept apart from the log, which is pruned (§4.2)
                        conn.execute("INSERT INTO visit_keys (key, fingerprint, visit, reply, created_at) "
                                     "VALUES (?, ?, ?, ?, ?)",
                                     (key.key, key.fingerprint, visit_id, key.reply, str(visit.created_at)))
                        if self.max_keys is not None:  # the keys of the last max_keys visits stay
                            conn.execute("DELETE FROM visit_keys WHERE visit <= ?",
                                         (visit_id - self.max_keys,))
                    clock = max(self._last_seq, self._seq_floor) + 1  # the seq the live step was given
                    gone = self._join(conn, [(str(visit.stream), j, self._last_seq) for j in visit.joins])
                    self._touch(conn, [(int(t), clock) for t in visit.touched])
                    if visit.resume is not None:
                        self._resume(conn, [(str(visit.stream), clock, visit.resume)])
                    if visit.closure is not None:
                        self._log_closures(conn, [_closure_params(visit.closure, None, visit.seq)])
            except sqlite3.IntegrityError as exc:
                if "visit_keys.key" in str(exc):
                    raise DuplicateObservation(str(exc)) from exc
                raise
            self._count -= gone  # only after COMMIT returned
            return visit_id

    def visits(self, after_id: int = 0, rows_after: int = 0) -> Iterator[Visit]:
        """Logged visits with id > `after_id`, in the order they were learned (their `after_seq`, then log
        order: a joined row's visit, logged at its join, takes its row's place, §11.8), read in pages
        (replay). `rows_after`: a joined row's visit only if its row is after it (a snapshot at that seq
        learned the rows up to it)."""
        if not self._v5:
            return
        row = "row_seq" if self._v12 else "NULL"
        last = (-1, 0)
        while True:
            with self._lock:
                found = self._db().execute(
                    "SELECT id, after_seq, stream, seq, context_prev_seq, input_sdr, winner_cells, "
                    f"created_at, metadata, {row} FROM visits WHERE id > ? AND (after_seq, id) > (?, ?) "
                    f"AND coalesce({row}, ?) > ? ORDER BY after_seq, id LIMIT ?",
                    (int(after_id), *last, int(rows_after) + 1, int(rows_after), _PAGE)).fetchall()
            if not found:
                return
            for r in found:
                yield Visit(id=int(r[0]), after_seq=int(r[1]), stream=r[2], seq=int(r[3]),
                            context_prev_seq=None if r[4] is None else int(r[4]),
                            input_sdr=decode(r[5], INPUT_DTYPE), winner_cells=decode(r[6], self._cell_dtype),
                            created_at=r[7], metadata=_json(r[8]), row=None if r[9] is None else int(r[9]))
            last = (int(found[-1][1]), int(found[-1][0]))

    def visit_stats(self) -> tuple[int, int, int]:
        """(visits logged, the first id kept (0: none), the last id ever logged (0: none))."""
        if not self._v5:
            return 0, 0, 0
        with self._lock:
            n, lo, hi = self._db().execute("SELECT count(*), coalesce(min(id), 0), coalesce(max(id), 0) "
                                           "FROM visits").fetchone()
        return int(n), int(lo), int(hi)

    def visit_mark(self, visit_id: int) -> str | None:
        """What tells visit `visit_id` from another that got its id on another branch (a restore rolls
        the log back and ids are handed out again): its stream and created_at; None: no such visit."""
        if not self._v5:
            return None
        with self._lock:
            r = self._db().execute("SELECT stream, created_at FROM visits WHERE id = ?",
                                   (int(visit_id),)).fetchone()
        return None if r is None else f"{r[0]}|{r[1]}"

    def _touch(self, conn: sqlite3.Connection, touches: list[tuple[int, int]]) -> None:
        """Within the caller's transaction: rows used at a clock (`recency`, kept at the latest)."""
        if touches and self._v6:
            conn.executemany("INSERT INTO recency (seq, used) VALUES (?, ?) ON CONFLICT (seq) DO UPDATE "
                             "SET used = max(used, excluded.used)", touches)

    def _resume(self, conn: sqlite3.Connection, states: list[tuple[str, int, bytes]]) -> None:
        """Within the caller's transaction: streams' states after their learned steps (`stream_states`)."""
        if states and self._v7:
            conn.executemany("INSERT INTO stream_states (stream, clock, state) VALUES (?, ?, ?) ON CONFLICT "
                             "(stream) DO UPDATE SET clock = excluded.clock, state = excluded.state", states)

    def stream_states(self) -> dict[str, bytes]:
        """Stream -> its state after its last learned step, as written with that step
        (`NewObservation.resume`); those a snapshot holds may have been pruned (`prune_stream_states`)."""
        if not self._v7:
            return {}
        with self._lock:
            return {r[0]: bytes(r[1]) for r in self._db().execute("SELECT stream, state FROM stream_states")}

    def prune_stream_states(self, through: int) -> int:
        """Delete the stream states written at a clock <= `through` (a snapshot at that seq holds them:
        the replay after it meets none of their steps). Returns how many."""
        if not self._v7:
            return 0
        with self._lock:
            conn = self._db()
            with transaction(conn):
                cur = conn.execute("DELETE FROM stream_states WHERE clock <= ?", (int(through),))
            return int(cur.rowcount)

    def recency(self) -> dict[int, int]:
        """Row -> the clock of its last use by a later step (a row's own making is its seq; not here),
        docs/design/science.md §11.9. Empty for a file before version 6."""
        if not self._v6:
            return {}
        with self._lock:
            return {int(r[0]): int(r[1]) for r in self._db().execute("SELECT seq, used FROM recency")}

    def visits_pruned_through(self) -> int:
        """The last visit id pruned from the log (0: none ever was): a replay that starts before it
        cannot reproduce the memory (docs/design/service.md §4.4).

        Durable as the log itself: ids start at 1 and are never reused (SQLite hands out max(id) + 1,
        and `prune_visits` always keeps the newest), so the oldest id kept minus one is how far the log
        was pruned."""
        _, first, _ = self.visit_stats()
        return max(first - 1, 0)

    def prune_visits(self, covered: int, keep: int) -> int:
        """Delete the oldest visits beyond the last `keep` (at least 1: `visits_pruned_through` reads
        the oldest kept), but only those with id <= `covered` (a snapshot holds the memory they taught;
        the replay after it never needs them). Returns how many."""
        if not self._v5:
            return 0
        keep = max(int(keep), 1)
        with self._lock:
            conn = self._db()
            with transaction(conn):
                cur = conn.execute("DELETE FROM visits WHERE id <= ? AND "
                                   "id <= (SELECT max(id) FROM visits) - ?", (int(covered), int(keep)))
            return int(cur.rowcount)

    def drop(self, seqs: Iterable[int], reason: str) -> None:
        """Record rows as no longer held (a forgotten place, docs/design/science.md §11.9) and COMMIT."""
        with self._lock:
            conn = self._db()
            with transaction(conn):
                self._drop(conn, [(int(s), reason, self._last_seq) for s in seqs])

    def _drop(self, conn: sqlite3.Connection, drops: list[tuple[int, str, int]]) -> None:
        if drops:
            conn.executemany("INSERT OR IGNORE INTO dropped (seq, reason, after_seq, created_at) "
                             "VALUES (?, ?, ?, ?)", [(*d, utc_now()) for d in drops])

    def _join(self, conn: sqlite3.Connection, joins: list[tuple[str, tuple[int, int], int]]) -> int:
        """Warm-up joins (stream, (row, old row), after_seq), each row dropped (`joined`) with it; from
        schema 12 each row that no loop closure or repair names is turned into a visit of the old row
        (`visits.row_seq`, after the row before it) and deleted, so a join leaves no row behind (§11.8).
        Returns how many rows were deleted."""
        if not joins:
            return 0
        now = utc_now()
        oid = "(SELECT observation_id FROM observations WHERE seq = ?)" if self._v12 else "NULL"
        conn.executemany(f"INSERT INTO joins (seq, place_seq, stream, after_seq, created_at"
                         f"{', observation_id' if self._v12 else ''}) "
                         f"VALUES (?, ?, ?, ?, ?{', ' + oid if self._v12 else ''})",
                         [(int(row), int(old), stream, after, now, *((int(row),) if self._v12 else ()))
                          for stream, (row, old), after in joins])
        self._drop(conn, [(int(row), "joined", after) for _, (row, _old), after in joins])
        if not self._v12:
            return 0
        gone = 0
        for _, (row, old), _after in joins:
            cur = conn.execute(
                "INSERT INTO visits (after_seq, stream, seq, context_prev_seq, input_sdr, winner_cells, "
                "metadata, created_at, row_seq) SELECT o.seq - 1, o.stream, ?, o.context_prev_seq, "
                "o.input_sdr, o.winner_cells, o.metadata, o.created_at, o.seq FROM observations o "
                "WHERE o.seq = ? AND NOT EXISTS (SELECT 1 FROM loop_closures c WHERE c.seq = o.seq "
                "OR c.place_seq = o.seq) AND NOT EXISTS (SELECT 1 FROM repairs r WHERE r.seq = o.seq)",
                (int(old), int(row)))
            if cur.rowcount:
                for table in ("thumbnails", "keyframes", "recency", "observations"):
                    conn.execute(f"DELETE FROM {table} WHERE seq = ?", (int(row),))
                gone += 1
        return gone

    def observation_id(self, seq: int) -> str | None:
        """The observation id of row `seq`, held or joined away (a warm-up join turned it into a visit,
        schema 12); None: no such row in this file."""
        with self._lock:
            db = self._db()
            r = db.execute("SELECT observation_id FROM observations WHERE seq = ?", (int(seq),)).fetchone()
            if r is None and self._v12:
                r = db.execute("SELECT observation_id FROM joins WHERE seq = ?", (int(seq),)).fetchone()
        return None if r is None else r[0]

    def code(self, seq: int) -> np.ndarray | None:
        """Row `seq`'s frame code (`input_sdr`), held or joined away (its visit's, schema 12); None: none."""
        with self._lock:
            db = self._db()
            r = db.execute("SELECT input_sdr FROM observations WHERE seq = ?", (int(seq),)).fetchone()
            if r is None and self._v12:
                r = db.execute("SELECT input_sdr FROM visits WHERE row_seq = ?", (int(seq),)).fetchone()
        return None if r is None else decode(r[0], INPUT_DTYPE)

    def joined_to(self, seq: int) -> int | None:
        """The old row whose place row `seq` joined (a warm-up join), or None."""
        if not self._v10:
            return None
        with self._lock:
            r = self._db().execute("SELECT place_seq FROM joins WHERE seq = ?", (int(seq),)).fetchone()
        return None if r is None else int(r[0])

    def joins(self) -> list[tuple[int, int]]:
        """The warm-up joins (row, old row whose place it joined) in log order (docs/design/science.md
        §11.8); the rows are `dropped` (reason `joined`)."""
        if not self._v10:
            return []
        with self._lock:
            return [(int(r[0]), int(r[1])) for r in self._db().execute(
                "SELECT seq, place_seq FROM joins ORDER BY after_seq, seq")]

    def join_problems(self, reach: int) -> list[str]:
        """What is wrong with the warm-up joins (`cortexloc verify`, docs/design/science.md §11.8): a join
        whose row is not dropped as `joined`, or that reached back over `reach` or more of its stream's rows
        held then; a row dropped as `joined` with no join."""
        if not self._v10:
            return []
        with self._lock:
            db = self._db()
            out = [f"join of row {r[0]}: the row is not dropped as joined" for r in db.execute(
                "SELECT j.seq FROM joins j LEFT JOIN dropped d ON d.seq = j.seq "
                "WHERE d.reason IS NOT 'joined'")]
            out += [f"row {r[0]} is dropped as joined without a join" for r in db.execute(
                "SELECT d.seq FROM dropped d LEFT JOIN joins j ON j.seq = d.seq "
                "WHERE d.reason = 'joined' AND j.seq IS NULL")]
            # The rows the live rule looked through: the stream's rows made after the joined one and
            # still held when the join was made (a row dropped at an earlier step, joined or over its
            # place's cap, had left the memory; a row a repair re-made is no step of it).
            split = "SELECT seq FROM repairs WHERE kind = 'split'" if self._v9 else "SELECT NULL WHERE 0"
            rows = ("(SELECT seq, stream FROM observations UNION ALL SELECT row_seq, stream FROM visits "
                    "WHERE row_seq IS NOT NULL)") if self._v12 else "observations"
            out += [f"join of row {r[0]}: {r[1]} held rows of its stream since, the reach is {reach}"
                    for r in db.execute(
                        f"SELECT j.seq, (SELECT count(*) FROM {rows} o WHERE o.stream = j.stream "
                        "AND o.seq > j.seq AND o.seq <= j.after_seq AND NOT EXISTS (SELECT 1 FROM dropped d "
                        "WHERE d.seq = o.seq AND d.after_seq < j.after_seq) "
                        f"AND o.seq NOT IN ({split})) AS n FROM joins j WHERE n >= ?", (int(reach),))]
            return out

    def dropped(self) -> dict[int, str]:
        """The rows no longer held and why (`appearance-cap` | `forgotten` | `joined`)."""
        if not self._v5:
            return {}
        with self._lock:
            return {int(r[0]): r[1] for r in self._db().execute("SELECT seq, reason FROM dropped")}

    def joined(self) -> dict[int, int]:
        """Learned row -> the row its loop closure named, from the log (the place of a row stored before
        version 5, docs/design/science.md §11.8)."""
        if not self._v3:
            return {}
        retraction = " AND retracts IS NULL" if self._v9 else ""  # a retraction joins nothing
        with self._lock:
            return {int(r[0]): int(r[1]) for r in self._db().execute(
                f"SELECT seq, place_seq FROM loop_closures WHERE seq IS NOT NULL{retraction}")}

    # ------------------------------------------------------------------ repairs (schema 9)

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
            if not self._v9:
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
                conn.executemany(
                    "INSERT INTO loop_closures (stream, seq, place_seq, confidence, support, metadata, "
                    "created_at, consolidated_into, retracts) SELECT stream, seq, place_seq, 0, 0, metadata, "
                    "?, consolidated_into, id FROM loop_closures c WHERE id = ? AND retracts IS NULL AND "
                    "NOT EXISTS (SELECT 1 FROM loop_closures r WHERE r.retracts = c.id)",
                    [(now, int(c)) for c in retracts])
                if retracts:
                    self._prune_closures(conn)
            if rows:  # only after COMMIT returned, as `append_many`
                self._last_seq = first + len(rows) - 1
                self._count += len(rows)
            return [first + i for i in range(len(rows))]

    def repairs(self) -> list[Repair]:
        """The logged repairs, in log order (empty before schema version 9)."""
        if not self._v9:
            return []
        with self._lock:
            found = self._db().execute(
                "SELECT id, kind, seq, visit, was, created_at FROM repairs ORDER BY id").fetchall()
        return [Repair(id=int(r[0]), kind=r[1], seq=int(r[2]), visit=None if r[3] is None else int(r[3]),
                       was=int(r[4]), created_at=r[5]) for r in found]

    def retracted(self) -> set[int]:
        """The ids of the closures a retraction entry withdraws (kept while the retraction is logged)."""
        if not self._v9:
            return set()
        with self._lock:
            return {int(r[0]) for r in self._db().execute(
                "SELECT retracts FROM loop_closures WHERE retracts IS NOT NULL")}

    def sync(self) -> None:
        """Make every commit so far durable, those made with `durable=False` included: one fsync of the
        WAL (and of the directory the first time a WAL file is seen, so its entry is on disk too) for
        all of them, the group commit of docs/design/service.md §4.3.

        Runs without the store's lock, so the writer goes on committing meanwhile; what it commits
        after this call began is covered by the next one. A closed store, or one without a WAL file,
        has nothing to sync: SQLite checkpoints the WAL into the database file and syncs it on close.
        """
        if self._conn is None:
            return
        wal = Path(f"{self.path}-wal")
        try:
            fd = os.open(wal, os.O_RDONLY)
        except FileNotFoundError:
            return
        try:
            os.fsync(fd)
            inode = os.fstat(fd).st_ino
        finally:
            os.close(fd)
        if inode != self._synced_wal:
            fsync_dir(wal.parent)
            self._synced_wal = inode

    def add_closure(self, closure: NewClosure) -> bool:
        """Log a localising stream's loop closure alone (it stores no observation) and COMMIT.

        Returns:
            False when its idempotency key is already logged (nothing written).

        Raises:
            StorageFull: the disk is full; nothing was written.
        """
        with self._lock:
            conn = self._db()
            with transaction(conn):
                return self._log_closures(conn, [_closure_params(closure, None)]) > 0

    def _log_closures(self, conn: sqlite3.Connection, params: list[tuple[Any, ...]]) -> int:
        """In a transaction: insert (a repeated key inserts nothing), then keep the last `max_closures`."""
        if not params:
            return 0
        before = conn.total_changes
        conn.executemany("INSERT OR IGNORE INTO loop_closures (stream, seq, place_seq, confidence, support, "
                         "metadata, idempotency_key, created_at, verification, consolidated_into, span, "
                         "span_seqs) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", params)
        added = conn.total_changes - before
        if added:
            self._prune_closures(conn)
        return added

    def _prune_closures(self, conn: sqlite3.Connection) -> None:
        """In a transaction: keep the last `max_closures` entries of the loop-closure log."""
        if self.max_closures is not None:
            conn.execute("DELETE FROM loop_closures WHERE id <= (SELECT max(id) FROM loop_closures) - ?",
                         (self.max_closures,))

    def closures(self, after: int, limit: int) -> list[LoopClosure]:
        """At most `limit` logged loop closures with id > `after`, oldest first, with both rows."""
        if not self._v3:
            return []
        with self._lock:
            found = self._db().execute(
                "SELECT c.id, c.stream, c.seq, o.observation_id, c.metadata, c.place_seq, p.observation_id, "
                "p.stream, p.label, p.metadata, c.confidence, c.support, c.created_at, "
                f"{'c.verification' if self.meta.schema_version >= 4 else 'NULL'}, "
                f"{'c.consolidated_into' if self.meta.schema_version >= 8 else 'NULL'}, "
                f"{'c.retracts' if self._v9 else 'NULL'}, "
                f"{'c.span, c.span_seqs' if self._v11 else 'NULL, NULL'} "
                "FROM loop_closures c JOIN observations p ON p.seq = c.place_seq "
                "LEFT JOIN observations o ON o.seq = c.seq WHERE c.id > ? ORDER BY c.id LIMIT ?",
                (int(after), int(limit))).fetchall()
        return [LoopClosure(id=int(r[0]), stream=r[1], seq=None if r[2] is None else int(r[2]),
                            observation_id=r[3], metadata=_json(r[4]), place_seq=int(r[5]),
                            place_observation_id=r[6], place_stream=r[7], place_label=r[8],
                            place_metadata=_json(r[9]), confidence=float(r[10]), support=int(r[11]),
                            created_at=r[12], verification=_json(r[13]),
                            consolidated_into=None if r[14] is None else int(r[14]),
                            retracts=None if r[15] is None else int(r[15]),
                            span=None if r[16] is None else int(r[16]),
                            span_seqs=None if r[17] is None else tuple(json.loads(r[17]))) for r in found]

    def closure_count(self) -> int:
        """Loop closures in the log."""
        if not self._v3:
            return 0
        with self._lock:
            return int(self._db().execute("SELECT count(*) FROM loop_closures").fetchone()[0])

    # ------------------------------------------------------------------ reads

    def count(self) -> int:
        """Number of stored observations."""
        with self._lock:
            return self._count

    def count_after(self, seq: int) -> int:
        """Number of stored observations with a seq above `seq` (a recovery's tail after a snapshot)."""
        with self._lock:
            return int(self._db().execute("SELECT count(*) FROM observations WHERE seq > ?",
                                          (int(seq),)).fetchone()[0])

    def last_seq(self) -> int:
        """Highest seq stored (a row held, or one a join turned into a visit, §11.8; 0 when empty); the seq
        floor is not counted."""
        with self._lock:
            return self._last_seq

    def get(self, seq: int) -> Observation | None:
        """The observation with this seq, or None."""
        with self._lock:
            r = self._db().execute(f"SELECT {self._cols} FROM observations WHERE seq = ?",
                                   (int(seq),)).fetchone()
        return None if r is None else self._row(r)

    def get_many(self, seqs: Iterable[int]) -> dict[int, Observation]:
        """Observations by seq (missing seqs are absent from the result); for the top-k of a ranking."""
        wanted = sorted({int(s) for s in seqs})
        out: dict[int, Observation] = {}
        # SQLite limits bound parameters per statement; 500 is far below every build's limit.
        for i in range(0, len(wanted), 500):
            chunk = wanted[i:i + 500]
            marks = ",".join("?" * len(chunk))
            with self._lock:
                found = self._db().execute(
                    f"SELECT {self._cols} FROM observations WHERE seq IN ({marks})", chunk).fetchall()
            out.update((int(r[0]), self._row(r)) for r in found)
        return out

    def rows(self, after_seq: int = 0) -> Iterator[Observation]:
        """Observations with seq > `after_seq`, in seq order (replay, index rebuild).

        Read in pages by seq, so appends between pages are fine and no read transaction is held while
        the caller works on a row.
        """
        last = int(after_seq)
        while page := self.page(last, _PAGE):
            yield from page
            last = page[-1].seq

    def page(self, after_seq: int, limit: int) -> list[Observation]:
        """At most `limit` observations with seq > `after_seq`, in seq order."""
        with self._lock:
            found = self._db().execute(
                f"SELECT {self._cols} FROM observations WHERE seq > ? ORDER BY seq LIMIT ?",
                (int(after_seq), int(limit))).fetchall()
        return [self._row(r) for r in found]

    def _row(self, r: tuple[Any, ...]) -> Observation:
        return Observation(seq=int(r[0]), observation_id=r[1], stream=r[2],
                           context_prev_seq=None if r[3] is None else int(r[3]), label=r[4],
                           created_at=r[5], image_sha256=r[6], input_sdr=decode(r[7], INPUT_DTYPE),
                           winner_cells=decode(r[8], self._cell_dtype),
                           metadata=None if r[9] is None else json.loads(r[9]),
                           place=None if r[10] is None else int(r[10]))

    def thumbnail(self, seq: int) -> bytes | None:
        """The JPEG thumbnail stored with this seq, or None."""
        if not self._v2:
            return None
        with self._lock:
            r = self._db().execute("SELECT jpeg FROM thumbnails WHERE seq = ?", (int(seq),)).fetchone()
        return None if r is None else bytes(r[0])

    def with_thumbnails(self, seqs: Iterable[int]) -> set[int]:
        """Those of `seqs` (at most 500) that have a thumbnail."""
        wanted = sorted({int(s) for s in seqs})
        if not self._v2 or not wanted:
            return set()
        with self._lock:
            marks = ",".join("?" * len(wanted))
            found = self._db().execute(f"SELECT seq FROM thumbnails WHERE seq IN ({marks})",
                                       wanted).fetchall()
        return {int(r[0]) for r in found}

    def keyframes(self, seqs: Iterable[int]) -> dict[int, tuple[bytes, dict[str, Any] | None]]:
        """The keyframes (packed features, camera or None) stored with those of `seqs` (at most 500)
        that have one (docs/design/science.md §12.1)."""
        wanted = sorted({int(s) for s in seqs})
        if self.meta.schema_version < 4 or not wanted:
            return {}
        with self._lock:
            marks = ",".join("?" * len(wanted))
            found = self._db().execute(f"SELECT seq, features, camera FROM keyframes WHERE seq IN ({marks})",
                                       wanted).fetchall()
        return {int(r[0]): (bytes(r[1]), None if r[2] is None else json.loads(r[2])) for r in found}

    def keyframe_bytes(self) -> tuple[int, int]:
        """(keyframes stored, bytes of their features and cameras): what the option costs on disk."""
        if self.meta.schema_version < 4:
            return 0, 0
        with self._lock:
            n, b = self._db().execute("SELECT count(*), coalesce(sum(length(features) + "
                                      "coalesce(length(camera), 0)), 0) FROM keyframes").fetchone()
        return int(n), int(b)

    def key_record(self, key: str) -> KeyRecord | None:
        """The idempotent post stored under `key`, or None (never stored, or pruned)."""
        if not self._v2:
            return None
        with self._lock:
            r = self._db().execute("SELECT key, fingerprint, reply FROM idempotency_keys WHERE key = ?",
                                   (key,)).fetchone()
            if r is None and self._v7:  # a consolidated frame's post (docs/design/science.md §11.8)
                r = self._db().execute("SELECT key, fingerprint, reply FROM visit_keys WHERE key = ?",
                                       (key,)).fetchone()
            elif r is None and self._v5:  # a version 5-6 file opened read-only: its visit log holds them
                r = self._db().execute("SELECT idempotency_key, fingerprint, reply FROM visits "
                                       "WHERE idempotency_key = ?", (key,)).fetchone()
        return None if r is None else KeyRecord(*r)

    # ------------------------------------------------------------------ checks and sizes

    def quick_check(self) -> bool:
        """`PRAGMA quick_check` is `ok` (recovery's first step; failure = map `failed`, database-corrupt)."""
        return self._check("quick_check")

    def integrity_check(self) -> bool:
        """`PRAGMA integrity_check` is `ok` (slower than quick_check: also verifies index contents)."""
        return self._check("integrity_check")

    def _check(self, pragma: str) -> bool:
        try:
            with self._lock:
                result = self._db().execute(f"PRAGMA {pragma}").fetchall()
        except sqlite3.DatabaseError:
            return False
        return result == [("ok",)]

    def durability(self) -> dict[str, Any]:
        """The connection's `journal_mode` and `synchronous` (2 = FULL) as SQLite reports them."""
        with self._lock:
            conn = self._db()
            return {"journal_mode": conn.execute("PRAGMA journal_mode").fetchone()[0],
                    "synchronous": int(conn.execute("PRAGMA synchronous").fetchone()[0])}

    def db_bytes(self) -> int:
        """Size of `map.sqlite` on disk."""
        return _size(self.path)

    def wal_bytes(self) -> int:
        """Size of `map.sqlite-wal` (0 when absent)."""
        return _size(Path(f"{self.path}-wal"))

    # ------------------------------------------------------------------ copies

    def backup_to(self, dest: str | os.PathLike[str]) -> int:
        """Consistent copy of the database with SQLite's online backup API (docs/design/service.md §4.4).

        The copy is switched to `journal_mode=DELETE` so it is one self-contained file: a snapshot's
        checksum then covers everything, and it can be opened read-only without -wal/-shm files.
        `MapStore.open` turns WAL back on when the copy is installed.

        Args:
            dest: the new file (must not exist).

        Returns:
            Size of the copy in bytes.
        """
        dest = Path(dest)
        if dest.exists():
            raise FileExistsError(f"{dest} exists")
        out = sqlite3.connect(str(dest), isolation_level=None)
        try:
            with self._lock:
                self._db().backup(out)
            out.execute("PRAGMA journal_mode=DELETE")
        except BaseException as exc:
            out.close()
            with contextlib.suppress(OSError):
                dest.unlink()
            if is_full_error(exc):
                raise StorageFull(str(exc)) from exc
            raise
        out.close()
        with dest.open("rb+") as f:
            os.fsync(f.fileno())
        return _size(dest)

    @staticmethod
    def install_copy(src: str | os.PathLike[str], dest: str | os.PathLike[str]) -> None:
        """Make `dest` an exact copy of the database file `src` (restore, import), atomically.

        The store on `dest` must be closed. `src` is copied to a temporary file beside `dest` and
        fsynced; then any `dest-wal`/`dest-shm` is removed *before* the rename, because SQLite would
        otherwise apply the old file's WAL frames to the new file; then the rename and a directory fsync.
        A crash before the rename leaves the old file (only its uncheckpointed tail is lost, and that is
        exactly what a restore discards); after it, the new file.
        """
        src, dest = Path(src), Path(dest)

        def copy(out: BinaryIO) -> None:
            with src.open("rb") as inp:
                shutil.copyfileobj(inp, out, 1 << 20)

        def drop_stale_wal() -> None:
            for stale in (Path(f"{dest}-wal"), Path(f"{dest}-shm")):
                with contextlib.suppress(FileNotFoundError):
                    stale.unlink()

        atomic_write(dest, copy, before_replace=drop_stale_wal)


def _json(text: str | None) -> Any:
    return None if text is None else json.loads(text)


def _closure_params(c: NewClosure, seq: int | None, consolidated_into: int | None = None) -> tuple[Any, ...]:
    meta = None if c.metadata is None else json.dumps(c.metadata, separators=(",", ":"))
    verification = None if c.verification is None else json.dumps(c.verification, separators=(",", ":"))
    span_seqs = None if c.span_seqs is None else json.dumps([int(s) for s in c.span_seqs])
    return (str(c.stream), seq, int(c.place_seq), float(c.confidence), int(c.support), meta, c.key,
            str(c.created_at), verification, consolidated_into, None if c.span is None else int(c.span),
            span_seqs)


def _size(p: Path) -> int:
    try:
        return p.stat().st_size
    except FileNotFoundError:
        return 0


