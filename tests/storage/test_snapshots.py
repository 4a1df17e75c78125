"""Snapshot directories: create, verify, tamper detection, load, tar export/import, unsafe tars refused."""

from __future__ import annotations

import hashlib
import io
import json
import os
import sqlite3
import tarfile
import warnings
import zipfile
from collections.abc import Callable
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

from models import presets
from models.memory.temporal_memory import TemporalMemory
from storage import snapshots
from storage.catalog import Lineage
from storage.manifest import parse_manifest
from storage.mapstore import MapStore, NewObservation
from storage.snapshots import SnapshotInvalid, create_snapshot, import_tar, load_memory, verify

RowFactory = Callable[..., NewObservation]
KNOWN = TemporalMemory.state_name  # the names `memory_arrays` (a TM's state) may have


def memory_arrays() -> dict[str, np.ndarray]:
    """Arrays shaped like `TemporalMemory.state_dict(streams=...)`: numbers, 0-d strings, prefixed keys."""
    rng = np.random.default_rng(3)
    return {
        "presyn": rng.integers(0, 2**16, 4096, dtype=np.uint16),
        "perm": rng.random(4096, dtype=np.float32),
        "last_used": rng.integers(0, 10**6, 256),
        "params": np.array(json.dumps({"cellsPerColumn": 4})),
        "rng": np.array([1, 2, 3, 4, 0, 0], dtype=np.uint64),
        "scalars": np.array([17, 4], dtype=np.int64),
        "ctx.active_cells": np.arange(12),
        "stream.cam-1.winner_cells": np.array([], dtype=np.int64),
    }


@pytest.fixture
def snap(tmp_path: Path, store: MapStore, row_factory: RowFactory) -> tuple[Path, snapshots.Manifest]:
    for i in range(1, 6):
        store.append(row_factory(i))
    dest = tmp_path / "snapshots" / "s1"
    manifest = create_snapshot(store, memory_arrays(), dest, kind="manual", code_version="0.3.0")
    return dest, manifest


def flip_byte(path: Path) -> None:
    """Change one byte in place like bit rot: same size, and the modification time put back."""
    st = path.stat()
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    with path.open("r+b") as f:
        f.write(data)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


def test_create_and_verify(snap: tuple[Path, snapshots.Manifest], store: MapStore,
                           row_factory: RowFactory) -> None:
    dest, m = snap
    assert sorted(p.name for p in dest.iterdir()) == ["manifest.json", "map.sqlite", "memory.npz"]
    assert [p.name for p in dest.parent.iterdir()] == ["s1"]  # no temporary directory left
    assert (m.snapshot_id, m.map_id, m.seq, m.last_observation_id, m.kind) == (
        "s1", "lab", 5, "obs-00000005", "manual")
    assert (m.encoder_id, m.projection_sha256, m.params) == (
        store.meta.encoder_id, store.meta.projection_sha256, store.meta.params)
    assert m.numpy_version == np.__version__ and m.code_version == "0.3.0"
    body = (dest / "manifest.json").read_bytes()
    assert m.manifest_sha256 == hashlib.sha256(body).hexdigest()
    assert m.bytes == sum(p.stat().st_size for p in dest.iterdir())
    for name, entry in m.files.items():
        assert entry.bytes == (dest / name).stat().st_size
        assert entry.sha256 == hashlib.sha256((dest / name).read_bytes()).hexdigest()
    assert verify(dest) == m

    # The copy is the cut at seq 5, whatever the map does next.
    store.append(row_factory(6))
    conn = sqlite3.connect(f"file:{dest / 'map.sqlite'}?mode=ro", uri=True)
    assert conn.execute("SELECT max(seq), count(*) FROM observations").fetchone() == (5, 5)
    conn.close()
    assert verify(dest) == m  # reading it changed nothing

    loaded = load_memory(dest, known=KNOWN)
    want = memory_arrays()
    assert loaded.keys() == want.keys()
    for k, v in want.items():
        assert loaded[k].dtype == v.dtype and loaded[k].shape == v.shape
        np.testing.assert_array_equal(loaded[k], v)


def test_empty_map_snapshot(tmp_path: Path, store: MapStore) -> None:
    m = create_snapshot(store, {"x": np.zeros(3)}, tmp_path / "s0", kind="auto")
    assert (m.seq, m.last_observation_id) == (0, None)
    assert verify(tmp_path / "s0").seq == 0


