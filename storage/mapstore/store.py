"""`MapStore`: one map's `map.sqlite` opened (docs/design/service.md §4.2–§4.3): its connection, lock and
lifecycle, what the file holds (`storage.mapschema.Holds`, read once at open) and the families of
tables composed (`storage.mapstore`'s docstring).
"""

from __future__ import annotations

import os
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from storage._common import (
    StorageError,
    StorageFull,
    StoreClosed,
    StoreCorrupt,
    StoreUnopenable,
    connect,
    is_full_error,
)
from storage.base.files import is_no_room, probe_write
from storage.mapschema import SCHEMA_VERSION, Holds, MapMeta, create_file, migrate, read_meta
from storage.mapstore.closures import Closures, closure_columns
from storage.mapstore.copies import Copies
from storage.mapstore.keyframes import Keyframes
from storage.mapstore.observations import Observations
from storage.mapstore.streams import Streams
from storage.mapstore.visits import Visits

__all__ = ["ROOM_PROBE_NAME", "MapStore"]

#: `MapStore.has_room`'s probe file, beside `map.sqlite` (one name: a probe cut short by a kill leaves one
#: file, which the next probe truncates and removes).
ROOM_PROBE_NAME = ".room-probe"


class MapStore(Observations, Visits, Streams, Closures, Keyframes, Copies):
    """One map's `map.sqlite`: frozen meta + append-only observations, and the tables written with them
    (one module per family: observations, visits, streams, closures, keyframes, copies).

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
                 max_keys: int | None = None, max_closures: int | None = None,
                 closure_floor: int = 0) -> None:
        """Use `MapStore.create` or `MapStore.open`."""
        self.path = path
        self.meta = meta
        self.max_keys = max_keys
        self.max_closures = max_closures
        # What the file holds, read once here: an older file opened read-only is not migrated, and
        # each reader asks for its table by name (`storage.mapschema.Holds`), never for a version.
        self.holds = Holds.of(meta.schema_version)
        self._closure_columns = closure_columns(self.holds)
        self._conn: sqlite3.Connection | None = conn
        self._lock = threading.RLock()
        self._cell_dtype = meta.cell_dtype
        last, count = conn.execute("SELECT coalesce(max(seq), 0), count(*) FROM observations").fetchone()
        if self.holds.joined_rows:  # a joined row turned into a visit was deleted: its seq stays handed out
            last = max(int(last), int(conn.execute("SELECT coalesce(max(seq), 0) FROM joins").fetchone()[0]))
        self._last_seq = int(last)
        self._count = int(count)
        self._seq_floor = max(0, int(seq_floor))
        self._closure_floor = max(0, int(closure_floor))
        self._synced_wal: int | None = None  # the inode of the WAL file whose directory entry `sync` synced

    @classmethod
    def create(cls, path: str | os.PathLike[str], meta: MapMeta, *, seq_floor: int = 0,
               max_keys: int | None = None, max_closures: int | None = None,
               closure_floor: int = 0) -> MapStore:
        """Create a new `map.sqlite` atomically (`storage.mapschema.create_file`: a crash leaves no map
        file or a complete one) and open it.

        Args:
            path: the file to create; its directory must exist.
            meta: what is frozen into the map.
            seq_floor, max_keys, max_closures, closure_floor: see `open`.

        Raises:
            FileExistsError: `path` exists.
        """
        create_file(Path(path), meta)
        return cls.open(path, seq_floor=seq_floor, max_keys=max_keys, max_closures=max_closures,
                        closure_floor=closure_floor)

    @classmethod
    def open(cls, path: str | os.PathLike[str], *, seq_floor: int = 0, readonly: bool = False,
             max_keys: int | None = None, max_closures: int | None = None,
             closure_floor: int = 0) -> MapStore:
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
            closure_floor: the same as `seq_floor` for loop-closure log ids (the catalog's mark): the
                next entry's id is above it, so a restored log never hands out an id again.

        Raises:
            FileNotFoundError: no such file (SQLite would silently create an empty one).
            StoreCorrupt: not a map database (damaged, or another file).
            StorageFull: no room to open it (its -wal and -shm files) or to migrate it: the file is whole.
            StoreUnopenable: SQLite could not open it (a permission, a read-only file or directory),
                with the OS's words: nothing says it is damaged.
            StorageError: written by a newer schema version.
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path} does not exist")
        try:
            conn = connect(path, readonly=readonly)
        except StoreCorrupt as exc:  # connect's own PRAGMAs read the file, and its cursors say no path
            raise _corrupt_at(path, exc) from exc
        except sqlite3.DatabaseError as exc:
            raise _open_error(path, exc) from exc
        try:
            meta = read_meta(conn, path)
            if meta.schema_version > SCHEMA_VERSION:
                raise StorageError(f"{path}: schema version {meta.schema_version} is newer than "
                                   f"this code's {SCHEMA_VERSION}")
            if not readonly:
                meta = migrate(conn, meta)
            return cls(path, conn, meta, seq_floor, max_keys, max_closures, closure_floor)
        except StoreCorrupt as exc:  # the first read of a file that is no database (read_meta's SELECT)
            conn.close()
            raise _corrupt_at(path, exc) from exc
        except sqlite3.DatabaseError as exc:
            conn.close()
            if is_full_error(exc):  # the migration found no room: the file is whole, the disk is not
                raise StorageFull(f"{path}: no room to migrate to schema {SCHEMA_VERSION}") from exc
            raise _open_error(path, exc) from exc
        except BaseException:
            conn.close()
            raise

    @property
    def writable(self) -> bool:
        """Whether this process may write the file (`os.access`, one system call, no probe written): an
        immutable or read-only file, or one on a read-only mount, is opened by SQLite read-only without a
        word, and only its first write would say so (`StoreReadOnly`)."""
        return os.access(self.path, os.W_OK)

    def has_room(self, nbytes: int) -> bool:
        """Whether the filesystem of the map's file takes `nbytes` now: a probe file beside it written,
        fsynced and removed (`storage.base.files.probe_write`), on the same disk and under the same quota
        as the file, without touching the file. False only where the OS says there is no room; another
        failure (a permission on the directory) cannot tell, so it is True and the store's own next write
        says what it is."""
        try:
            probe_write(self.path.parent / ROOM_PROBE_NAME, nbytes)
        except OSError as exc:
            return not is_no_room(exc)
        return True

    def close(self) -> None:
        """Close the connection (idempotent). SQLite checkpoints and removes the WAL on the last close."""
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    @contextmanager
    def reader(self) -> Iterator[MapStore]:
        """A second connection to this file, for a long read off the connection its writer uses, in one
        read transaction: it sees the file as of its first read, whatever the writer commits meanwhile
        (WAL), and holds no lock the writer waits on. Its floors are this store's, so it answers as this
        one does (`next_closure_id`). Closed after."""
        other = MapStore.open(self.path, seq_floor=self._seq_floor, closure_floor=self._closure_floor)
        with other, other._lock:
            conn = other._db()
            conn.execute("BEGIN")  # deferred: a read transaction from the first read to the end
            try:
                yield other
            finally:
                conn.execute("COMMIT")

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


#: SQLite's codes for a file it could not open or write as asked (prefixes of `sqlite_errorname`).
_UNOPENABLE = ("SQLITE_CANTOPEN", "SQLITE_PERM", "SQLITE_READONLY", "SQLITE_AUTH")


def _corrupt_at(path: Path, exc: StoreCorrupt) -> StoreCorrupt:
    """`exc` naming the file (the cursors' `StoreCorrupt` has SQLite's words alone; read_meta's names it)."""
    return exc if str(exc).startswith(f"{path}:") else StoreCorrupt(f"{path}: {exc}")


def _open_error(path: Path, exc: sqlite3.DatabaseError) -> StorageError:
    """What an open's SQLite error means: the file or its directory cannot be reached as needed
    (`_UNOPENABLE`: a permission, a read-only file, directory or mount) is `StoreUnopenable` with the OS's
    words where it gives them, never called corrupt (an operator deletes a corrupt map, and a permission
    must not cost a healthy one); no room beside it for its -wal and -shm files (SQLITE_IOERR_SHMSIZE on a
    full disk: `is_full_error`) is `StorageFull`, for the same reason (before, a healthy map met a full disk
    at a restart and was called corrupt); anything else says the file is no map database: `StoreCorrupt`."""
    if is_full_error(exc):
        return StorageFull(f"{path}: no room to open it ({exc}): its -wal and -shm files are made beside it")
    if not str(getattr(exc, "sqlite_errorname", "")).startswith(_UNOPENABLE):
        return StoreCorrupt(f"{path}: {exc}")
    why = str(exc)
    try:  # SQLite keeps the errno to itself: ask the OS for the file, then for its directory (-wal, -shm)
        os.close(os.open(path, os.O_RDWR))
        if not os.access(path.parent, os.W_OK | os.X_OK):
            why += f" ({path.parent}: the directory is not writable, SQLite's -wal and -shm files live there)"
    except OSError as e:
        why += f" ({e.strerror or e})"
    return StoreUnopenable(f"{path}: {why}")
