"""`catalog.sqlite`: the list of maps, their states, the snapshot registry and seq high-water marks.

The catalog is small and written rarely (map creation, state changes, snapshots, restores), so one file
for the whole data directory is enough; each map's observations live in its own `map.sqlite`.

The high-water marks are what keep seqs and loop-closure ids unique across restores (docs/design/service.md
§1: "never reused, not even after a restore"; §1.2): before a restore replaces `map.sqlite` with an older
copy, the service raises the marks to the current last seq and log id and counts the restore
(`mark_restore`), and opens the restored file with `MapStore.open(seq_floor=, closure_floor=)`. Marking
only at restore (not per observation) keeps the per-observation commit to one file. The count is the log's
epoch: a client following the log or the rows with a cursor learns from it that they were rolled back.
So is the count of rewrites (`mark_rewrite`): repairs run after the log's cap had pruned entries logged
since the last repair (`mark_repaired`), which may withdraw closures whose retractions cannot be logged.

Plain CRUD goes through `sqlite_utils` tables over our own connection (`storage._common.connect`: WAL,
synchronous=FULL, explicit `BEGIN IMMEDIATE` transactions, inside which sqlite-utils writes as
savepoints); the schema stays SQL, since sqlite-utils' table creation has no CHECK constraints.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

import sqlite_utils
from sqlite_utils.db import NotFoundError

from storage._common import (
    StorageError,
    StorageFull,
    StoreClosed,
    connect,
    is_full_error,
    transaction,
    utc_now,
)
from storage.layout import Layout

__all__ = [
    "MAP_ID_RE",
    "MAP_STATES",
    "SNAPSHOT_ID_RE",
    "SNAPSHOT_KINDS",
    "Catalog",
    "Lineage",
    "MapExists",
    "MapNotFound",
    "MapRecord",
    "SnapshotRecord",
    "StorageError",
    "StoreClosed",
    "utc_now",
]

#: A map id (the API's rule; also a directory name under `maps/`, so never `.`, `..` or a path).
MAP_ID_RE = re.compile(r"^[a-z0-9][a-z0-9._-]{0,63}$")
#: A snapshot id: also the API's `{snapshot_id}` pattern, and a directory name (so never `.`, `..`, `-x`).
SNAPSHOT_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,79}$")

MapState = Literal["ready", "recovering", "failed"]
SnapshotKind = Literal["manual", "auto", "pre-restore"]
MAP_STATES: tuple[str, ...] = get_args(MapState)
SNAPSHOT_KINDS: tuple[str, ...] = get_args(SnapshotKind)

_SCHEMA_VERSION = 3
# Statements separated by ";" (no ";" inside comments): run one by one inside one transaction, since
# executescript would commit on its own.
_SCHEMA = f"""
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
INSERT OR IGNORE INTO meta (key, value) VALUES ('schema_version', '{_SCHEMA_VERSION}');
CREATE TABLE IF NOT EXISTS maps (
    map_id          TEXT PRIMARY KEY,
    created_at      TEXT NOT NULL,
    state           TEXT NOT NULL CHECK (state IN ('ready', 'recovering', 'failed')),
    state_reason    TEXT NULL,
    preset          TEXT NULL,
    params          TEXT NOT NULL,                        -- JSON
    seq_high_water  INTEGER NOT NULL DEFAULT 0 CHECK (seq_high_water >= 0),
    closure_high_water INTEGER NOT NULL DEFAULT 0 CHECK (closure_high_water >= 0),
    restores        INTEGER NOT NULL DEFAULT 0 CHECK (restores >= 0),
    rewrites        INTEGER NOT NULL DEFAULT 0 CHECK (rewrites >= 0),
    repaired_below  INTEGER NOT NULL DEFAULT 0 CHECK (repaired_below >= 0)
);
CREATE TABLE IF NOT EXISTS snapshots (
    -- Registration order = "newest first", explicit so that VACUUM cannot renumber it.
    ord             INTEGER PRIMARY KEY AUTOINCREMENT,
    snapshot_id     TEXT NOT NULL,
    map_id          TEXT NOT NULL REFERENCES maps (map_id) ON DELETE CASCADE,
    seq             INTEGER NOT NULL CHECK (seq >= 0),
    kind            TEXT NOT NULL CHECK (kind IN ('manual', 'auto', 'pre-restore')),
    created_at      TEXT NOT NULL,
    bytes           INTEGER NOT NULL CHECK (bytes >= 0),
    manifest_sha256 TEXT NOT NULL,
    path            TEXT NOT NULL,
    UNIQUE (map_id, snapshot_id)
);
"""
# What version 2 added to a version 1 catalog: the loop-closure id mark and the restore count.
_V2 = ("ALTER TABLE maps ADD COLUMN closure_high_water INTEGER NOT NULL DEFAULT 0 "
       "CHECK (closure_high_water >= 0)",
       "ALTER TABLE maps ADD COLUMN restores INTEGER NOT NULL DEFAULT 0 CHECK (restores >= 0)",
       "UPDATE meta SET value = '2' WHERE key = 'schema_version'")
# What version 3 added: the count of rewrites and the log ids the last repair judged.
_V3 = ("ALTER TABLE maps ADD COLUMN rewrites INTEGER NOT NULL DEFAULT 0 CHECK (rewrites >= 0)",
       "ALTER TABLE maps ADD COLUMN repaired_below INTEGER NOT NULL DEFAULT 0 CHECK (repaired_below >= 0)",
       "UPDATE meta SET value = '3' WHERE key = 'schema_version'")


class MapExists(StorageError):  # noqa: N818 - named after the problem slug `map-exists`
    """`create_map` with an id that is already in the catalog."""


class MapNotFound(StorageError):  # noqa: N818 - named after the problem slug `map-not-found`
    """An operation on a map id that is not in the catalog."""


@dataclass(frozen=True)
class Lineage:
    """What makes a map the same map on another server (a move between shards; docs/design/service.md
    §1.2): the parts of its epoch and the marks of the ids it handed out. A snapshot's manifest carries it.

    Attributes:
        created_at: ISO 8601 UTC, the map's creation.
        restores, rewrites, repaired_below: as `MapRecord`'s.
        seq_high_water, closure_high_water: the highest seq and loop-closure log id handed out by then.
    """

    created_at: str
    restores: int = 0
    rewrites: int = 0
    repaired_below: int = 0
    seq_high_water: int = 0
    closure_high_water: int = 0


@dataclass(frozen=True)
class MapRecord:
    """A row of `maps`.

    Attributes:
        map_id: identifier.
        created_at: ISO 8601 UTC.
        state: `ready`, `recovering` or `failed`.
        state_reason: why the map is not ready (e.g. `database-corrupt`, `projection-invalid`), else None.
        preset: the preset the parameters were resolved from.
        params: resolved parameters (decoded JSON).
        seq_high_water: highest seq ever handed out that a restore may have removed from `map.sqlite`.
        closure_high_water: the same for loop-closure log ids.
        restores: how many restores rolled the map back: the loop-closure log's and the rows' epoch.
        rewrites: how many repairs ran past entries the log's cap had pruned: the epoch too.
        repaired_below: the log ids below this one were judged by a repair (0: none since the map was made
            or last restored).
    """

    map_id: str
    created_at: str
    state: str
    state_reason: str | None
    preset: str | None
    params: dict[str, Any]
    seq_high_water: int
    closure_high_water: int = 0
    restores: int = 0
    rewrites: int = 0
    repaired_below: int = 0

    @property
    def epoch(self) -> str:
        """The map's loop-closure log's and rows' epoch (docs/design/service.md §1.2): which map (a map
        deleted and made again, or imported, is another), how many restores, and how many rewrites
        (shown once there is one, so the epochs of maps without are as before)."""
        return f"{self.created_at}/{self.restores}" + (f"/{self.rewrites}" if self.rewrites else "")

    def lineage(self, seq: int = 0, closure_id: int = 0) -> Lineage:
        """The record's `Lineage`, its marks raised to the ids `seq` and `closure_id` the map's file has
        handed out."""
        return Lineage(self.created_at, self.restores, self.rewrites, self.repaired_below,
                       max(self.seq_high_water, int(seq)), max(self.closure_high_water, int(closure_id)))


@dataclass(frozen=True)
class SnapshotRecord:
    """A row of the snapshot registry (the docs/design/service.md §1.5 resource, plus where it lies).

    Attributes:
        snapshot_id: identifier, unique within the map.
        map_id: the map.
        seq: the last seq the snapshot contains (0 = empty map).
        kind: `manual`, `auto` or `pre-restore`.
        created_at: ISO 8601 UTC.
        bytes: total size of the snapshot's files.
        manifest_sha256: SHA-256 of its manifest.json.
        path: its directory; as read from the catalog, relative to the data directory (the catalog's
            folder, see `Catalog.snapshot_dir`), so a moved or copied data directory keeps its snapshots.
    """

    snapshot_id: str
    map_id: str
    seq: int
    kind: str
    created_at: str
    bytes: int
    manifest_sha256: str
    path: str


def _map(r: dict[str, Any]) -> MapRecord:
    return MapRecord(map_id=r["map_id"], created_at=r["created_at"], state=r["state"],
                     state_reason=r["state_reason"], preset=r["preset"], params=json.loads(r["params"]),
                     seq_high_water=int(r["seq_high_water"]),
                     # (a version 1 catalog opened read-only has neither column)
                     closure_high_water=int(r.get("closure_high_water") or 0),
                     restores=int(r.get("restores") or 0), rewrites=int(r.get("rewrites") or 0),
                     repaired_below=int(r.get("repaired_below") or 0))


def _snap(r: dict[str, Any]) -> SnapshotRecord:
    path = r["path"]
    if os.path.isabs(path):
        # Written by a version that stored absolute paths: the directory may have been moved or copied
        # since, and reading the path as written would use another data directory's files. A snapshot
        # always lies at its place in *this* data directory.
        path = Layout.snapshot_relpath(r["map_id"], r["snapshot_id"])
    return SnapshotRecord(snapshot_id=r["snapshot_id"], map_id=r["map_id"], seq=int(r["seq"]),
                          kind=r["kind"], created_at=r["created_at"], bytes=int(r["bytes"]),
                          manifest_sha256=r["manifest_sha256"], path=path)


_ONE_SNAPSHOT = "map_id = ? AND snapshot_id = ?"


def _tables(conn: sqlite3.Connection) -> sqlite_utils.Database:
    # Over our connection as configured: no PRAGMA of its own (recursive_triggers), no plugins.
    return sqlite_utils.Database(conn, recursive_triggers=False, execute_plugins=False)


def _get_map(db: sqlite_utils.Database, map_id: str) -> dict[str, Any]:
    try:
        return db["maps"].get(map_id)
    except NotFoundError:
        raise MapNotFound(f"map {map_id!r} not found") from None


class Catalog:
    """The data directory's `catalog.sqlite` (WAL, synchronous=FULL, like every storage file).

    Thread-safe through one lock; every mutation is one committed transaction when it returns.
    """

    def __init__(self, path: str | os.PathLike[str], readonly: bool = False) -> None:
        """Open (creating if needed) the catalog at `path`; prefer `Catalog.open`.

        Raises:
            StorageFull: no room beside it for its -wal and -shm files (or to create it).
        """
        self.path = Path(path)
        self._lock = threading.RLock()
        self._conn: sqlite3.Connection | None = None
        if readonly:
            if not self.path.is_file():  # SQLite would answer as if it were empty
                raise FileNotFoundError(f"{self.path} does not exist")
            self._conn = connect(self.path, readonly=True)
            self._db = _tables(self._conn)
            return
        try:
            self._conn = connect(self.path)
        except sqlite3.Error as exc:  # its -wal and -shm files are made beside it: a full disk says so here
            if is_full_error(exc):
                raise StorageFull(f"{self.path}: no room to open it ({exc}): make room in the data "
                                  "directory") from exc
            raise
        self._db = _tables(self._conn)
        try:
            # Per connection: without it ON DELETE CASCADE would not remove a deleted map's snapshots.
            self._conn.execute("PRAGMA foreign_keys=ON")
            with transaction(self._conn):
                for statement in _SCHEMA.split(";"):
                    if statement.strip():
                        self._conn.execute(statement)
            version = int(self._conn.execute(
                "SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0])
            if version > _SCHEMA_VERSION:
                raise StorageError(f"{path}: catalog schema {version} is newer than this code's "
                                   f"{_SCHEMA_VERSION}")
            if version < _SCHEMA_VERSION:
                with transaction(self._conn):  # read again under the write lock: another opener may
                    current = int(self._conn.execute(  # have migrated it meanwhile
                        "SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0])
                    for statement in (*(_V2 if current < 2 else ()), *(_V3 if current < 3 else ())):
                        self._conn.execute(statement)
            with transaction(self._conn):  # absolute paths of older versions become relative (`_snap`)
                snapshots = self._db["snapshots"]
                for r in list(snapshots.rows_where("path LIKE '/%'")):
                    snapshots.update(r["ord"], {"path": _snap(r).path})
        except BaseException:
            self._conn.close()
            raise

    @classmethod
    def open(cls, path: str | os.PathLike[str], *, readonly: bool = False) -> Catalog:
        """Open or create the catalog file; `readonly`: inspect an existing one, changing nothing (no
        schema upgrade, no path migration: `_snap` reads old rows the same way)."""
        return cls(path, readonly)

    @property
    def root(self) -> Path:
        """The data directory: snapshot paths are relative to it."""
        return self.path.parent

    @property
    def layout(self) -> Layout:
        """The paths of the data directory this catalog describes."""
        return Layout(self.root)

    def snapshot_dir(self, record: SnapshotRecord) -> Path:
        """A registered snapshot's directory (absolute, in this data directory)."""
        return self.root / record.path

    def close(self) -> None:
        """Close the connection (idempotent)."""
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    def __enter__(self) -> Catalog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @contextmanager
    def _write(self) -> Iterator[sqlite_utils.Database]:
        """The tables, inside one `BEGIN IMMEDIATE` ... `COMMIT` under the lock."""
        with self._lock:
            if self._conn is None:
                raise StoreClosed(f"{self.path}: catalog is closed")
            with transaction(self._conn):
                yield self._db

    @contextmanager
    def _tables(self) -> Iterator[sqlite_utils.Database]:
        """The tables, to read, under the lock."""
        with self._lock:
            if self._conn is None:
                raise StoreClosed(f"{self.path}: catalog is closed")
            yield self._db

    def check(self) -> dict[str, Any]:
        """`/readyz`'s catalog check: `PRAGMA quick_check` reads every page of this small file, so a
        file damaged or replaced under the open connection is seen, not only a closed one."""
        try:
            with self._tables() as db:
                result = [r[0] for r in db.execute("PRAGMA quick_check").fetchall()]
        except (sqlite3.Error, StorageError) as exc:
            return {"status": "fail", "path": str(self.path), "error": f"catalog unreadable: {exc}"}
        if result != ["ok"]:
            return {"status": "fail", "path": str(self.path), "error": f"catalog damaged: {result[:3]}"}
        return {"status": "pass", "path": str(self.path)}

    # ------------------------------------------------------------------ maps

    def create_map(self, map_id: str, params: dict[str, Any], *, preset: str | None = None,
                   state: MapState = "ready", lineage: Lineage | None = None) -> MapRecord:
        """Register a new map, made now; `lineage`: its creation, counts and id marks where it comes from
        elsewhere (a snapshot's: a move between shards, an import).

        Raises:
            MapExists: the id is taken.
            ValueError: unknown state.
        """
        if state not in MAP_STATES:
            raise ValueError(f"state must be one of {MAP_STATES}, got {state!r}")
        line = lineage or Lineage(utc_now())
        try:
            with self._write() as db:
                db["maps"].insert({"map_id": map_id, "created_at": line.created_at, "state": state,
                                   "preset": preset, "params": json.dumps(params, sort_keys=True),
                                   "seq_high_water": line.seq_high_water,
                                   "closure_high_water": line.closure_high_water, "restores": line.restores,
                                   "rewrites": line.rewrites, "repaired_below": line.repaired_below})
        except sqlite3.IntegrityError as exc:
            raise MapExists(f"map {map_id!r} exists") from exc
        return MapRecord(map_id, line.created_at, state, None, preset, json.loads(json.dumps(params)),
                         line.seq_high_water, line.closure_high_water, line.restores, line.rewrites,
                         line.repaired_below)

    def get_map(self, map_id: str) -> MapRecord | None:
        """The map's record, or None."""
        with self._tables() as db:
            try:
                return _map(db["maps"].get(map_id))
            except NotFoundError:
                return None

    def list_maps(self) -> list[MapRecord]:
        """All maps, oldest first (creation order)."""
        with self._tables() as db:
            return [_map(r) for r in db["maps"].rows_where(order_by="created_at, map_id")]

    def set_state(self, map_id: str, state: MapState, reason: str | None = None) -> MapRecord:
        """Set a map's state and reason (the reason is cleared when not given).

        Raises:
            MapNotFound: unknown map.
            ValueError: unknown state.
        """
        if state not in MAP_STATES:
            raise ValueError(f"state must be one of {MAP_STATES}, got {state!r}")
        with self._write() as db:
            _get_map(db, map_id)
            db["maps"].update(map_id, {"state": state, "state_reason": reason})
            return _map(db["maps"].get(map_id))

    def update_params(self, map_id: str, **changes: Any) -> MapRecord:
        """Change a map's settings that may change after creation (e.g. `revisit_threshold`), in its
        params, in one transaction.

        Raises:
            MapNotFound: unknown map.
        """
        with self._write() as db:
            params = {**json.loads(_get_map(db, map_id)["params"]), **changes}
            db["maps"].update(map_id, {"params": json.dumps(params, sort_keys=True)})
            return _map(db["maps"].get(map_id))

    def delete_map(self, map_id: str) -> list[SnapshotRecord]:
        """Remove a map, its snapshot registrations and its high-water mark from the catalog.

        Files are the caller's to remove (maps/<id>/ as a whole); the returned records say which
        snapshot directories were registered.

        Raises:
            MapNotFound: unknown map.
        """
        with self._write() as db:
            _get_map(db, map_id)
            snaps = [_snap(r) for r in db["snapshots"].rows_where("map_id = ?", [map_id],
                                                                  order_by="ord DESC")]
            db["maps"].delete(map_id)  # ON DELETE CASCADE removes its snapshot rows
        return snaps

    # ------------------------------------------------------------------ high-water marks

    def mark_restore(self, map_id: str, seq: int, closure_id: int) -> MapRecord:
        """Before a restore replaces the map's file: raise its seq and loop-closure id marks to at least
        `seq` and `closure_id` (never lowered) and count the restore (module docstring). The ids a repair
        judged are forgotten: the restored log is another, whose pruned entries a follower that rebuilt
        from it may hold.

        Returns:
            The map's record after the call.

        Raises:
            MapNotFound: unknown map.
        """
        with self._write() as db:
            r = _get_map(db, map_id)
            db["maps"].update(map_id, {
                "seq_high_water": max(int(r["seq_high_water"]), int(seq)),
                "closure_high_water": max(int(r["closure_high_water"]), int(closure_id)),
                "restores": int(r["restores"]) + 1, "repaired_below": 0})
            return _map(_get_map(db, map_id))

    def mark_rewrite(self, map_id: str) -> MapRecord:
        """Before a repair on a log whose cap pruned entries logged since the last repair: count it, which
        changes the map's epoch (module docstring), so a follower of the log rebuilds its edges.

        Raises:
            MapNotFound: unknown map.
        """
        with self._write() as db:
            r = _get_map(db, map_id)
            db["maps"].update(map_id, {"rewrites": int(r.get("rewrites") or 0) + 1})
            return _map(_get_map(db, map_id))

    def mark_repaired(self, map_id: str, below: int) -> MapRecord:
        """After a repair: the log ids below `below` were judged (`repaired_below`, never lowered).

        Raises:
            MapNotFound: unknown map.
        """
        with self._write() as db:
            r = _get_map(db, map_id)
            db["maps"].update(map_id, {"repaired_below": max(int(r.get("repaired_below") or 0), int(below))})
            return _map(_get_map(db, map_id))

    # ------------------------------------------------------------------ snapshots

    def register_snapshot(self, record: SnapshotRecord) -> SnapshotRecord:
        """Add a snapshot to the registry (after its directory was renamed into place).

        Raises:
            MapNotFound: unknown map.
            ValueError: unknown kind, a snapshot id already registered for this map, or a path outside
                the data directory (an absolute path inside it is stored relative to it).
        """
        if record.kind not in SNAPSHOT_KINDS:
            raise ValueError(f"kind must be one of {SNAPSHOT_KINDS}, got {record.kind!r}")
        path = Path(record.path)
        if path.is_absolute():
            try:
                path = path.resolve().relative_to(self.root.resolve())
            except ValueError:
                raise ValueError(f"snapshot path {record.path} is outside the data directory "
                                 f"{self.root}") from None
        if ".." in path.parts:
            raise ValueError(f"snapshot path {record.path} leaves the data directory")
        try:
            with self._write() as db:
                _get_map(db, record.map_id)
                db["snapshots"].insert({**dataclasses.asdict(record), "seq": int(record.seq),
                                        "bytes": int(record.bytes), "path": path.as_posix()})
        except sqlite3.IntegrityError as exc:
            raise ValueError(f"snapshot {record.snapshot_id!r} of map {record.map_id!r}: {exc}") from exc
        return record

    def list_snapshots(self, map_id: str, kind: SnapshotKind | None = None) -> list[SnapshotRecord]:
        """A map's snapshots, newest first.

        "Newest" is registration order, not `seq`: after a restore a newer snapshot can have a
        lower seq than the pre-restore one, and wall-clock times can step back.
        """
        where, args = ("map_id = ?", [map_id]) if kind is None else ("map_id = ? AND kind = ?",
                                                                      [map_id, kind])
        with self._tables() as db:
            return [_snap(r) for r in db["snapshots"].rows_where(where, args, order_by="ord DESC")]

    def get_snapshot(self, map_id: str, snapshot_id: str) -> SnapshotRecord | None:
        """One snapshot's record, or None."""
        with self._tables() as db:
            rows = list(db["snapshots"].rows_where(_ONE_SNAPSHOT, [map_id, snapshot_id]))
        return _snap(rows[0]) if rows else None

    def delete_snapshot(self, map_id: str, snapshot_id: str) -> bool:
        """Remove a snapshot from the registry (its directory is the caller's to remove).

        Returns:
            Whether it was registered.
        """
        with self._write() as db:
            found = db["snapshots"].count_where(_ONE_SNAPSHOT, [map_id, snapshot_id]) > 0
            db["snapshots"].delete_where(_ONE_SNAPSHOT, [map_id, snapshot_id])
            return found

    def snapshots_bytes(self, map_id: str) -> int:
        """Total registered snapshot bytes of a map (`storage.snapshots_bytes` of the memory endpoint)."""
        with self._tables() as db:
            return int(db.execute("SELECT coalesce(sum(bytes), 0) FROM snapshots WHERE map_id = ?",
                                  [map_id]).fetchone()[0])