def test_real_temporal_memory_state_round_trips(tmp_path: Path, store: MapStore) -> None:
    tm = TemporalMemory(presets.TmOptions(columnDimensions=32, cellsPerColumn=4, activationThreshold=3,
                                          minThreshold=2, maxNewSynapseCount=4, maxSegmentsPerCell=4,
                                          maxSynapsesPerSegment=8, seed=7))
    cam = tm.new_context()
    for cols in ([0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11]):
        tm.compute(np.array(cols), learn=True, context=cam)
    state = tm.state_dict(streams={"cam-1": cam})
    create_snapshot(store, state, tmp_path / "tm", kind="manual")
    verify(tmp_path / "tm")
    loaded = load_memory(tmp_path / "tm", known=KNOWN)
    back = TemporalMemory.from_state(loaded)
    again = back.state_dict(streams=TemporalMemory.load_streams(loaded))
    assert again.keys() == state.keys()
    for k in state:
        np.testing.assert_array_equal(again[k], state[k])


def npy_header(shape: tuple[int, ...], descr: str = "|u1") -> bytes:
    """A `.npy` header alone: an array that declares `shape` and holds no data."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def with_member(npz: bytes, member: str, data: bytes, compress: int = zipfile.ZIP_STORED) -> bytes:
    """`npz` with one more member (what a crafted snapshot carries beside the memory's arrays)."""
    buf = io.BytesIO(npz)
    with zipfile.ZipFile(buf, "a") as z, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a name twice, on purpose
        z.writestr(zipfile.ZipInfo(member), data, compress_type=compress)
    return buf.getvalue()


def planted(manifest: bytes, npz: bytes, member: str, data: bytes,
            compress: int = zipfile.ZIP_STORED) -> tuple[bytes, bytes]:
    """(manifest, memory.npz) of a crafted snapshot: `member` added to the memory (`compress`: the
    outside tester's was deflated), and the manifest made to agree, so every checksum verifies (the
    tester's craft_snapshot.py)."""
    npz = with_member(npz, member, data, compress)
    body = json.loads(manifest)
    body["files"]["memory.npz"] = {"bytes": len(npz), "sha256": hashlib.sha256(npz).hexdigest()}
    return json.dumps(body).encode(), npz


def deflated_zeros(n: int) -> bytes:
    """A `.npy` of `n` zero bytes: it deflates about a thousandfold."""
    return npy_header((n,)) + bytes(n)


def test_a_memory_as_np_savez_writes_it_loads(snap: tuple[Path, snapshots.Manifest]) -> None:
    """Every member stored as it is: the arrays hold what the members hold (`.npy` headers included)."""
    dest, _ = snap
    with zipfile.ZipFile(dest / "memory.npz") as z:
        total = sum(i.file_size for i in z.infolist())
    assert snapshots.check_memory(dest, known=KNOWN) == total
    assert load_memory(dest, known=KNOWN).keys() == memory_arrays().keys()


def test_a_zip_directory_of_more_entries_than_a_memory_writes_is_refused_before_it_is_read(
        snap: tuple[Path, snapshots.Manifest], monkeypatch: pytest.MonkeyPatch) -> None:
    """zipfile holds the whole directory in memory when it opens a zip: its end record's count is read
    first (a ZIP64 directory, 0xFFFF, is none a memory writes)."""
    dest, _ = snap
    npz = dest / "memory.npz"
    data = bytearray(npz.read_bytes())
    at = data.rfind(b"PK\x05\x06")
    data[at + 8:at + 12] = b"\xff\xff\xff\xff"  # entries on this disk, and in all: 0xFFFF
    npz.write_bytes(bytes(data))
    opened: list[object] = []
    monkeypatch.setattr(zipfile, "ZipFile", lambda *a, **k: opened.append(a))
    with pytest.raises(SnapshotInvalid, match="no zip directory a memory writes"):
        snapshots.check_memory(dest, known=KNOWN)
    assert opened == []


@pytest.mark.parametrize(("member", "data", "compress", "why"), [
    # 1 TiB declared by its header, no data behind it: refused by the header, before a byte is read
    ("presyn2.npy", npy_header((2**40,)), zipfile.ZIP_STORED,
     r"'presyn2.npy' declares uint8\(1099511627776,\), more than its"),
    # 16 MiB of zeros deflated to ~16 KB: np.savez stores its members, so a deflated one is refused
    ("presyn2.npy", deflated_zeros(2**24), zipfile.ZIP_DEFLATED, "'presyn2.npy' is compressed"),
    ("bomb.npy", b"\x93NUMPY", zipfile.ZIP_STORED, "'bomb.npy' is no array of a map's memory"),
    ("notes.txt", b"hello", zipfile.ZIP_STORED, "'notes.txt' is no array of a map's memory"),
    ("perm.npy", npy_header((3,), "<f4") + bytes(12), zipfile.ZIP_STORED, "'perm.npy' appears twice"),
    ("presyn2.npy", npy_header((3,), "|O"), zipfile.ZIP_STORED, "holds objects"),
    ("presyn2.npy", npy_header((-1, 4)), zipfile.ZIP_STORED, "declares the shape"),
    ("presyn2.npy", b"not an array", zipfile.ZIP_STORED, "unreadable"),
], ids=["declared-1TiB", "deflated-16MiB", "unknown-name", "not-npy", "twice", "object", "negative",
        "garbage"])
def test_a_memory_member_is_refused_before_any_array_is_read(
        snap: tuple[Path, snapshots.Manifest], monkeypatch: pytest.MonkeyPatch,
        member: str, data: bytes, compress: int, why: str) -> None:
    """A crafted `memory.npz` (docs/design/service.md §4.4): a member compressed or declaring more than it
    holds, of a name the memory's writer never writes, or not an array of numbers, is refused by
    `check_memory` and by `load_memory` before any array's data is read."""
    dest, _ = snap
    npz = dest / "memory.npz"
    npz.write_bytes(with_member(npz.read_bytes(), member, data, compress))
    read: list[object] = []
    monkeypatch.setattr(np.lib.format, "read_array", lambda *a, **k: read.append(a))
    known = {*memory_arrays(), "presyn2"}.__contains__
    with pytest.raises(SnapshotInvalid, match=why):
        snapshots.check_memory(dest, known=known)
    with pytest.raises(SnapshotInvalid, match=why):
        load_memory(dest, known=known)
    assert read == []


def test_a_damaged_memory_file_is_invalid(snap: tuple[Path, snapshots.Manifest]) -> None:
    dest, _ = snap
    (dest / "memory.npz").write_bytes(b"not an archive")
    with pytest.raises(SnapshotInvalid, match="no zip directory"):
        load_memory(dest, known=KNOWN)


def test_create_refuses(tmp_path: Path, store: MapStore) -> None:
    with pytest.raises(ValueError, match="object"):
        create_snapshot(store, {"bad": np.array([{"a": 1}], dtype=object)}, tmp_path / "s", kind="manual")
    with pytest.raises(ValueError, match="not allowed"):
        create_snapshot(store, {"file": np.zeros(1)}, tmp_path / "s", kind="manual")
    with pytest.raises(ValueError, match="kind"):
        create_snapshot(store, {}, tmp_path / "s", kind="hourly")
    assert not (tmp_path / "s").exists()
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]
    (tmp_path / "s").mkdir()
    with pytest.raises(FileExistsError):
        create_snapshot(store, {}, tmp_path / "s", kind="manual")


