"""Snapshot directories: create, verify, load, export as tar, import from tar (docs/design/service.md §1.5,
§4.4).

A snapshot is a directory `maps/<map_id>/snapshots/<snapshot_id>/` holding

    map.sqlite     copy of the map database at seq S (SQLite online backup, journal_mode=DELETE)
    memory.npz     the memory's arrays (`TemporalMemory.state_dict(streams=...)`), `np.savez`, no pickle
    manifest.json  written last: ids, S and its observation id, kind, time, parameters, encoder id,
                   projection SHA-256, NumPy/code versions, and size + SHA-256 of every file

It is built in a temporary directory beside its final place and renamed in one step, so the final name
holds a complete snapshot or nothing; and "a snapshot exists iff its manifest verifies" (`verify`).

Export streams a tar (`manifest.json` first, so an importer learns the checksums before the data) whose
exact length `tar_size` gives in advance for `Content-Length`. Import checks every member's name (plain
file names only: no directories, links, absolute paths or `..`) and every checksum before the directory
appears under its final name.

Files outside the snapshot directory (the content-addressed `projection.npy`) can be recorded in the
manifest's `external` section at creation (size + SHA-256, the file itself not copied), exported
alongside, and are then verified on import like the others.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import stat
import tarfile
import tempfile
import uuid
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import IO, Any, BinaryIO

import numpy as np

from models.files import atomic_write, fsync_dir, sha256_file
from storage._common import StorageError, StorageFull, connect, is_full_error, utc_now
from storage.catalog import MAP_ID_RE, SNAPSHOT_ID_RE
from storage.mapstore import MapStore

__all__ = [
    "DB_FILE",
    "FORMAT",
    "MANIFEST_FILE",
    "MEMORY_FILE",
    "FileEntry",
    "Manifest",
    "SnapshotInvalid",
    "TarExport",
    "create_snapshot",
    "export_tar",
    "import_tar",
    "load_memory",
    "new_snapshot_id",
    "remove_stale_temp",
    "scan",
    "tar_size",
    "verify",
]

FORMAT = "cortexloc-snapshot/1"
MANIFEST_FILE = "manifest.json"
DB_FILE = "map.sqlite"
MEMORY_FILE = "memory.npz"
KINDS = ("manual", "auto", "pre-restore")

# A member or file name: one path component, no leading dot (so neither `..` nor hidden temp files).
_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
_TMP_MARK = ".tmp-"
_CHUNK = 1 << 20
_MAX_MANIFEST = 1 << 20  # a manifest is a few KiB; read whole, so bounded
# np.savez(file, *args, allow_pickle=..., **kwds): array names that would collide with its parameters.
_RESERVED_KEYS = frozenset({"file", "allow_pickle"})


class SnapshotInvalid(StorageError):  # noqa: N818 - "the snapshot is invalid", as the spec phrases it
    """A snapshot directory or tar that does not verify (missing file, wrong size or checksum, bad
    manifest, unsafe tar member)."""


@dataclass(frozen=True)
class FileEntry:
    """Size and SHA-256 of one file, as recorded in the manifest."""

    bytes: int
    sha256: str


@dataclass(frozen=True)
class Manifest:
    """A parsed, verified `manifest.json`, plus two facts about the manifest file itself.

    Attributes:
        snapshot_id, map_id, seq, last_observation_id, kind, created_at: the cut and its identity
            (`seq` 0 and `last_observation_id` None for an empty map).
        params, encoder_id, projection_sha256, cell_dtype, schema_version: copied from the map's meta.
        numpy_version, code_version: of the writer (the generator stream is only stable per NumPy build).
        files: name → entry for the files inside the directory.
        external: name → entry for files kept elsewhere (e.g. `projection.npy`), checked on import.
        manifest_sha256: SHA-256 of manifest.json (not stored inside it).
        bytes: total size of the directory's files, manifest included.
    """

    snapshot_id: str
    map_id: str
    seq: int
    last_observation_id: str | None
    kind: str
    created_at: str
    params: dict[str, Any]
    encoder_id: str
    projection_sha256: str
    cell_dtype: str
    schema_version: int
    numpy_version: str
    code_version: str
    files: dict[str, FileEntry]
    external: dict[str, FileEntry] = field(default_factory=dict)
    manifest_sha256: str = ""
    bytes: int = 0

    def to_json_dict(self) -> dict[str, Any]:
        """What manifest.json holds (everything but `manifest_sha256` and `bytes`)."""
        return {
            "format": FORMAT,
            "snapshot_id": self.snapshot_id,
            "map_id": self.map_id,
            "seq": self.seq,
            "last_observation_id": self.last_observation_id,
            "kind": self.kind,
            "created_at": self.created_at,
            "params": self.params,
            "encoder_id": self.encoder_id,
            "projection_sha256": self.projection_sha256,
            "cell_dtype": self.cell_dtype,
            "schema_version": self.schema_version,
            "numpy_version": self.numpy_version,
            "code_version": self.code_version,
            "files": {k: {"bytes": v.bytes, "sha256": v.sha256} for k, v in sorted(self.files.items())},
            "external": {k: {"bytes": v.bytes, "sha256": v.sha256} for k, v in sorted(self.external.items())},
        }


def new_snapshot_id() -> str:
    """A fresh id that sorts by creation time: `YYYYmmddTHHMMSSffffffZ-<8 hex>`."""
    stamp = utc_now().replace("-", "").replace(":", "").replace(".", "")
    return f"{stamp}-{uuid.uuid4().hex[:8]}"


# ---------------------------------------------------------------------- create


def create_snapshot(store: MapStore, memory: Mapping[str, np.ndarray], dest: str | os.PathLike[str], *,
                    kind: str, snapshot_id: str | None = None, code_version: str = "",
                    created_at: str | None = None,
                    external: Mapping[str, str | os.PathLike[str]] | None = None) -> Manifest:
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

    Returns:
        The manifest (with `manifest_sha256` and total `bytes` for the catalog).

    Raises:
        FileExistsError: `dest` exists.
        ValueError: bad kind, object arrays or reserved names in `memory`, unsafe external names.
        StorageFull: the disk filled up (nothing is left behind).
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    dest = Path(dest)
    snapshot_id = snapshot_id or dest.name
    arrays = _check_memory(memory)
    ext = {name: Path(p) for name, p in (external or {}).items()}
    for name in ext:
        if not _SAFE_NAME.match(name) or name in (MANIFEST_FILE, DB_FILE, MEMORY_FILE):
            raise ValueError(f"unsafe or reserved external file name {name!r}")
    if dest.exists():
        raise FileExistsError(f"{dest} exists")
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=dest.parent, prefix=f".{dest.name}{_TMP_MARK}"))
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
            external={name: FileEntry(p.stat().st_size, sha256_file(p)) for name, p in ext.items()})
        body = _manifest_bytes(manifest)
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
    return _with_facts(manifest, hashlib.sha256(body).hexdigest(), total)


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


def _manifest_bytes(m: Manifest) -> bytes:
    return (json.dumps(m.to_json_dict(), indent=2, sort_keys=True) + "\n").encode()


def _with_facts(m: Manifest, sha: str, total: int) -> Manifest:
    return Manifest(**{**m.__dict__, "manifest_sha256": sha, "bytes": total})


# ---------------------------------------------------------------------- verify and load


def _parse_manifest(body: bytes, where: str) -> Manifest:
    """Parse and type-check manifest.json; `SnapshotInvalid` on anything unexpected."""
    try:
        d = json.loads(body)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SnapshotInvalid(f"{where}: manifest is not JSON: {exc}") from exc
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise SnapshotInvalid(f"{where}: not a {FORMAT} manifest")

    def entries(key: str) -> dict[str, FileEntry]:
        raw = d.get(key, {})
        if not isinstance(raw, dict):
            raise SnapshotInvalid(f"{where}: manifest {key!r} is not an object")
        out = {}
        for name, e in raw.items():
            ok = (isinstance(name, str) and _SAFE_NAME.match(name) and name != MANIFEST_FILE
                  and isinstance(e, dict) and isinstance(e.get("bytes"), int) and e["bytes"] >= 0
                  and isinstance(e.get("sha256"), str) and re.fullmatch(r"[0-9a-f]{64}", e["sha256"]))
            if not ok:
                raise SnapshotInvalid(f"{where}: bad manifest entry {key}.{name!r}")
            out[name] = FileEntry(e["bytes"], e["sha256"])
        return out

    try:
        files, external = entries("files"), entries("external")
        if not {DB_FILE, MEMORY_FILE} <= files.keys():
            raise SnapshotInvalid(f"{where}: manifest lacks {DB_FILE} or {MEMORY_FILE}")
        if files.keys() & external.keys():
            raise SnapshotInvalid(f"{where}: a name is both a file and an external file")
        m = Manifest(
            snapshot_id=str(d["snapshot_id"]), map_id=str(d["map_id"]), seq=int(d["seq"]),
            last_observation_id=None if d["last_observation_id"] is None else str(d["last_observation_id"]),
            kind=str(d["kind"]), created_at=str(d["created_at"]), params=dict(d["params"]),
            encoder_id=str(d["encoder_id"]), projection_sha256=str(d["projection_sha256"]),
            cell_dtype=str(d["cell_dtype"]), schema_version=int(d["schema_version"]),
            numpy_version=str(d["numpy_version"]), code_version=str(d.get("code_version", "")),
            files=files, external=external)
    except (KeyError, TypeError, ValueError) as exc:
        raise SnapshotInvalid(f"{where}: manifest field missing or mistyped: {exc}") from exc
    if m.kind not in KINDS or m.seq < 0 or (m.seq > 0) != (m.last_observation_id is not None):
        raise SnapshotInvalid(f"{where}: inconsistent manifest (kind {m.kind!r}, seq {m.seq})")
    # The ids and the projection's checksum become directory and file names on import.
    if not MAP_ID_RE.match(m.map_id):
        raise SnapshotInvalid(f"{where}: map_id {m.map_id!r} must match {MAP_ID_RE.pattern}")
    if not SNAPSHOT_ID_RE.match(m.snapshot_id):
        raise SnapshotInvalid(f"{where}: snapshot_id {m.snapshot_id!r} must match {SNAPSHOT_ID_RE.pattern}")
    if not re.fullmatch(r"[0-9a-f]{64}", m.projection_sha256):
        raise SnapshotInvalid(f"{where}: projection_sha256 is not a SHA-256")
    return m


def _digest(path: Path) -> str:
    # Deliberately not models.files.sha256_file: its cache is keyed by (path, mtime, size), so bit rot
    # or a same-size overwrite within one clock tick would be answered from the cache. Verification
    # must read the bytes.
    with path.open("rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def verify(directory: str | os.PathLike[str]) -> Manifest:
    """Check a snapshot directory against its manifest: every listed file present, regular, same size
    and same SHA-256 (all bytes re-read).

    Returns:
        The manifest, with `manifest_sha256` and `bytes`.

    Raises:
        SnapshotInvalid: anything missing or different.
    """
    directory = Path(directory)
    try:
        body = (directory / MANIFEST_FILE).read_bytes()
    except OSError as exc:
        raise SnapshotInvalid(f"{directory}: no readable {MANIFEST_FILE}: {exc}") from exc
    m = _parse_manifest(body, str(directory))
    for name, entry in m.files.items():
        path = directory / name
        try:
            st = path.lstat()
        except OSError as exc:
            raise SnapshotInvalid(f"{directory}: {name} missing") from exc
        if not stat.S_ISREG(st.st_mode):
            raise SnapshotInvalid(f"{directory}: {name} is not a regular file")
        if st.st_size != entry.bytes:
            raise SnapshotInvalid(f"{directory}: {name} has {st.st_size} bytes, manifest says {entry.bytes}")
        if _digest(path) != entry.sha256:
            raise SnapshotInvalid(f"{directory}: {name} checksum mismatch")
    total = sum(e.bytes for e in m.files.values()) + len(body)
    return _with_facts(m, hashlib.sha256(body).hexdigest(), total)


def load_memory(directory: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """The arrays of `memory.npz`, loaded with `allow_pickle=False` (call `verify` first)."""
    with np.load(Path(directory) / MEMORY_FILE, allow_pickle=False) as z:
        return {name: z[name] for name in z.files}


def scan(parent: str | os.PathLike[str]) -> list[tuple[Path, Manifest]]:
    """Every snapshot directory under `parent` that verifies, newest `created_at` first.

    For recovery when the catalog and the directory disagree (a crash between the rename and the
    registration); temporary directories and invalid snapshots are skipped.
    """
    found = []
    parent = Path(parent)
    if not parent.is_dir():
        return []
    for d in parent.iterdir():
        if d.name.startswith(".") or not d.is_dir():
            continue
        with contextlib.suppress(SnapshotInvalid):
            found.append((d, verify(d)))
    found.sort(key=lambda t: (t[1].created_at, t[1].seq), reverse=True)
    return found


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
            if d.name.startswith(".") and _TMP_MARK in d.name and d.is_dir() and not d.is_symlink():
                shutil.rmtree(d, ignore_errors=True)
                removed.append(d)
    return removed


# ---------------------------------------------------------------------- tar


class TarExport:
    """A snapshot opened for export as an uncompressed tar: `manifest.json`, its files, then `extra`.

    Opening holds one descriptor per member and, by default, verifies every file the manifest lists
    (regular, same size, same SHA-256, all bytes re-read from those descriptors), `extra` files too
    where the manifest's `external` section records them. The tar is then generated from the same
    descriptors chunk by chunk (`chunks`), with no copy anywhere: what is sent is what was verified,
    even if the snapshot directory is pruned meanwhile (an unlinked file stays readable while open).
    `close` (or leaving the `with` block) releases every descriptor.

    Layout (GNU, as `tarfile` writes it): per member a 512-byte header and the data padded to 512; two
    zero blocks; the whole padded to a 10,240-byte record. Names are short plain names, so no long-name
    or pax headers appear, and GNU format stores sizes of 8 GiB and more without extra headers.

    Args:
        directory: a snapshot directory.
        extra: member name -> path of files to add, e.g. `{"projection.npy": path}`.
        verify: check the checksums on opening (False: sizes only, the importer verifies).

    Attributes:
        manifest: the parsed manifest.
        size: exact byte length of the tar (for `Content-Length`).

    Raises:
        SnapshotInvalid: unreadable or inconsistent manifest, a missing file, a size or checksum that
            differs from the manifest.
        ValueError: an unsafe or duplicate `extra` name.
    """

    def __init__(self, directory: str | os.PathLike[str],
                 extra: Mapping[str, str | os.PathLike[str]] | None = None, *, verify: bool = True) -> None:
        directory = Path(directory)
        self._held: list[BinaryIO] = []  # every descriptor opened, closed by `close`
        self._files: list[tuple[tarfile.TarInfo, BinaryIO]] = []
        try:
            self._open(directory, extra or {}, verify)
        except BaseException:
            self.close()
            raise

    def _open(self, directory: Path, extra: Mapping[str, str | os.PathLike[str]], verify: bool) -> None:
        manifest_file = self._hold(directory / MANIFEST_FILE, f"{directory}: no readable {MANIFEST_FILE}")
        body = manifest_file.read()
        manifest_file.seek(0)
        self.manifest = _parse_manifest(body, str(directory))
        m = self.manifest
        for name in extra:
            if not _SAFE_NAME.match(name) or name == MANIFEST_FILE or name in m.files:
                raise ValueError(f"unsafe or duplicate extra member name {name!r}")
        # (member name, where it is for messages, open file, what the manifest records or None)
        here = str(directory)
        members = [(MANIFEST_FILE, here, manifest_file, FileEntry(len(body), ""))]
        members += [(name, here, self._hold(directory / name, f"{here}: {name} missing"), entry)
                    for name, entry in sorted(m.files.items())]
        members += [(name, str(src), self._hold(Path(src), f"{src}: {name} missing"), m.external.get(name))
                    for name, src in extra.items()]
        mtime = int(datetime.fromisoformat(m.created_at.replace("Z", "+00:00")).timestamp())
        for name, where, f, entry in members:
            st = os.fstat(f.fileno())
            if not stat.S_ISREG(st.st_mode):
                raise SnapshotInvalid(f"{where}: {name} is not a regular file")
            if entry is not None and st.st_size != entry.bytes:
                raise SnapshotInvalid(f"{where}: {name} has {st.st_size} bytes, manifest says {entry.bytes}")
            if verify and entry is not None and entry.sha256:
                if hashlib.file_digest(f, "sha256").hexdigest() != entry.sha256:
                    raise SnapshotInvalid(f"{where}: {name} checksum mismatch")
                f.seek(0)
            info = tarfile.TarInfo(name)
            info.size, info.mtime, info.mode = st.st_size, mtime, 0o644
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            self._files.append((info, f))
        self._members_bytes = sum(tarfile.BLOCKSIZE + -(-info.size // tarfile.BLOCKSIZE) * tarfile.BLOCKSIZE
                                  for info, _ in self._files)
        end = self._members_bytes + 2 * tarfile.BLOCKSIZE
        self.size = -(-end // tarfile.RECORDSIZE) * tarfile.RECORDSIZE

    def _hold(self, path: Path, missing: str) -> BinaryIO:
        try:
            f = path.open("rb")
        except OSError as exc:
            raise SnapshotInvalid(f"{missing} ({exc.strerror or exc})") from exc
        self._held.append(f)
        return f

    def chunks(self, chunk_bytes: int = _CHUNK) -> Iterator[bytes]:
        """The tar, in pieces of at most `chunk_bytes` (headers and padding are separate pieces).

        Raises:
            SnapshotInvalid: a file got shorter since it was opened (the tar would disagree with `size`).
        """
        for info, f in self._files:
            yield info.tobuf(tarfile.GNU_FORMAT, tarfile.ENCODING, "surrogateescape")
            remaining = info.size
            while remaining:
                chunk = f.read(min(chunk_bytes, remaining))
                if not chunk:
                    raise SnapshotInvalid(f"{f.name}: shorter than when the export began")
                remaining -= len(chunk)
                yield chunk
            if info.size % tarfile.BLOCKSIZE:
                yield bytes(tarfile.BLOCKSIZE - info.size % tarfile.BLOCKSIZE)
        yield bytes(self.size - self._members_bytes)  # the two end-of-archive blocks, the record padding

    def close(self) -> None:
        """Release every descriptor (idempotent)."""
        for f in self._held:
            f.close()
        self._held.clear()

    def __enter__(self) -> TarExport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def tar_size(directory: str | os.PathLike[str], extra: Mapping[str, str | os.PathLike[str]] | None = None
             ) -> int:
    """Exact byte length of what `export_tar` writes (see `TarExport` for the layout)."""
    with TarExport(directory, extra, verify=False) as export:
        return export.size


def export_tar(directory: str | os.PathLike[str], fileobj: IO[bytes],
               extra: Mapping[str, str | os.PathLike[str]] | None = None, *, verify: bool = False) -> int:
    """Write a snapshot as an uncompressed tar to `fileobj` (which need not be seekable); see `TarExport`.

    Args:
        directory: a snapshot directory.
        fileobj: where the tar goes (a file, a pipe).
        extra: member name → path of files to add, e.g. `{"projection.npy": path}`.
        verify: check every checksum first (by default only sizes: the importer verifies checksums).

    Returns:
        Bytes written (= `tar_size(directory, extra)`).
    """
    n = 0
    with TarExport(directory, extra, verify=verify) as export:
        for chunk in export.chunks():
            fileobj.write(chunk)
            n += len(chunk)
    return n


def import_tar(fileobj: BinaryIO, dest: str | os.PathLike[str], *,
               allow_unlisted: tuple[str, ...] = ("projection.npy",),
               max_bytes: int | None = None, check: Callable[[Manifest], None] | None = None) -> Manifest:
    """Unpack a snapshot tar into the new directory `dest`, verifying everything on the way.

    The tar must begin with `manifest.json` (as `export_tar` writes it): it is parsed first (ids and
    names checked), the total it declares is held against `max_bytes`, and `check` may refuse it,
    all before anything is written. Every further member must be a regular file with a plain name (no
    `/`, no leading `.`, so no `..` or absolute path; links, directories and devices are refused),
    appear once, and be listed in the manifest with the size its tar header declares, or be named in
    `allow_unlisted` (a projection exported from a snapshot that did not record it; the caller verifies
    it, e.g. with `models.frontend.slsbh.load_projection` against `projection_sha256`). Sizes come from the
    tar headers, so a member is refused before its data is read, and a compressed bomb costs no disk.
    Each file is hashed while it is written into a temporary directory beside `dest`; only when every
    listed file is there with its SHA-256 is the directory renamed to `dest`.

    (`tarfile`'s extraction filters, e.g. `filter="data"`, would still accept subdirectories, links
    inside the tree and unlisted names; this format needs less, so it checks for exactly that.)

    Args:
        fileobj: the tar stream (plain or compressed; read sequentially).
        dest: the directory to create (must not exist).
        allow_unlisted: member names accepted without a manifest entry.
        max_bytes: refuse tars whose members total more (bounds disk use of an import or upload).
        check: called with the parsed manifest before anything is written; raises to refuse it.

    Returns:
        The manifest (with `manifest_sha256` and `bytes` of the snapshot files proper).

    Raises:
        SnapshotInvalid: unsafe member, unknown or missing file, size or checksum mismatch, too large,
            bad tar.
        FileExistsError: `dest` exists.
    """
    dest = Path(dest)
    if dest.exists():
        raise FileExistsError(f"{dest} exists")
    tmp: Path | None = None
    try:
        got: dict[str, FileEntry] = {}
        m: Manifest | None = None
        body = b""
        listed: dict[str, FileEntry] = {}
        total = 0
        try:
            with tarfile.open(fileobj=fileobj, mode="r|*") as tar:
                for member in tar:
                    name = member.name
                    if not member.isreg():
                        raise SnapshotInvalid(f"tar member {name!r} is not a regular file")
                    if not _SAFE_NAME.match(name):
                        raise SnapshotInvalid(f"tar member name {name!r} is not a plain file name")
                    if name in got or (m is not None and name == MANIFEST_FILE):
                        raise SnapshotInvalid(f"tar member {name!r} appears twice")
                    src = tar.extractfile(member)
                    assert src is not None  # a regular file always has a data stream
                    if m is None:
                        if name != MANIFEST_FILE:
                            raise SnapshotInvalid(f"the tar must begin with {MANIFEST_FILE}, not {name!r}")
                        if member.size > _MAX_MANIFEST:
                            raise SnapshotInvalid(f"{MANIFEST_FILE} has {member.size} bytes")
                        body = src.read()
                        m = _parse_manifest(body, "tar")
                        listed = {**m.files, **m.external}
                        total = len(body) + sum(e.bytes for e in listed.values())
                        if max_bytes is not None and total > max_bytes:
                            raise SnapshotInvalid(f"the manifest declares {total} bytes, more than the "
                                                  f"{max_bytes} allowed")
                        if check is not None:
                            check(m)
                        dest.parent.mkdir(parents=True, exist_ok=True)
                        tmp = Path(tempfile.mkdtemp(dir=dest.parent, prefix=f".{dest.name}{_TMP_MARK}"))
                        atomic_write(tmp / MANIFEST_FILE, lambda f, b=body: f.write(b))
                        continue
                    entry = listed.get(name)
                    if entry is None:
                        if name not in allow_unlisted:
                            raise SnapshotInvalid(f"tar member {name!r} is not in the manifest")
                        total += member.size
                    elif member.size != entry.bytes:
                        raise SnapshotInvalid(f"tar member {name}: {member.size} bytes, the manifest says "
                                              f"{entry.bytes}")
                    if max_bytes is not None and total > max_bytes:
                        raise SnapshotInvalid(f"tar holds more than {max_bytes} bytes")
                    assert tmp is not None
                    got[name] = _write_hashed(src, tmp / name)
        except (tarfile.TarError, EOFError, OSError) as exc:
            if is_full_error(exc):
                raise StorageFull(str(exc)) from exc
            raise SnapshotInvalid(f"unreadable tar: {exc}") from exc
        if m is None or tmp is None:
            raise SnapshotInvalid(f"tar has no {MANIFEST_FILE}")
        for name, entry in listed.items():
            if name in m.files and name not in got:
                raise SnapshotInvalid(f"tar lacks {name}")
            if name in got and got[name] != entry:
                raise SnapshotInvalid(f"tar member {name}: checksum differs from the manifest")
        fsync_dir(tmp)
        if dest.exists():
            raise FileExistsError(f"{dest} exists")
        os.rename(tmp, dest)
    except BaseException:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        raise
    fsync_dir(dest.parent)
    size = sum(e.bytes for e in m.files.values()) + len(body)
    return _with_facts(m, hashlib.sha256(body).hexdigest(), size)


def _write_hashed(src: IO[bytes], path: Path) -> FileEntry:
    """Copy a stream to a new file (exclusive create), fsync it, and return its size and SHA-256."""
    h = hashlib.sha256()
    n = 0
    with path.open("xb") as out:
        for chunk in _chunks(src):
            h.update(chunk)
            out.write(chunk)
            n += len(chunk)
        out.flush()
        os.fsync(out.fileno())
    return FileEntry(n, h.hexdigest())


def _chunks(src: IO[bytes]) -> Iterator[bytes]:
    while chunk := src.read(_CHUNK):
        yield chunk
