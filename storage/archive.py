"""A snapshot as an uncompressed tar: export (streamed, exact length in advance) and checked import
(docs/design/service.md §1.5, §4.4).

Export (`TarExport`) streams `manifest.json` first, so an importer learns the checksums before the data,
and knows the tar's exact length in advance for `Content-Length`. Import checks every member (the standard
library's `data` extraction filter, then this format's own rules) and every checksum before the
directory appears under its final name.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import stat
import tarfile
import tempfile
from collections.abc import Callable, Iterator, Mapping
from datetime import datetime
from pathlib import Path
from typing import IO, BinaryIO

from storage._common import StorageFull, is_full_error
from storage.base.files import atomic_write, fsync_dir
from storage.manifest import (
    MANIFEST_FILE,
    PROJECTION_FILE,
    SAFE_NAME,
    TMP_MARK,
    FileEntry,
    Manifest,
    SnapshotInvalid,
    parse_manifest,
    with_facts,
)

__all__ = ["TarExport", "import_tar"]

_CHUNK = 1 << 20
_MAX_MANIFEST = 1 << 20  # a manifest is a few KiB; read whole, so bounded


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
        extra: member name -> path of files to add, e.g. `{PROJECTION_FILE: path}`.
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
        self.manifest = parse_manifest(body, str(directory))
        m = self.manifest
        for name in extra:
            if not SAFE_NAME.fullmatch(name) or name == MANIFEST_FILE or name in m.files:
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


def import_tar(fileobj: BinaryIO, dest: str | os.PathLike[str], *,
               allow_unlisted: tuple[str, ...] = (PROJECTION_FILE,),
               max_bytes: int | None = None, check: Callable[[Manifest], None] | None = None) -> Manifest:
    """Unpack a snapshot tar into the new directory `dest`, verifying everything on the way.

    The tar must begin with `manifest.json` (as `TarExport` writes it): it is parsed first (ids and
    names checked), the total it declares is held against `max_bytes`, and `check` may refuse it,
    all before anything is written. Every further member must be a regular file with a plain name (no
    `/`, no leading `.`, so no `..` or absolute path; links, directories and devices are refused),
    appear once, and be listed in the manifest with the size its tar header declares, or be named in
    `allow_unlisted` (a projection exported from a snapshot that did not record it; the caller verifies
    it, e.g. with `models.frontend.slsbh.load_projection` against `projection_sha256`). Sizes come from the
    tar headers, so a member is refused before its data is read, and a compressed bomb costs no disk.
    Each file is hashed while it is written into a temporary directory beside `dest`; only when every
    listed file is there with its SHA-256 is the directory renamed to `dest`.

    Members first pass `tarfile.data_filter` (`..`, devices, links out of `dest`); it would still
    accept subdirectories, links inside the tree, absolute names (stripped) and unlisted names, which
    this format refuses on its own.

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
                    # The standard library's `data` filter refuses names that leave `dest`, devices,
                    # and links to absolute paths or out of `dest`. This format allows less than the
                    # filter does (it passes subdirectories, links inside the tree, hidden and
                    # unlisted names, and strips a leading `/` instead of refusing it), so the rest
                    # stays ours: regular files with a plain name only, each once, the manifest
                    # first, and sizes held to what the manifest declares.
                    try:
                        tarfile.data_filter(member, str(dest))
                    except tarfile.FilterError as exc:
                        raise SnapshotInvalid(f"tar member {name!r} refused: {exc}") from exc
                    if not member.isreg():
                        raise SnapshotInvalid(f"tar member {name!r} is not a regular file")
                    if not SAFE_NAME.fullmatch(name):
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
                        m = parse_manifest(body, "tar")
                        listed = {**m.files, **m.external}
                        total = len(body) + sum(e.bytes for e in listed.values())
                        if max_bytes is not None and total > max_bytes:
                            raise SnapshotInvalid(f"the manifest declares {total} bytes, more than the "
                                                  f"{max_bytes} allowed")
                        if check is not None:
                            check(m)
                        dest.parent.mkdir(parents=True, exist_ok=True)
                        tmp = Path(tempfile.mkdtemp(dir=dest.parent, prefix=f".{dest.name}{TMP_MARK}"))
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
    return with_facts(m, hashlib.sha256(body).hexdigest(), size)


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
