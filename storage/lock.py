"""One process at a time on a data directory (docs/design/service.md §4.1): an exclusive advisory lock
on `<root>/.lock`, held while a process has the directory's maps open.

Two servers on one directory each believe they are its only writer: they hand out the same seqs (one of
them answers 500 on every learned post) and, creating a map the other holds, would find its files as
leftovers. The lock is `flock(2)`: the kernel drops it when the holding process exits however it exits
(kill -9 included), so a crash never leaves a stale lock behind. The file holds the holder's pid, for
the refusal's message only. Where `fcntl` does not exist (not POSIX) there is no lock.
"""

from __future__ import annotations

import os
from pathlib import Path

from storage._common import StorageError

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]

__all__ = ["DataDirInUse", "DataDirLock"]


class DataDirInUse(StorageError):  # noqa: N818 - what it says
    """Another process holds the data directory's lock."""


class DataDirLock:
    """The exclusive lock on one data directory: `acquire` or raise DataDirInUse; `release` (idempotent)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._fd: int | None = None

    def acquire(self) -> DataDirLock:
        """Take the lock now, without waiting.

        Raises:
            DataDirInUse: another process (or another open registry of this one) holds it.
        """
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            if fcntl is not None:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
                    raise DataDirInUse(
                        f"{self.path.parent} is in use by another cortexloc process (pid {holder}): one "
                        "process at a time serves a data directory; stop it, or give this one another "
                        "--data-dir") from None
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        return self

    def release(self) -> None:
        """Let the lock go (closing the file drops it)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