@pytest.mark.parametrize("target", ["map.sqlite", "memory.npz"])
def test_flipped_byte_is_detected(snap: tuple[Path, snapshots.Manifest], target: str) -> None:
    dest, _ = snap
    verify(dest)  # warm any hash cache on purpose: verification must still re-read the bytes
    flip_byte(dest / target)
    with pytest.raises(SnapshotInvalid, match="checksum"):
        verify(dest)


def test_other_damage_is_detected(snap: tuple[Path, snapshots.Manifest]) -> None:
    dest, _ = snap
    raw = (dest / "manifest.json").read_text()
    m = json.loads(raw)
    (dest / "memory.npz").rename(dest / "moved.npz")
    with pytest.raises(SnapshotInvalid, match="missing"):
        verify(dest)
    (dest / "moved.npz").rename(dest / "memory.npz")
    with (dest / "map.sqlite").open("ab") as f:
        f.write(b"\0")
    with pytest.raises(SnapshotInvalid, match="bytes"):
        verify(dest)
    with (dest / "map.sqlite").open("r+b") as f:
        f.truncate(m["files"]["map.sqlite"]["bytes"])
    verify(dest)
    (dest / "manifest.json").write_text(raw.replace('"seq": 5', '"seq": 6'))
    verify(dest)  # the manifest's own integrity is the catalog's manifest_sha256, checked by the caller
    assert verify(dest).manifest_sha256 != hashlib.sha256(raw.encode()).hexdigest()
    for broken in ("{", json.dumps({**m, "format": "other"}), json.dumps({**m, "files": {}}),
                   json.dumps({**m, "files": {**m["files"], "../x": m["files"]["map.sqlite"]}})):
        (dest / "manifest.json").write_text(broken)
        with pytest.raises(SnapshotInvalid):
            verify(dest)
    (dest / "manifest.json").unlink()
    with pytest.raises(SnapshotInvalid):
        verify(dest)


