"""Pieces shared by the storage modules: the error base class, timestamps, and how SQLite is opened.

Kept private (leading underscore): the public names are re-exported by the modules that use them.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from storage.base.files import is_no_room


class StorageError(Exception):
    """Base class of every error raised on purpose by `storage` (the service maps them to problems)."""


# Exception names follow the service's problem slugs (map-full, snapshot-invalid, ...), hence no "Error"
# suffix on the subclasses.
class StorageFull(StorageError):  # noqa: N818
    """A write failed for lack of space (SQLITE_FULL or ENOSPC); nothing of that write is committed."""


class StoreCorrupt(StorageError):  # noqa: N818
    """The file is not a readable database (not SQLite, malformed pages, tables missing, meta unreadable):
    SQLITE_CORRUPT or SQLITE_NOTADB at open or at any later read (`connect`'s connections say it so)."""


class StoreUnopenable(StorageError):  # noqa: N818
    """The file could not be opened (SQLITE_CANTOPEN, SQLITE_PERM, SQLITE_READONLY at open: a permission,
    a read-only file or directory): nothing says its contents are damaged; the message has the OS's words."""


class StoreReadOnly(StorageError):  # noqa: N818
    """A write met a database SQLite could open read-only only (SQLITE_READONLY: an immutable or
    read-only file, a read-only mount); nothing of that write is committed."""


class StoreClosed(StorageError):  # noqa: N818
    """A read or write reached a store or catalog that is closed (a restore, a deletion or a shutdown is
    swapping it): nothing was done, and the same request may succeed a moment later."""


def utc_now() -> str:
    """Current UTC time as ISO 8601 with microseconds and a `Z` suffix (sortable as text)."""
    return datetime.now(UTC).isoformat(timespec="microseconds").replace("+00:00", "Z")


#: SQLite's words for a damaged file (`sqlite_errorname`, extended codes included): `StoreCorrupt`.
_CORRUPT_SQLITE = ("SQLITE_CORRUPT", "SQLITE_NOTADB")
#: Python's sqlite3 on a text cell whose bytes are not UTF-8 (an OperationalError, no SQLite code). Every
#: text cell is written as UTF-8 by this code, so such a cell is flipped bits that SQLite's page checks
#: passed: an outside probe's bit-flipped file was "the check itself failed" in `cortexloc verify` and a
#: traceback in the server. In a schema name it comes as a UnicodeDecodeError instead (`_corruption_named`).
_UNDECODABLE = "Could not decode to UTF-8"


def is_corrupt_error(exc: BaseException) -> bool:
    """True when SQLite says the file is damaged (`_CORRUPT_SQLITE`), not that it cannot reach it."""
    return isinstance(exc, sqlite3.DatabaseError) and str(getattr(exc, "sqlite_errorname", "")).startswith(
        _CORRUPT_SQLITE)


@contextmanager
def _corruption_named() -> Iterator[None]:
    try:
        yield
    except sqlite3.DatabaseError as exc:
        if is_corrupt_error(exc):
            raise StoreCorrupt(str(exc)) from exc
        if str(exc).startswith(_UNDECODABLE):
            raise StoreCorrupt(f"a text cell is not UTF-8 (damaged file): {exc}") from exc
        raise
    except UnicodeDecodeError as exc:  # the same, in SQLite's own message about a schema name
        raise StoreCorrupt(f"a text cell is not UTF-8 (damaged file): {exc}") from exc


class _Cursor(sqlite3.Cursor):
    """A cursor whose statements and fetches say a damaged file as `StoreCorrupt` (a malformed page is
    met at whichever step reads it), so that no caller above storage sees a raw sqlite3 error for it."""

    def execute(self, sql: str, parameters: Any = (), /) -> _Cursor:
        with _corruption_named():
            return super().execute(sql, parameters)

    def executemany(self, sql: str, seq_of_parameters: Any, /) -> _Cursor:
        with _corruption_named():
            return super().executemany(sql, seq_of_parameters)

    def executescript(self, sql_script: str, /) -> _Cursor:
        with _corruption_named():
            return super().executescript(sql_script)

    def __next__(self) -> Any:
        with _corruption_named():
            return super().__next__()

    def fetchone(self) -> Any:
        with _corruption_named():
            return super().fetchone()

    def fetchmany(self, size: int | None = None) -> list[Any]:
        with _corruption_named():
            return super().fetchmany(self.arraysize if size is None else size)

    def fetchall(self) -> list[Any]:
        with _corruption_named():
            return super().fetchall()


class _Connection(sqlite3.Connection):
    """`connect`'s connection: its statements run on `_Cursor`s (CPython's own `execute` would not)."""

    def cursor(self, factory: Any = _Cursor) -> Any:
        return super().cursor(factory)

    def execute(self, sql: str, parameters: Any = (), /) -> Any:
        return self.cursor().execute(sql, parameters)

    def executemany(self, sql: str, parameters: Any, /) -> Any:
        return self.cursor().executemany(sql, parameters)

    def executescript(self, sql_script: str, /) -> Any:
        return self.cursor().executescript(sql_script)


def connect(path: str | Path, *, readonly: bool = False) -> sqlite3.Connection:
    """Open a SQLite file the way every storage file is opened.

    - `isolation_level=None`: Python's implicit transactions are off; writers say `BEGIN IMMEDIATE` and
      `COMMIT` themselves, so a commit happens exactly where the code says (docs/design/service.md §4.3).
    - `check_same_thread=False`: a connection is opened in one thread and used from others: a map's
      store is opened at startup in a worker thread, written by the map's own single writer thread (a
      one-thread executor per map) and read from request handler threads; the catalog likewise. The
      owners (`MapStore`, `Catalog`) serialise access with their own lock instead.
    - a damaged file (SQLITE_CORRUPT, SQLITE_NOTADB) raises `StoreCorrupt` from any statement or fetch,
      not `sqlite3.DatabaseError` (`_Cursor`).
    - WAL + `synchronous=FULL` (read-write only): a commit is on disk when COMMIT returns. `journal_mode`
      is stored in the file, `synchronous` is per connection, so both are set on every open.

    Args:
        path: the database file.
        readonly: inspect without changing anything: `immutable=1` when there is no (non-empty) `-wal`
            file, since even `mode=ro` creates `-wal` and `-shm` files beside a WAL database; `mode=ro`
            when a crash left committed rows in the `-wal` (they must be read; its `-shm` is reused).

    Returns:
        The connection.
    """
    if readonly:
        wal = Path(f"{path}-wal")
        mode = "mode=ro" if wal.is_file() and wal.stat().st_size > 0 else "mode=ro&immutable=1"
        conn = sqlite3.connect(f"{Path(path).resolve().as_uri()}?{mode}", uri=True,
                               isolation_level=None, check_same_thread=False, factory=_Connection)
        return conn
    conn = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False, factory=_Connection)
    try:
        # A reader of another connection (backup, inspection) waits instead of failing at once.
        conn.execute("PRAGMA busy_timeout=5000")
        mode = conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
        if str(mode).lower() != "wal":
            raise StorageError(f"{path}: could not enable WAL journal mode (got {mode!r})")
        conn.execute("PRAGMA synchronous=FULL")
    except BaseException:
        conn.close()
        raise
    return conn


