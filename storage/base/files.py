"""File helpers shared by weights, projections and result files: hashing and atomic writes; and what
says there is no room to write, with a write that asks the filesystem (`probe_write`)."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

_CHUNK = 1 << 20
# (resolved path, mtime_ns, size) -> sha256: a model file is hashed once per process, not per use.
_SHA256_CACHE: dict[tuple[str, int, int], str] = {}


def sha256_file(path: str | os.PathLike[str]) -> str:
    """SHA-256 (lowercase hex) of a file, read in 1 MiB chunks; cached per (path, mtime, size)."""
    p = Path(path).resolve()
    st = p.stat()
    key = (str(p), st.st_mtime_ns, st.st_size)
    if key not in _SHA256_CACHE:
        h = hashlib.sha256()
        with p.open("rb") as f:
            while chunk := f.read(_CHUNK):
                h.update(chunk)
        _SHA256_CACHE[key] = h.hexdigest()
    return _SHA256_CACHE[key]


def fsync_dir(directory: str | os.PathLike[str]) -> None:
    """Make a rename in `directory` durable; a no-op where directories cannot be opened (Windows)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write(target: str | os.PathLike[str], write: Callable[[BinaryIO], None],
                 mode: int = 0o644, before_replace: Callable[[], None] | None = None) -> None:
    """Write `target` so that readers see either the old file or the complete new one.

    A temporary file in the same directory is written by `write`, fsynced, given `mode` (mkstemp makes
    0600, and the service may run as another user than the CLI that wrote the file), renamed over
    `target`, and the directory is fsynced. `before_replace` runs just before the rename (e.g. to drop
    an SQLite WAL that belongs to the file being replaced).
    """
    target = Path(target)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        if before_replace is not None:
            before_replace()
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    fsync_dir(target.parent)


#: What says there is no room to write: the disk full, the user's quota used up, the file-size limit
#: (`ulimit -f`) reached. The one home of these errnos: `storage._common.is_full_error` adds SQLite's own
#: words for them, and `/readyz` tells a full data directory (a warning) from an unwritable one with it.
NO_ROOM_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})


def is_no_room(exc: BaseException) -> bool:
    """True when `exc` is the OS saying there is no room to write (`NO_ROOM_ERRNOS`)."""
    return isinstance(exc, OSError) and exc.errno in NO_ROOM_ERRNOS


def probe_write(path: str | os.PathLike[str], nbytes: int) -> None:
    """Write `nbytes` to a file at `path` (made or truncated), fsync it and remove it: whether the
    filesystem takes a write now. Random bytes, so that a compressing filesystem stores them all. The
    file is removed whatever happens.

    Raises:
        OSError: the write failed (`is_no_room` says whether for lack of room).
    """
    path = Path(path)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            data = memoryview(os.urandom(nbytes))
            while data:
                data = data[os.write(fd, data):]
            os.fsync(fd)  # a network filesystem may say ENOSPC only here
        finally:
            os.close(fd)
    finally:
        with contextlib.suppress(OSError):
            path.unlink()