def test_the_lineage_travels_in_the_manifest_and_a_malformed_one_is_invalid(
        tmp_path: Path, store: MapStore, row_factory: RowFactory) -> None:
    # a move keeps the map's epoch and id marks (docs/design/service.md §1.2): the manifest carries them
    store.append(row_factory(1))
    line = Lineage("2026-11-30T05:00:00.000000Z", restores=2, rewrites=1, repaired_below=7,
                   seq_high_water=40, closure_high_water=90)
    dest = tmp_path / "s1"
    m = create_snapshot(store, memory_arrays(), dest, kind="manual", lineage=line)
    assert m.lineage == line and verify(dest).lineage == line
    raw = json.loads((dest / "manifest.json").read_text())
    assert raw["lineage"]["closure_high_water"] == 90
    assert import_tar(io.BytesIO(exported(dest)), tmp_path / "imported").lineage == line
    # a manifest written before the lineage was recorded has none
    (dest / "manifest.json").write_text(json.dumps({k: v for k, v in raw.items() if k != "lineage"}))
    assert verify(dest).lineage is None
    # its stamp becomes part of an epoch and its counts floors of ids: anything else is refused
    for bad in ({**raw["lineage"], "restores": -1}, {**raw["lineage"], "seq_high_water": 2**63},
                {**raw["lineage"], "closure_high_water": True}, {**raw["lineage"], "created_at": "../x"},
                {**raw["lineage"], "extra": 1}, {k: v for k, v in raw["lineage"].items() if k != "rewrites"},
                [1, 2], "2026"):
        (dest / "manifest.json").write_text(json.dumps({**raw, "lineage": bad}))
        with pytest.raises(SnapshotInvalid, match="lineage"):
            verify(dest)


def exported(directory: Path, extra: dict[str, Path] | None = None) -> bytes:
    """The snapshot's tar as the download route streams it, chunk by chunk; exactly its announced size."""
    with snapshots.TarExport(directory, extra) as export:
        data = b"".join(export.chunks())
        assert len(data) == export.size
    return data


def test_export_import_round_trip(tmp_path: Path, store: MapStore, row_factory: RowFactory) -> None:
    store.append(row_factory(1))
    projection = tmp_path / "proj.npy"
    np.save(projection, np.ones((4, 3), dtype=np.float32))
    src = tmp_path / "snapshots" / "s1"
    m = create_snapshot(store, memory_arrays(), src, kind="manual", external={"projection.npy": projection})
    assert m.external["projection.npy"].sha256 == hashlib.sha256(projection.read_bytes()).hexdigest()

    data = exported(src, {"projection.npy": projection})
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        assert tar.getnames() == ["manifest.json", "map.sqlite", "memory.npz", "projection.npy"]

    dest = tmp_path / "elsewhere" / "imported"
    got = import_tar(io.BytesIO(data), dest)
    assert got == m
    assert verify(dest) == m
    for name in ("manifest.json", "map.sqlite", "memory.npz"):
        assert (dest / name).read_bytes() == (src / name).read_bytes()
    assert (dest / "projection.npy").read_bytes() == projection.read_bytes()
    with pytest.raises(FileExistsError):
        import_tar(io.BytesIO(data), dest)
    # Without the extra file the tar is still a complete snapshot.
    assert import_tar(io.BytesIO(exported(src)), tmp_path / "plain") == m


