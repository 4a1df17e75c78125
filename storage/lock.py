"""One process at a time on a data directory (docs/design/service.md §4.1): an exclusive advisory lock
on the data directory itself, held while a process has the directory's maps open; `<root>/.lock` names
the holder's pid, for the refusal's message only.

Two servers on one directory each believe they are its only writer: they hand out the same seqs (one of
them answers 500 on every learned post) and, creating a map the other holds, would find its files as
leftovers. The lock is `flock(2)` on the directory's own descriptor: the kernel drops it when the holding
process exits however it exits (kill -9 included), so a crash never leaves a stale lock, and no file can
be deleted from under it (an outside test deleted a locked `.lock` file while a server ran: a second
server then took a new one, deleted the first's live map, and acknowledged rows were lost). Where
`fcntl` does not exist (not POSIX), or the file system has no `flock` (some network and FUSE mounts),
there is no lock, with a warning.

A process that finds the lock held waits for it up to a bound (`acquire(wait_s=)`): a restart or a
rolling update starts the new process while the old one is still closing its maps, and the new one
must then start, not give up.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import time
import weakref
from pathlib import Path

from storage._common import StorageError

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]

__all__ = ["DataDirInUse", "DataDirLock"]

log = logging.getLogger("cortexloc.storage")

#: How often a waiting process tries the lock again.
_POLL_S = 0.2
#: `flock` errors that mean the file system has no such lock (not that another process holds it).
_NO_FLOCK = frozenset({errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL})


class DataDirInUse(StorageError):  # noqa: N818 - what it says
    """Another process holds the data directory's lock."""


class DataDirLock:
    """The exclusive lock on one data directory, `path` its `.lock` (the holder's pid; the lock is the
    directory's): `acquire` or raise DataDirInUse; `release` (idempotent)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._fd: int | None = None

    def acquire(self, wait_s: float = 0.0) -> DataDirLock:
        """Take the lock, waiting up to `wait_s` seconds while another process holds it.

        Raises:
            DataDirInUse: another process (or another open registry of this one) still holds it.
        """
        fd = os.open(self.path.parent, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            deadline = time.monotonic() + wait_s
            while fcntl is not None:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if time.monotonic() >= deadline:
                        raise DataDirInUse(
                            f"{self.path.parent} is in use by another cortexloc process (pid "
                            f"{self._holder()}), still after {wait_s:g} s: one process at a time serves a "
                            "data directory; stop it, or give this one another --data-dir") from None
                    time.sleep(_POLL_S)
                except OSError as e:
                    if e.errno not in _NO_FLOCK:
                        raise
                    log.warning("%s: the file system has no flock (%s); no lock: make sure one process "
                                "at a time serves this data directory", self.path.parent, e)
                    break
            # who holds it, for another's refusal; never through a link (it would write where it points)
            with contextlib.suppress(OSError):
                flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0)
                pid = os.open(self.path, flags, 0o644)
                try:
                    os.write(pid, f"{os.getpid()}\n".encode())
                finally:
                    os.close(pid)
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        # a lock whose holder is dropped unclosed (a failed start) goes with it, not with the process
        self._closer = weakref.finalize(self, os.close, fd)
        return self

    def _holder(self) -> str:
        """The pid `.lock` names (what the holder wrote), or `unknown`."""
        try:
            with open(self.path, "rb") as f:
                return f.read(32).decode(errors="replace").strip() or "unknown"
        except OSError:
            return "unknown"

    def release(self) -> None:
        """Let the lock go (closing the file drops it)."""
        if self._fd is not None:
            self._closer()
            self._fd = None
