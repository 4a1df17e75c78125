"""`map.sqlite` as a file (docs/design/service.md §4.3–§4.4): the group commit's fsync of the WAL, the
integrity checks, the sizes on disk, the online backup a snapshot is taken with and the atomic install of
a copy (restore, import).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sqlite3
from pathlib import Path
from typing import Any, BinaryIO

from storage._common import StorageFull, StoreCorrupt, is_full_error
from storage.base.files import atomic_write, fsync_dir

__all__ = ["Copies"]


class Copies:
    """`MapStore`'s file-level operations (module docstring). It owns the WAL file whose directory
    entry `sync` synced."""

    _synced_wal: int | None

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
        except (sqlite3.DatabaseError, StoreCorrupt):  # (a page too damaged to check: `connect`'s cursors)
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


def _size(p: Path) -> int:
    try:
        return p.stat().st_size
    except FileNotFoundError:
        return 0
