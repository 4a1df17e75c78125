"""`cortexloc import` refuses hostile manifests and oversized tars before writing anything, and never
writes outside the data directory (issue 11, item 2)."""

from __future__ import annotations

import hashlib
import io
import json
import re
import tarfile
from pathlib import Path

import pytest
from typer.testing import CliRunner

from service.cli import app as cli_app
from service.maps.errors import SnapshotInvalid
from storage import archive
from tests.service.helpers import frame, make_client, post
from tests.service.maps.maps_fixtures import registry
from tests.service.maps.recovery.test_memory import CRAFTED
from tests.storage.test_snapshots import planted


@pytest.fixture
def members(tmp_path) -> dict[str, bytes]:
    """The members of a real downloaded snapshot tar, by name (manifest first)."""
    with make_client(tmp_path / "source") as c:
        c.post("/v1/maps", json={"map_id": "lab"})
        for p in range(3):
            post(c, frame(p), map_id="lab")
        sid = c.post("/v1/maps/lab/snapshots").json()["snapshot_id"]
        raw = c.get(f"/v1/maps/lab/snapshots/{sid}/download").content
    with tarfile.open(fileobj=io.BytesIO(raw)) as tar:
        return {m.name: tar.extractfile(m).read() for m in tar}


def make_tar(path: Path, members: dict[str, bytes], mode: str = "w") -> Path:
    with tarfile.open(path, mode) as tar:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return path


def with_manifest(members: dict[str, bytes], **changes) -> dict[str, bytes]:
    manifest = json.loads(members["manifest.json"])
    manifest.update(changes)
    return {**members, "manifest.json": json.dumps(manifest).encode()}


