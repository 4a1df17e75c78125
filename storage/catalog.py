"""`catalog.sqlite`: the list of maps, their states, the snapshot registry and seq high-water marks.

The catalog is small and written rarely (map creation, state changes, snapshots, restores), so one file
for the whole data directory is enough; each map's observations live in its own `map.sqlite`.

The seq high-water mark is what keeps seqs unique across restores (docs/design/service.md §1: "never reused,
not even after a restore"): before a restore replaces `map.sqlite` with an older copy, the service bumps
the mark to the current last seq, and opens the restored file with `MapStore.open(seq_floor=mark)`.
Bumping only at restore (not per observation) keeps the per-observation commit to one file.
"""

from __future__ import annotations

import json
import os
import re
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from storage._common import StorageError, connect, transaction, utc_now

__all__ = [
    "MAP_ID_RE",
    "MAP_STATES",
    "SNAPSHOT_ID_RE",
    "SNAPSHOT_KINDS",
    "Catalog",
    "MapExists",
    "MapNotFound",
    "MapRecord",
    "SnapshotRecord",
    "StorageError",
    "snapshot_relpath",
]

#: A map id (the API's rule; also a directory name under `maps/`, so never `.`, `..` or a path).
MAP_ID_RE = re.compile(r"^[a-z0-9][a-z0-9._-]{0,63}$")
#: A snapshot id: what the API's `{snapshot_id}` accepts, less a leading dot (also a directory name).
SNAPSHOT_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,79}$")

MapState = Literal["ready", "recovering", "failed"]
SnapshotKind = Literal["manual", "auto", "pre-restore"]
MAP_STATES: tuple[str, ...] = ("ready", "recovering", "failed")
SNAPSHOT_KINDS: tuple[str, ...] = ("manual", "auto", "pre-restore")

_SCHEMA_VERSION = 1
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
    seq_high_water  INTEGER NOT NULL DEFAULT 0 CHECK (seq_high_water >= 0)
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


class MapExists(StorageError):  # noqa: N818 - named after the problem slug `map-exists`
    """`create_map` with an id that is already in the catalog."""