def test_import_detects_tampering(tmp_path: Path, snap: tuple[Path, snapshots.Manifest]) -> None:
    src, _ = snap
    good = exported(src)
    data = bytearray(good)
    # Flip a byte inside map.sqlite's data (the second member, after manifest header+data and its header).
    with tarfile.open(fileobj=io.BytesIO(bytes(data))) as tar:
        member = tar.getmember("map.sqlite")
        data[member.offset_data + member.size // 2] ^= 0x01
    with pytest.raises(SnapshotInvalid, match="checksum"):
        import_tar(io.BytesIO(bytes(data)), tmp_path / "bad")
    assert not (tmp_path / "bad").exists()
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]
    with pytest.raises(SnapshotInvalid):
        import_tar(io.BytesIO(b"not a tar at all" * 100), tmp_path / "bad")
    with pytest.raises(SnapshotInvalid, match="more than"):
        import_tar(io.BytesIO(good), tmp_path / "bad", max_bytes=1000)


def _tar(members: list[tuple[tarfile.TarInfo, bytes | None]]) -> io.BytesIO:
    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode="w", format=tarfile.GNU_FORMAT) as tar:
        for info, payload in members:
            if payload is not None:
                info.size = len(payload)
                tar.addfile(info, io.BytesIO(payload))
            else:
                tar.addfile(info)
    out.seek(0)
    return out


def _file(name: str) -> tarfile.TarInfo:
    return tarfile.TarInfo(name)


@pytest.mark.parametrize("name", ["../evil", "/tmp/evil", "sub/evil", "..", ".hidden", "a\\..\\evil", ""])
def test_path_traversal_refused(tmp_path: Path, snap: tuple[Path, snapshots.Manifest], name: str) -> None:
    src, _ = snap
    good = [(_file(n), (src / n).read_bytes()) for n in ("manifest.json", "map.sqlite", "memory.npz")]
    work = tmp_path / "work"
    work.mkdir()
    with pytest.raises(SnapshotInvalid):
        import_tar(_tar([*good[:1], (_file(name), b"owned"), *good[1:]]), work / "dest")
    assert not (work / "dest").exists()
    assert not (tmp_path / "evil").exists() and not (work / "evil").exists()
    assert list(work.iterdir()) == []


def test_links_duplicates_and_unknown_members_refused(tmp_path: Path,
                                                      snap: tuple[Path, snapshots.Manifest]) -> None:
    src, _ = snap
    good = [(_file(n), (src / n).read_bytes()) for n in ("manifest.json", "map.sqlite", "memory.npz")]
    sym = tarfile.TarInfo("memory.npz")
    sym.type, sym.linkname = tarfile.SYMTYPE, "/etc/passwd"
    hard = tarfile.TarInfo("memory.npz")
    hard.type, hard.linkname = tarfile.LNKTYPE, "map.sqlite"
    inside = tarfile.TarInfo("memory.npz")  # a link that stays in the tree: the `data` filter allows it
    inside.type, inside.linkname = tarfile.SYMTYPE, "map.sqlite"
    folder = tarfile.TarInfo("dir")
    folder.type = tarfile.DIRTYPE
    device = tarfile.TarInfo("memory.npz")
    device.type, device.devmajor, device.devminor = tarfile.CHRTYPE, 1, 3  # /dev/null
    cases = {
        "symlink": [*good[:2], (sym, None)],
        "symlink inside": [*good[:2], (inside, None)],
        "device": [*good[:2], (device, None)],
        "hardlink": [*good[:2], (hard, None)],
        "directory": [*good, (folder, None)],
        "duplicate": [*good, good[1]],
        "unknown": [*good, (_file("notes.txt"), b"hello")],
        "missing": good[:2],
        "no manifest": good[1:],
    }
    for why, members in cases.items():
        with pytest.raises(SnapshotInvalid):
            import_tar(_tar(members), tmp_path / "dest")
        assert not (tmp_path / "dest").exists(), why
    # A projection the manifest does not list is accepted (the caller verifies it by its own checksum).
    got = import_tar(_tar([*good, (_file("projection.npy"), b"npy")]), tmp_path / "dest")
    assert (tmp_path / "dest" / "projection.npy").read_bytes() == b"npy" and got.seq == 5