#: What says there is no room to write, in SQLite's words: the disk full, the user's quota used up, the
#: file-size limit (`ulimit -f`) reached (the OS's words: `storage.base.files.NO_ROOM_ERRNOS`). SQLite
#: reports the first as SQLITE_FULL and the other two as a failed write (its VFS keeps the errno to
#: itself); a WAL database whose shared-memory file (-shm) cannot be made or grown says
#: SQLITE_IOERR_SHMSIZE (a new map's file with a few KiB left, answered 500 before; a healthy map opened
#: at a restart on a full disk, called corrupt before). So a failed write counts as no room: a write that
#: fails for any reason is storage refusing the row, answered as such (507, nothing changed), never as a
#: bug. A failing or read-only disk fails writes the same way; the answer carries SQLite's own words
#: ("disk I/O error", "database or disk is full") so that an operator can tell.
_NO_ROOM_SQLITE = frozenset({"SQLITE_FULL", "SQLITE_IOERR_WRITE", "SQLITE_IOERR_SHMSIZE"})


def is_full_error(exc: BaseException) -> bool:
    """True when `exc` means there is no room to write (`_NO_ROOM_SQLITE`, `is_no_room`)."""
    if isinstance(exc, sqlite3.Error):
        return getattr(exc, "sqlite_errorname", "") in _NO_ROOM_SQLITE
    return is_no_room(exc)


@contextmanager
def transaction(conn: sqlite3.Connection) -> Iterator[sqlite3.Connection]:
    """`BEGIN IMMEDIATE` … `COMMIT`, rolled back on any exception; SQLITE_FULL becomes `StorageFull`,
    SQLITE_READONLY `StoreReadOnly`.

    IMMEDIATE takes the write lock at BEGIN, so a second writer fails (or waits) before doing work
    rather than at COMMIT.
    """
    try:
        conn.execute("BEGIN IMMEDIATE")  # a file SQLite holds read-only refuses the write lock already
    except sqlite3.Error as exc:
        if is_read_only_error(exc):
            raise StoreReadOnly(str(exc)) from exc
        raise
    try:
        yield conn
        conn.execute("COMMIT")
    except BaseException as exc:
        if conn.in_transaction:
            # SQLite may already have rolled back on its own (e.g. after SQLITE_FULL).
            with suppress(sqlite3.Error):
                conn.execute("ROLLBACK")
        if is_full_error(exc):
            raise StorageFull(str(exc)) from exc
        if is_read_only_error(exc):
            raise StoreReadOnly(str(exc)) from exc
        raise


def is_read_only_error(exc: BaseException) -> bool:
    """True when SQLite refused a write because it holds the file read-only (SQLITE_READONLY and its
    extended codes)."""
    return isinstance(exc, sqlite3.Error) and str(getattr(exc, "sqlite_errorname", "")).startswith(
        "SQLITE_READONLY")
