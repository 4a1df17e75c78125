"""Snapshot directories: create and load; with `storage.manifest` (format, verification) and
`storage.archive` (tar export and checked import), whose names this module re-exports
(docs/design/service.md §1.5, §4.4).

A snapshot is a directory `maps/<map_id>/snapshots/<snapshot_id>/` holding `map.sqlite`, `memory.npz`
and `manifest.json` (see `storage.manifest`). It is built in a temporary directory beside its final
place and renamed in one step, so the final name holds a complete snapshot or nothing; and "a snapshot
exists iff its manifest verifies" (`verify`).
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import shutil
import struct
import tempfile
import uuid
import zipfile
import zlib
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

import numpy as np

from storage._common import StorageFull, connect, is_full_error, utc_now
from storage.archive import TarExport, import_tar
from storage.base.files import atomic_write, fsync_dir, sha256_file
from storage.catalog import SNAPSHOT_KINDS, Lineage
from storage.manifest import (
    DB_FILE,
    FORMAT,
    MANIFEST_FILE,
    MEMORY_FILE,
    PROJECTION_FILE,
    SAFE_NAME,
    TMP_MARK,
    FileEntry,
    Manifest,
    SnapshotInvalid,
    manifest_bytes,
    verify,
    with_facts,
)
from storage.mapstore import MapStore

__all__ = [
    "DB_FILE",
    "FORMAT",
    "MANIFEST_FILE",
    "MEMORY_FILE",
    "PROJECTION_FILE",
    "FileEntry",
    "Manifest",
    "SnapshotInvalid",
    "TarExport",
    "check_memory",
    "create_snapshot",
    "import_tar",
    "load_memory",
    "new_snapshot_id",
    "remove_stale_temp",
    "verify",
]

# np.savez(file, *args, allow_pickle=..., **kwds): array names that would collide with its parameters.
_RESERVED_KEYS = frozenset({"file", "allow_pickle"})


def new_snapshot_id() -> str:
    """A fresh id that sorts by creation time: `YYYYmmddTHHMMSSffffffZ-<8 hex>`."""
    stamp = utc_now().replace("-", "").replace(":", "").replace(".", "")
    return f"{stamp}-{uuid.uuid4().hex[:8]}"


def create_snapshot(store: MapStore, memory: Mapping[str, np.ndarray], dest: str | os.PathLike[str], *,
                    kind: str, snapshot_id: str | None = None, code_version: str = "",
                    created_at: str | None = None,
                    external: Mapping[str, str | os.PathLike[str]] | None = None,
                    lineage: Lineage | None = None) -> Manifest:
    """Write a snapshot directory at `dest` (docs/design/service.md §4.4), to be called by the map's writer.

    Order: temporary directory beside `dest` → `map.sqlite` by online backup → `memory.npz` → fsync →
    `manifest.json` last → fsync the directory → rename to `dest` → fsync the parent. The cut's seq and
    observation id are read from the *copy*, so the manifest describes exactly what was copied.

    Args:
        store: the map's open store.
        memory: arrays of the memory (e.g. `tm.state_dict(streams=contexts)`); no object arrays.
        dest: the final directory (must not exist); usually `.../snapshots/<snapshot_id>`.
        kind: `manual`, `auto` or `pre-restore`.
        snapshot_id: defaults to `dest`'s name.
        code_version: the service's version string, recorded for diagnosis.
        created_at: ISO 8601 UTC (now by default).
        external: name → path of files that belong with the snapshot but live elsewhere (the
            projection), recorded by size and SHA-256 only.
        lineage: the map's creation, counts and id marks (`storage.catalog.Lineage`), recorded so that a
            move between shards keeps the map's epoch and never hands out an id again.

    Returns:
        The manifest (with `manifest_sha256` and total `bytes` for the catalog).

    Raises:
        FileExistsError: `dest` exists.
        ValueError: bad kind, object arrays or reserved names in `memory`, unsafe external names.
        StorageFull: the disk filled up (nothing is left behind).
    """
    if kind not in SNAPSHOT_KINDS:
        raise ValueError(f"kind must be one of {SNAPSHOT_KINDS}, got {kind!r}")
    dest = Path(dest)
    snapshot_id = snapshot_id or dest.name
    arrays = _check_memory(memory)
    ext = {name: Path(p) for name, p in (external or {}).items()}
    for name in ext:
        if not SAFE_NAME.fullmatch(name) or name in (MANIFEST_FILE, DB_FILE, MEMORY_FILE):
            raise ValueError(f"unsafe or reserved external file name {name!r}")
    if dest.exists():
        raise FileExistsError(f"{dest} exists")
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=dest.parent, prefix=f".{dest.name}{TMP_MARK}"))
    try:
        store.backup_to(tmp / DB_FILE)
        seq, last_id = _last_observation(tmp / DB_FILE)
        # atomic_write fsyncs the file (and the directory); allow_pickle=False makes object arrays fail.
        atomic_write(tmp / MEMORY_FILE, lambda f: np.savez(f, allow_pickle=False, **arrays))
        files = {name: FileEntry((tmp / name).stat().st_size, sha256_file(tmp / name))
                 for name in (DB_FILE, MEMORY_FILE)}
        meta = store.meta
        manifest = Manifest(
            snapshot_id=snapshot_id, map_id=meta.map_id, seq=seq, last_observation_id=last_id, kind=kind,
            created_at=created_at or utc_now(), params=meta.params, encoder_id=meta.encoder_id,
            projection_sha256=meta.projection_sha256, cell_dtype=meta.cell_dtype,
            schema_version=meta.schema_version, numpy_version=np.__version__, code_version=code_version,
            files=files,
            external={name: FileEntry(p.stat().st_size, sha256_file(p)) for name, p in ext.items()},
            lineage=lineage)
        body = manifest_bytes(manifest)
        atomic_write(tmp / MANIFEST_FILE, lambda f: f.write(body))
        fsync_dir(tmp)
        if dest.exists():  # os.rename would silently replace an empty directory
            raise FileExistsError(f"{dest} exists")
        os.rename(tmp, dest)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if is_full_error(exc) and not isinstance(exc, StorageFull):
            raise StorageFull(str(exc)) from exc
        raise
    fsync_dir(dest.parent)
    total = sum(e.bytes for e in files.values()) + len(body)
    return with_facts(manifest, hashlib.sha256(body).hexdigest(), total)


def _check_memory(memory: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    arrays: dict[str, np.ndarray] = {}
    for key, value in memory.items():
        if not isinstance(key, str) or not key or key in _RESERVED_KEYS or "/" in key:
            raise ValueError(f"memory array name {key!r} is not allowed")
        a = np.asarray(value)
        if a.dtype.hasobject:
            # Object arrays would need pickle to save and to load; snapshots never use pickle.
            raise ValueError(f"memory array {key!r} has dtype {a.dtype}; object arrays need pickle")
        arrays[key] = a
    return arrays


def _last_observation(db: Path) -> tuple[int, str | None]:
    # Read-only: opening the copy read-write in WAL mode would create -wal/-shm files in the snapshot.
    conn = connect(db, readonly=True)
    try:
        row = conn.execute(
            "SELECT seq, observation_id FROM observations ORDER BY seq DESC LIMIT 1").fetchone()
    finally:
        conn.close()
    return (0, None) if row is None else (int(row[0]), str(row[1]))


def check_memory(directory: str | os.PathLike[str], *, known: Callable[[str], bool]) -> int:
    """Check `memory.npz` without reading its data (docs/design/service.md §4.4). A snapshot is untrusted
    input (an imported one comes from elsewhere), and its checksums say nothing of what its members
    inflate to; `np.savez`, its only writer, stores every member uncompressed, so one that is compressed
    (or encrypted) is refused, and what the arrays hold is then at most the file's own size: each member
    a `.npy` of a name `known` takes, once, whose header (shape, dtype) declares no more than the member
    holds. The zip's directory, read whole when it is opened, is held to 65,534 entries (no ZIP64
    directory: a memory writes a few dozen arrays a stream).

    Returns:
        The bytes the arrays hold.

    Raises:
        SnapshotInvalid: any of the above.
    """
    with _open_memory(Path(directory) / MEMORY_FILE) as z:
        return sum(info.file_size for _, info in _members(z, known))


def load_memory(directory: str | os.PathLike[str], *, known: Callable[[str], bool]) -> dict[str, np.ndarray]:
    """The arrays of `memory.npz`, every member checked first as `check_memory` does (call `verify` first).
    No pickle. Raises SnapshotInvalid."""
    with _open_memory(Path(directory) / MEMORY_FILE) as z:
        members = _members(z, known)
        try:
            out = {}
            for name, info in members:
                with z.open(info) as f:
                    out[name] = np.lib.format.read_array(f, allow_pickle=False)
        except _UNREADABLE as exc:
            raise SnapshotInvalid(f"{MEMORY_FILE}: unreadable: {exc}") from exc
    return out


# What a damaged or hostile zip raises while it is read (a truncated or corrupt member, a bad header).
_UNREADABLE = (zipfile.BadZipFile, zlib.error, EOFError, ValueError, NotImplementedError, RuntimeError,
               struct.error)
#: The end of a zip's central directory: its signature, and the bytes it may end with (a comment).
_EOCD, _EOCD_TAIL = b"PK\x05\x06", 22 + 65535


@contextlib.contextmanager
def _open_memory(path: Path) -> Iterator[zipfile.ZipFile]:
    """The zip, opened once its directory's entry count (from its end record, read first) is below
    0xFFFF: zipfile reads the whole directory at open, an object of a few hundred bytes per entry for as
    few as 46 on disk."""
    try:
        with path.open("rb") as f:
            f.seek(max(path.stat().st_size - _EOCD_TAIL, 0))
            tail = f.read()
        at = tail.rfind(_EOCD)
        entries = struct.unpack("<H", tail[at + 10:at + 12])[0] if at >= 0 else None
    except (OSError, struct.error) as exc:
        raise SnapshotInvalid(f"{MEMORY_FILE}: unreadable: {exc}") from exc
    if entries is None or entries == 0xFFFF:
        raise SnapshotInvalid(f"{MEMORY_FILE}: no zip directory a memory writes (entries: {entries})")
    try:
        z = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, ValueError) as exc:
        raise SnapshotInvalid(f"{MEMORY_FILE}: not a zip archive: {exc}") from exc
    with z:
        yield z


def _members(z: zipfile.ZipFile, known: Callable[[str], bool]) -> list[tuple[str, zipfile.ZipInfo]]:
    """(array name, member) of each member of `memory.npz`, checked (`check_memory`) from the zip's
    directory and each `.npy` header, no array data read."""
    out: list[tuple[str, zipfile.ZipInfo]] = []
    seen: set[str] = set()
    for info in z.infolist():
        member = info.filename
        name = member.removesuffix(".npy")
        where = f"{MEMORY_FILE}: member {member!r}"
        if name == member or not known(name):
            raise SnapshotInvalid(f"{where} is no array of a map's memory")
        if name in seen:
            raise SnapshotInvalid(f"{where} appears twice")
        seen.add(name)
        if info.flag_bits & 0x1 or info.compress_type != zipfile.ZIP_STORED \
                or info.compress_size != info.file_size:
            raise SnapshotInvalid(f"{where} is compressed (method {info.compress_type}) or encrypted: a "
                                  "memory's members are stored as they are")
        try:
            with z.open(info) as f:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    shape, _, dtype = np.lib.format.read_array_header_1_0(f)
                elif version == (2, 0):
                    shape, _, dtype = np.lib.format.read_array_header_2_0(f)
                else:
                    raise ValueError(f".npy format version {version}")
        except _UNREADABLE as exc:
            raise SnapshotInvalid(f"{where} unreadable: {exc}") from exc
        if any(d < 0 for d in shape):
            raise SnapshotInvalid(f"{where} declares the shape {shape}")
        if dtype.hasobject:
            raise SnapshotInvalid(f"{where} holds objects (dtype {dtype}): pickle")
        if math.prod(shape) * dtype.itemsize > info.file_size:  # read_array would allocate it first
            raise SnapshotInvalid(f"{where} declares {dtype}{shape}, more than its {info.file_size} bytes")
        out.append((name, info))
    return out


def remove_stale_temp(parent: str | os.PathLike[str]) -> list[Path]:
    """Delete temporary directories left under `parent` by an interrupted create or import.

    Only call while no snapshot is being written there (at startup, before the map's writer runs).

    Returns:
        The directories removed.
    """
    parent = Path(parent)
    removed = []
    if parent.is_dir():
        for d in parent.iterdir():
            if d.name.startswith(".") and TMP_MARK in d.name and d.is_dir() and not d.is_symlink():
                shutil.rmtree(d, ignore_errors=True)
                removed.append(d)
    return removed