class MapNotFound(StorageError):  # noqa: N818 - named after the problem slug `map-not-found`
    """An operation on a map id that is not in the catalog."""


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
    """

    map_id: str
    created_at: str
    state: str
    state_reason: str | None
    preset: str | None
    params: dict[str, Any]
    seq_high_water: int


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


_MAP_COLS = "map_id, created_at, state, state_reason, preset, params, seq_high_water"
_SNAP_COLS = "snapshot_id, map_id, seq, kind, created_at, bytes, manifest_sha256, path"


def _map(r: tuple[Any, ...]) -> MapRecord:
    return MapRecord(map_id=r[0], created_at=r[1], state=r[2], state_reason=r[3], preset=r[4],
                     params=json.loads(r[5]), seq_high_water=int(r[6]))


def snapshot_relpath(map_id: str, snapshot_id: str) -> str:
    """Where a snapshot lives, relative to the data directory (the one layout every writer uses)."""
    return f"maps/{map_id}/snapshots/{snapshot_id}"


def _snap(r: tuple[Any, ...]) -> SnapshotRecord:
    path = r[7]
    if os.path.isabs(path):
        # Written by a version that stored absolute paths: the directory may have been moved or copied
        # since, and reading the path as written would use another data directory's files. A snapshot
        # always lies at its place in *this* data directory.
        path = snapshot_relpath(r[1], r[0])
    return SnapshotRecord(snapshot_id=r[0], map_id=r[1], seq=int(r[2]), kind=r[3], created_at=r[4],
                          bytes=int(r[5]), manifest_sha256=r[6], path=path)


class Catalog:
    """The data directory's `catalog.sqlite` (WAL, synchronous=FULL, like every storage file).

    Thread-safe through one lock; every mutation is one committed transaction when it returns.
    """

    def __init__(self, path: str | os.PathLike[str], readonly: bool = False) -> None:
        """Open (creating if needed) the catalog at `path`; prefer `Catalog.open`."""
        self.path = Path(path)
        self._lock = threading.RLock()
        self._conn: sqlite3.Connection | None = None
        if readonly:
            if not self.path.is_file():  # SQLite would answer as if it were empty
                raise FileNotFoundError(f"{self.path} does not exist")
            self._conn = connect(self.path, readonly=True)
            return
        self._conn = connect(self.path)
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
            with transaction(self._conn):  # absolute paths of older versions become relative (`_snap`)
                for r in self._conn.execute(f"SELECT {_SNAP_COLS} FROM snapshots WHERE path LIKE '/%'"
                                            ).fetchall():
                    self._conn.execute("UPDATE snapshots SET path = ? WHERE map_id = ? AND snapshot_id = ?",
                                       (_snap(r).path, r[1], r[0]))
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
    def _write(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            if self._conn is None:
                raise StorageError(f"{self.path}: catalog is closed")
            with transaction(self._conn) as conn:
                yield conn

    def _read(self, sql: str, args: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
        with self._lock:
            if self._conn is None:
                raise StorageError(f"{self.path}: catalog is closed")
            return self._conn.execute(sql, args).fetchall()

    def ping(self) -> bool:
        """The catalog answers a query."""
        try:
            self._read("SELECT 1")
        except (sqlite3.Error, StorageError):
            return False
        return True

    def check(self) -> dict[str, Any]:
        """`/readyz`'s catalog check: `PRAGMA quick_check` reads every page of this small file, so a
        file damaged or replaced under the open connection is seen, not only a closed one."""
        try:
            result = [r[0] for r in self._read("PRAGMA quick_check")]
        except (sqlite3.Error, StorageError) as exc:
            return {"status": "fail", "path": str(self.path), "error": f"catalog unreadable: {exc}"}
        if result != ["ok"]:
            return {"status": "fail", "path": str(self.path), "error": f"catalog damaged: {result[:3]}"}
        return {"status": "pass", "path": str(self.path)}

    # ------------------------------------------------------------------ maps

    def create_map(self, map_id: str, params: dict[str, Any], *, preset: str | None = None,
                   state: MapState = "ready", created_at: str | None = None) -> MapRecord:
        """Register a new map.

        Raises:
            MapExists: the id is taken.
            ValueError: unknown state.
        """
        if state not in MAP_STATES:
            raise ValueError(f"state must be one of {MAP_STATES}, got {state!r}")
        created_at = created_at or utc_now()
        try:
            with self._write() as conn:
                conn.execute(f"INSERT INTO maps ({_MAP_COLS}) VALUES (?, ?, ?, NULL, ?, ?, 0)",
                             (map_id, created_at, state, preset, json.dumps(params, sort_keys=True)))
        except sqlite3.IntegrityError as exc:
            raise MapExists(f"map {map_id!r} exists") from exc
        return MapRecord(map_id, created_at, state, None, preset, json.loads(json.dumps(params)), 0)

    def get_map(self, map_id: str) -> MapRecord | None:
        """The map's record, or None."""
        rows = self._read(f"SELECT {_MAP_COLS} FROM maps WHERE map_id = ?", (map_id,))
        return _map(rows[0]) if rows else None

    def list_maps(self) -> list[MapRecord]:
        """All maps, oldest first (creation order)."""
        return [_map(r) for r in self._read(f"SELECT {_MAP_COLS} FROM maps ORDER BY created_at, map_id")]

    def count_maps(self) -> int:
        """Number of maps (for `CORTEXLOC_MAX_MAPS`)."""
        return int(self._read("SELECT count(*) FROM maps")[0][0])

    def set_state(self, map_id: str, state: MapState, reason: str | None = None) -> MapRecord:
        """Set a map's state and reason (the reason is cleared when not given).

        Raises:
            MapNotFound: unknown map.
            ValueError: unknown state.
        """
        if state not in MAP_STATES:
            raise ValueError(f"state must be one of {MAP_STATES}, got {state!r}")
        with self._write() as conn:
            cur = conn.execute("UPDATE maps SET state = ?, state_reason = ? WHERE map_id = ?",
                               (state, reason, map_id))
            if cur.rowcount == 0:
                raise MapNotFound(f"map {map_id!r} not found")
        rec = self.get_map(map_id)
        assert rec is not None
        return rec

    def delete_map(self, map_id: str) -> list[SnapshotRecord]:
        """Remove a map, its snapshot registrations and its high-water mark from the catalog.

        Files are the caller's to remove (maps/<id>/ as a whole); the returned records say which
        snapshot directories were registered.

        Raises:
            MapNotFound: unknown map.
        """
        with self._write() as conn:
            snaps = [_snap(r) for r in conn.execute(
                f"SELECT {_SNAP_COLS} FROM snapshots WHERE map_id = ? ORDER BY ord DESC", (map_id,))]
            if conn.execute("DELETE FROM maps WHERE map_id = ?", (map_id,)).rowcount == 0:
                raise MapNotFound(f"map {map_id!r} not found")
        return snaps

    # ------------------------------------------------------------------ seq high-water mark

    def bump_high_water(self, map_id: str, seq: int) -> int:
        """Raise the map's seq high-water mark to at least `seq` (never lowers it).

        Returns:
            The mark after the call.

        Raises:
            MapNotFound: unknown map.
        """
        with self._write() as conn:
            cur = conn.execute("UPDATE maps SET seq_high_water = max(seq_high_water, ?) WHERE map_id = ?",
                               (int(seq), map_id))
            if cur.rowcount == 0:
                raise MapNotFound(f"map {map_id!r} not found")
            return int(conn.execute("SELECT seq_high_water FROM maps WHERE map_id = ?",
                                    (map_id,)).fetchone()[0])

    def get_high_water(self, map_id: str) -> int:
        """The map's seq high-water mark.

        Raises:
            MapNotFound: unknown map.
        """
        rows = self._read("SELECT seq_high_water FROM maps WHERE map_id = ?", (map_id,))
        if not rows:
            raise MapNotFound(f"map {map_id!r} not found")
        return int(rows[0][0])

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
            with self._write() as conn:
                if conn.execute("SELECT 1 FROM maps WHERE map_id = ?", (record.map_id,)).fetchone() is None:
                    raise MapNotFound(f"map {record.map_id!r} not found")
                conn.execute(f"INSERT INTO snapshots ({_SNAP_COLS}) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                             (record.snapshot_id, record.map_id, int(record.seq), record.kind,
                              record.created_at, int(record.bytes), record.manifest_sha256,
                              path.as_posix()))
        except sqlite3.IntegrityError as exc:
            raise ValueError(f"snapshot {record.snapshot_id!r} of map {record.map_id!r}: {exc}") from exc
        return record

    def list_snapshots(self, map_id: str, kind: SnapshotKind | None = None) -> list[SnapshotRecord]:
        """A map's snapshots, newest first.

        "Newest" is registration order, not `seq`: after a restore a newer snapshot can have a
        lower seq than the pre-restore one, and wall-clock times can step back.
        """
        if kind is None:
            rows = self._read(f"SELECT {_SNAP_COLS} FROM snapshots WHERE map_id = ? ORDER BY ord DESC",
                              (map_id,))
        else:
            rows = self._read(f"SELECT {_SNAP_COLS} FROM snapshots WHERE map_id = ? AND kind = ? "
                              "ORDER BY ord DESC", (map_id, kind))
        return [_snap(r) for r in rows]

    def get_snapshot(self, map_id: str, snapshot_id: str) -> SnapshotRecord | None:
        """One snapshot's record, or None."""
        rows = self._read(f"SELECT {_SNAP_COLS} FROM snapshots WHERE map_id = ? AND snapshot_id = ?",
                          (map_id, snapshot_id))
        return _snap(rows[0]) if rows else None

    def delete_snapshot(self, map_id: str, snapshot_id: str) -> bool:
        """Remove a snapshot from the registry (its directory is the caller's to remove).

        Returns:
            Whether it was registered.
        """
        with self._write() as conn:
            cur = conn.execute("DELETE FROM snapshots WHERE map_id = ? AND snapshot_id = ?",
                               (map_id, snapshot_id))
            return cur.rowcount > 0

    def snapshots_bytes(self, map_id: str) -> int:
        """Total registered snapshot bytes of a map (`storage.snapshots_bytes` of the memory endpoint)."""
        return int(self._read("SELECT coalesce(sum(bytes), 0) FROM snapshots WHERE map_id = ?",
                              (map_id,))[0][0])
