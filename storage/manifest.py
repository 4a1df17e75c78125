"""A snapshot directory's format: its file names, `manifest.json`, and verification against it
(docs/design/service.md §4.4).

    map.sqlite     copy of the map database at seq S (SQLite online backup, journal_mode=DELETE)
    memory.npz     the memory's arrays (`TemporalMemory.state_dict(streams=...)`), `np.savez`, no pickle
    manifest.json  written last: ids, S and its observation id, kind, time, parameters, encoder id,
                   projection SHA-256, NumPy/code versions, size + SHA-256 of every file, and the
                   map's lineage (its epoch's parts and id marks, `storage.catalog.Lineage`)

"A snapshot exists iff its manifest verifies" (`verify`). Files outside the directory (the
content-addressed `projection.npy`) can be recorded in the manifest's `external` section (size +
SHA-256, the file itself not copied) and are verified on import like the others.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from storage._common import StorageError
from storage.catalog import MAP_ID_RE, SNAPSHOT_ID_RE, SNAPSHOT_KINDS, Lineage
from storage.layout import DB_FILE, TMP_MARK

__all__ = [
    "DB_FILE",
    "FORMAT",
    "MANIFEST_FILE",
    "MEMORY_FILE",
    "PROJECTION_FILE",
    "SAFE_NAME",
    "TMP_MARK",
    "FileEntry",
    "Manifest",
    "SnapshotInvalid",
    "manifest_bytes",
    "parse_manifest",
    "verify",
    "with_facts",
]

FORMAT = "cortexloc-snapshot/1"
MANIFEST_FILE = "manifest.json"
MEMORY_FILE = "memory.npz"
#: The sLSBH projection as a member of an exported tar; a snapshot directory records only its size and
#: checksum (`external`): the file itself is content-addressed under `projections/`.
PROJECTION_FILE = "projection.npy"

#: A member or file name: one path component, no leading dot (so neither `..` nor hidden temp files).
#: Use `fullmatch`: its `$` also matches before a last newline.
SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
_SHA256 = re.compile(r"[0-9a-f]{64}")


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
        lineage: the map's creation, restore and rewrite counts and id marks when the snapshot was taken
            (`storage.catalog.Lineage`); None in a manifest written before it was recorded.
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
    lineage: Lineage | None = None
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
            **({} if self.lineage is None else {"lineage": dict(self.lineage.__dict__)}),
        }



def manifest_bytes(m: Manifest) -> bytes:
    """What manifest.json holds, as written: sorted keys, indented, one final newline."""
    return (json.dumps(m.to_json_dict(), indent=2, sort_keys=True) + "\n").encode()


def with_facts(m: Manifest, sha: str, total: int) -> Manifest:
    """`m` with the two facts about the manifest file itself (its SHA-256, the snapshot's bytes)."""
    return Manifest(**{**m.__dict__, "manifest_sha256": sha, "bytes": total})


def parse_manifest(body: bytes, where: str) -> Manifest:
    """Parse and type-check manifest.json; `SnapshotInvalid` on anything unexpected."""
    try:
        d = json.loads(body)
    # ValueError: not UTF-8, not JSON, an integer past Python's 4,300 digits; RecursionError: nested
    # deeper than the parser recurses (a tar is outside input: each is a bad manifest, not a traceback)
    except (ValueError, RecursionError) as exc:
        raise SnapshotInvalid(f"{where}: manifest is not JSON: {exc}") from exc
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise SnapshotInvalid(f"{where}: not a {FORMAT} manifest")

    def entries(key: str) -> dict[str, FileEntry]:
        raw = d.get(key, {})
        if not isinstance(raw, dict):
            raise SnapshotInvalid(f"{where}: manifest {key!r} is not an object")
        out = {}
        for name, e in raw.items():
            ok = (isinstance(name, str) and SAFE_NAME.fullmatch(name) and name != MANIFEST_FILE
                  and isinstance(e, dict) and isinstance(e.get("bytes"), int) and e["bytes"] >= 0
                  and isinstance(e.get("sha256"), str) and _SHA256.fullmatch(e["sha256"]))
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
            files=files, external=external, lineage=_lineage(d.get("lineage"), where))
    except (KeyError, TypeError, ValueError) as exc:
        raise SnapshotInvalid(f"{where}: manifest field missing or mistyped: {exc}") from exc
    if m.kind not in SNAPSHOT_KINDS or m.seq < 0 or (m.seq > 0) != (m.last_observation_id is not None):
        raise SnapshotInvalid(f"{where}: inconsistent manifest (kind {m.kind!r}, seq {m.seq})")
    # The ids and the projection's checksum become directory and file names on import.
    if not MAP_ID_RE.fullmatch(m.map_id):  # fullmatch: `$` also matches before a last newline
        raise SnapshotInvalid(f"{where}: map_id {m.map_id!r} must match {MAP_ID_RE.pattern}")
    if not SNAPSHOT_ID_RE.fullmatch(m.snapshot_id):
        raise SnapshotInvalid(f"{where}: snapshot_id {m.snapshot_id!r} must match {SNAPSHOT_ID_RE.pattern}")
    if not _SHA256.fullmatch(m.projection_sha256):
        raise SnapshotInvalid(f"{where}: projection_sha256 is not a SHA-256")
    return m


#: A lineage's creation stamp: what `utc_now` writes, give or take the fraction's digits.
_STAMP = re.compile(r"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}(\.\d{1,9})?(Z|[+-]\d{2}:\d{2})")
_COUNTS = ("restores", "rewrites", "repaired_below", "seq_high_water", "closure_high_water")


def _lineage(raw: Any, where: str) -> Lineage | None:
    """The manifest's `lineage` (absent: None); its stamp becomes part of an epoch and its counts ids'
    floors, so each is checked: a stamp as the catalog writes it, non-negative integers SQLite holds."""
    if raw is None:
        return None
    ok = (isinstance(raw, dict) and set(raw) == {"created_at", *_COUNTS}
          and isinstance(raw["created_at"], str) and _STAMP.fullmatch(raw["created_at"])
          and all(type(raw[k]) is int and 0 <= raw[k] < 2**63 for k in _COUNTS))
    if not ok:
        raise SnapshotInvalid(f"{where}: manifest lineage is malformed")
    return Lineage(**raw)


def _digest(path: Path) -> str:
    # Deliberately not storage.base.files.sha256_file: its cache is keyed by (path, mtime, size), so bit rot
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
    m = parse_manifest(body, str(directory))
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
    return with_facts(m, hashlib.sha256(body).hexdigest(), total)