def tree(root: Path) -> dict[str, bytes]:
    """Every file under `root` with its bytes (what 'nothing was written' compares)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def run_import(tar: Path, data: Path):
    return CliRunner().invoke(cli_app, ["import", str(tar), "--data-dir", str(data)])


@pytest.mark.parametrize("changes", [
    {"map_id": "../../escaped"},
    {"map_id": "<absolute>"},
    {"map_id": "Bad Map!"},
    {"map_id": ".."},
    {"snapshot_id": "../../../../newdir/snap"},
    {"snapshot_id": ".."},
    {"map_id": "m\n"},  # `$` also matches before a last newline
    {"snapshot_id": "s\n"},
    {"projection_sha256": "../../../projection-escape"},
], ids=lambda c: f"{next(iter(c))}={next(iter(c.values()))}")
def test_hostile_names_are_refused_before_anything_is_written(tmp_path, members, changes):
    root = tmp_path / "box"
    data = root / "deep" / "data"
    with make_client(data):
        pass  # a data directory as the server leaves it
    before = tree(root)
    changes = {k: str(root / "escaped") if v == "<absolute>" else v for k, v in changes.items()}
    r = run_import(make_tar(tmp_path / "bad.tar", with_manifest(members, **changes)), data)
    assert r.exit_code == 1, r.output
    assert "must match" in r.output or "not a SHA-256" in r.output
    assert tree(root) == before  # nothing inside the data directory, nor beside it


def test_a_malformed_lineage_is_refused_before_anything_is_written(tmp_path, members):
    # its stamp becomes part of the map's epoch and its counts floors of ids (docs/design/service.md §1.2)
    assert json.loads(members["manifest.json"])["lineage"]["seq_high_water"] == 3
    data = tmp_path / "data"
    with make_client(data):
        pass
    before = tree(data)
    r = run_import(make_tar(tmp_path / "bad.tar", with_manifest(members, lineage={"created_at": "x"})), data)
    assert r.exit_code == 1 and "lineage" in r.output, r.output
    assert tree(data) == before


def test_a_good_tar_still_imports(tmp_path, members):
    r = run_import(make_tar(tmp_path / "good.tar", members), tmp_path / "data")
    assert r.exit_code == 0, r.output
    assert (tmp_path / "data" / "maps" / "lab" / "map.sqlite").is_file()


@pytest.mark.parametrize("damage", ["truncated", "not a tar"])
def test_a_refused_import_leaves_no_data_directory_it_made_and_changes_none_there_was(tmp_path, members,
                                                                                      damage):
    """Found from outside: a truncated tar (or a JPEG given as one) was refused, but the data directory
    the import had opened stayed behind (its lock, an empty catalog, the folders)."""
    good = make_tar(tmp_path / "good.tar", members).read_bytes()
    bad = tmp_path / "bad.tar"
    bad.write_bytes(good[: len(good) // 3] if damage == "truncated" else b"\xff\xd8\xff\xe0" + b"\0" * 600)
    fresh = tmp_path / "fresh"
    r = run_import(bad, fresh)
    assert r.exit_code == 1 and isinstance(r.exception, SystemExit), (r.exception, r.output)
    assert r.output.startswith("error: "), r.output
    assert not fresh.exists()
    kept = tmp_path / "kept"  # a data directory that was there stays as it was
    assert run_import(tmp_path / "good.tar", kept).exit_code == 0
    before = tree(kept)
    assert run_import(bad, kept).exit_code == 1
    assert tree(kept) == before


@pytest.mark.parametrize("manifest", [b'{"a":' * 100_000 + b"1" + b"}" * 100_000, b"1" * 5000],
                         ids=["nested 100000 deep", "an integer of 5000 digits"])
def test_a_manifest_json_cannot_parse_is_one_line_refusal(tmp_path, members, manifest):
    """Found from outside: a manifest nested 100,000 deep escaped as a RecursionError traceback (and an
    over-long integer is Python's ValueError, not a JSONDecodeError); each is a bad manifest."""
    data = tmp_path / "data"
    r = run_import(make_tar(tmp_path / "deep.tar", {**members, "manifest.json": manifest}), data)
    assert r.exit_code == 1 and isinstance(r.exception, SystemExit), (r.exception, r.output)
    assert "manifest is not JSON" in r.output, r.output
    assert not list(data.glob("maps/*"))


def test_a_compressed_bomb_is_refused_before_its_data_is_written(tmp_path, members, monkeypatch):
    """64 MiB of zeros, gzip-compressed to ~64 KB, against a 32 MiB cap: refused from the manifest
    when declared, from the member's tar header when not, and never written either way."""
    monkeypatch.setenv("CORTEXLOC_MAX_IMPORT_BYTES", str(32 * 2**20))
    zeros = bytes(64 * 2**20)
    members = {k: v for k, v in members.items() if k != "projection.npy"}  # random floats: incompressible
    manifest = json.loads(members["manifest.json"])
    manifest["files"]["map.sqlite"] = {"bytes": len(zeros), "sha256": hashlib.sha256(zeros).hexdigest()}
    bomb = {**members, "manifest.json": json.dumps(manifest).encode(), "map.sqlite": zeros}
    written: list[str] = []
    real = archive._write_hashed

    def spy(src, path):
        written.append(path.name)
        return real(src, path)

    monkeypatch.setattr(archive, "_write_hashed", spy)
    data = tmp_path / "data"
    tar = make_tar(tmp_path / "bomb.tar.gz", bomb, "w:gz")
    assert tar.stat().st_size < 2**20
    r = run_import(tar, data)
    assert r.exit_code == 1 and f"more than the {32 * 2**20} allowed" in r.output, r.output
    assert written == [] and not list(data.glob("maps/*"))
    # An unlisted member (a projection needs no manifest entry) is held against the cap by its header.
    unlisted = json.loads(members["manifest.json"])
    unlisted["external"] = {}
    sneaky = {**members, "manifest.json": json.dumps(unlisted).encode(), "projection.npy": zeros}
    r = run_import(make_tar(tmp_path / "sneaky.tar.gz", sneaky, "w:gz"), data)
    assert r.exit_code == 1 and f"more than {32 * 2**20} bytes" in r.output, r.output
    assert "projection.npy" not in written and not list(data.glob("maps/*"))
    # A member larger than the manifest says is refused by its header, before its data is read.
    written.clear()
    r = run_import(make_tar(tmp_path / "liar.tar.gz", {**members, "memory.npz": zeros}, "w:gz"), data)
    assert r.exit_code == 1 and "the manifest says" in r.output, r.output
    assert "memory.npz" not in written


@CRAFTED
def test_a_crafted_memory_is_refused_and_nothing_is_stored(tmp_path, members, member, data, compress, why):
    """A tar whose every checksum verifies, its memory.npz carrying a compressed member, one declaring more
    than it holds, or one of a name no memory writes (the outside tester's bomb): `cortexloc import` and
    the live import (a move's receiving end) refuse it as an invalid snapshot, and nothing stored changes
    (docs/design/service.md §4.4)."""
    manifest, npz = planted(members["manifest.json"], members["memory.npz"], member, data, compress)
    crafted = make_tar(tmp_path / "crafted.tar", {**members, "manifest.json": manifest, "memory.npz": npz})
    data_dir = tmp_path / "data"
    with make_client(data_dir):
        pass  # a data directory as the server leaves it
    before = tree(data_dir)
    r = run_import(crafted, data_dir)
    assert r.exit_code == 1 and "error: " in r.output and why in r.output, r.output
    assert tree(data_dir) == before
    with registry(tmp_path / "live") as reg:
        before = tree(tmp_path / "live" / "maps")
        with pytest.raises(SnapshotInvalid, match=re.escape(why)):
            reg.import_live(crafted, 2**33)
        assert reg.catalog.get_map("lab") is None and tree(tmp_path / "live" / "maps") == before


def test_the_manifest_must_come_first(tmp_path, members):
    reordered = {k: members[k] for k in sorted(members, key=lambda n: n != "map.sqlite")}
    r = run_import(make_tar(tmp_path / "late.tar", reordered), tmp_path / "data")
    assert r.exit_code == 1 and "must begin with manifest.json" in r.output
