"""Pieces shared by the storage modules: the error base class, timestamps, and how SQLite is opened.

Kept private (leading underscore): the public names are re-exported by the modules that use them.
"""

from __future__ import annotations

import errno
import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from datetime import UTC, datetime
from pathlib import Path


class StorageError(Exception):
    """Base class of every error raised on purpose by `storage` (the service maps them to problems)."""


# Exception names follow the service's problem slugs (map-full, snapshot-invalid, ...), hence no "Error"
# suffix on the subclasses.
class StorageFull(StorageError):  # noqa: N818
    """A write failed for lack of space (SQLITE_FULL or ENOSPC); nothing of that write is committed."""


class StoreClosed(StorageError):  # noqa: N818
    """A read or write reached a store or catalog that is closed (a restore, a deletion or a shutdown is
    swapping it): nothing was done, and the same request may succeed a moment later."""


def utc_now() -> str:
    """Current UTC time as ISO 8601 with microseconds and a `Z` suffix (sortable as text)."""
    return datetime.now(UTC).isoformat(timespec="microseconds").replace("+00:00", "Z")


def connect(path: str | Path, *, readonly: bool = False) -> sqlite3.Connection:
    """Open a SQLite file the way every storage file is opened.

    - `isolation_level=None`: Python's implicit transactions are off; writers say `BEGIN IMMEDIATE` and
      `COMMIT` themselves, so a commit happens exactly where the code says (docs/design/service.md §4.3).
    - `check_same_thread=False`: a connection is opened in one thread and used from others: a map's
      store is opened at startup in a worker thread, written by the map's own single writer thread (a
      one-thread executor per map) and read from request handler threads; the catalog likewise. The
      owners (`MapStore`, `Catalog`) serialise access with their own lock instead.
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
                               isolation_level=None, check_same_thread=False)
        return conn
    conn = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False)
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


#: What says there is no room to write: the disk full, the user's quota used up, the file-size limit
#: (`ulimit -f`) reached. SQLite reports the first as SQLITE_FULL and the other two as a failed write
#: (its VFS keeps the errno to itself), so a failed write counts as no room too: a write that fails for
#: any reason is storage refusing the row, answered as such (507, nothing changed), never as a bug. A
#: failing or read-only disk fails writes the same way; the answer carries SQLite's own words ("disk I/O
#: error", "database or disk is full") so that an operator can tell.
_NO_ROOM_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})
_NO_ROOM_SQLITE = frozenset({"SQLITE_FULL", "SQLITE_IOERR_WRITE"})


def is_full_error(exc: BaseException) -> bool:
    """True when `exc` means there is no room to write (`_NO_ROOM_ERRNOS`, `_NO_ROOM_SQLITE`)."""
    if isinstance(exc, sqlite3.Error):
        return getattr(exc, "sqlite_errorname", "") in _NO_ROOM_SQLITE
    return isinstance(exc, OSError) and exc.errno in _NO_ROOM_ERRNOS


@contextmanager
def transaction(conn: sqlite3.Connection) -> Iterator[sqlite3.Connection]:
    """`BEGIN IMMEDIATE` … `COMMIT`, rolled back on any exception; SQLITE_FULL becomes `StorageFull`.

    IMMEDIATE takes the write lock at BEGIN, so a second writer fails (or waits) before doing work
    rather than at COMMIT.
    """
    conn.execute("BEGIN IMMEDIATE")
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
        raise
