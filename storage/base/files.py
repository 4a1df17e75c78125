"""File helpers shared by weights, projections and result files: hashing and atomic writes."""

from __future__ import annotations

import contextlib
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