def test_a_file_name_ending_in_a_newline_is_refused(tmp_path: Path, store: MapStore,
                                                   snap: tuple[Path, snapshots.Manifest]) -> None:
    """SAFE_NAME ends in `$`, which also matches before a last newline: every use is a fullmatch (a tar
    member, a manifest entry, an external file written or exported)."""
    src, _ = snap
    good = [(_file(n), (src / n).read_bytes()) for n in ("manifest.json", "map.sqlite", "memory.npz")]
    with pytest.raises(SnapshotInvalid, match="not a plain file name"):
        import_tar(_tar([*good, (_file("projection.npy\n"), b"npy")]), tmp_path / "dest")
    assert not (tmp_path / "dest").exists()
    body = json.loads((src / "manifest.json").read_bytes())
    body["external"] = {"projection.npy\n": {"bytes": 3, "sha256": "0" * 64}}
    with pytest.raises(SnapshotInvalid, match="bad manifest entry"):
        parse_manifest(json.dumps(body).encode(), "here")
    projection = tmp_path / "proj.npy"
    projection.write_bytes(b"npy")
    with pytest.raises(ValueError, match="unsafe"):
        create_snapshot(store, memory_arrays(), tmp_path / "s2", kind="manual",
                        external={"projection.npy\n": projection})
    assert not (tmp_path / "s2").exists()
    with pytest.raises(ValueError, match="unsafe"):
        exported(src, {"projection.npy\n": projection})


def test_stale_temp_is_removed_and_nothing_else(tmp_path: Path, snap: tuple[Path, snapshots.Manifest],
                                                store: MapStore) -> None:
    src, _ = snap
    parent = src.parent
    create_snapshot(store, {"x": np.zeros(1)}, parent / "s2", kind="auto",
                    created_at="2999-01-01T00:00:00.000000Z")
    (parent / ".s3.tmp-abc").mkdir()  # an interrupted create
    (parent / "broken").mkdir()  # no manifest: not a snapshot, but not ours to remove either
    assert [p.name for p in snapshots.remove_stale_temp(parent)] == [".s3.tmp-abc"]
    assert sorted(p.name for p in parent.iterdir()) == ["broken", "s1", "s2"]
    assert len(snapshots.new_snapshot_id()) > 20


def test_tar_export_is_tarfile_layout_from_held_files(tmp_path: Path, snap: tuple[Path, snapshots.Manifest]
                                                      ) -> None:
    # The chunked export writes exactly what tarfile's streaming writer would, and reads the files it
    # opened (and verified) even when the directory disappears meanwhile (a pruned snapshot).
    src, m = snap
    projection = tmp_path / "proj.npy"
    np.save(projection, np.arange(1000, dtype=np.float32))
    expected = io.BytesIO()
    mtime = int(datetime.fromisoformat(m.created_at.replace("Z", "+00:00")).timestamp())
    with tarfile.open(fileobj=expected, mode="w|", format=tarfile.GNU_FORMAT) as tar:
        for name, path in [("manifest.json", src / "manifest.json"), ("map.sqlite", src / "map.sqlite"),
                           ("memory.npz", src / "memory.npz"), ("projection.npy", projection)]:
            info = tarfile.TarInfo(name)
            info.size = path.stat().st_size
            info.mtime = mtime
            info.mode, info.uname, info.gname = 0o644, "", ""
            with path.open("rb") as f:
                tar.addfile(info, f)
    export = snapshots.TarExport(src, {"projection.npy": projection})
    for p in src.iterdir():
        p.unlink()
    src.rmdir()
    data = b"".join(export.chunks(chunk_bytes=1000))
    export.close()
    assert data == expected.getvalue() and len(data) == export.size


def test_tar_export_verifies_before_the_first_byte(snap: tuple[Path, snapshots.Manifest]) -> None:
    src, _ = snap
    flip_byte(src / "memory.npz")
    assert snapshots.TarExport(src, verify=False).size > 0  # sizes still agree
    with pytest.raises(SnapshotInvalid, match=r"memory\.npz checksum"):
        snapshots.TarExport(src)
    (src / "manifest.json").write_text("{")
    with pytest.raises(SnapshotInvalid, match="not JSON"):
        snapshots.TarExport(src, verify=False)
