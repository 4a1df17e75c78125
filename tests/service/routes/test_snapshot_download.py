"""Snapshot downloads and restores at the HTTP edge (issue 11, items 4 and 8): the tar is streamed from
the snapshot's own files with no copy, released when the client goes, guarded by the key when the
operator asks, and a damaged snapshot is refused with a 409 problem instead of served or a 500."""

from __future__ import annotations

import io
import json
import os
import tarfile
from pathlib import Path

import anyio
import pytest
from fastapi.testclient import TestClient

from service.errors import PROBLEM_MEDIA_TYPE
from service.settings import ConfigError, Settings
from tests.service.helpers import frame, make_client, tm_digest


def snapshot_with_frames(c: TestClient, n: int = 3, headers: dict | None = None) -> tuple[str, Path]:
    """Post `n` frames and snapshot them: (snapshot id, its directory)."""
    for p in range(n):
        r = c.post("/v1/maps/default/observations", content=frame(p), headers={"Content-Type": "image/png",
                                                                               **(headers or {})})
        assert r.status_code == 200, r.text
    sid = c.post("/v1/maps/default/snapshots", headers=headers).json()["snapshot_id"]
    rt = c.app.state.registry.get("default")
    return sid, rt.snapshot_dir(sid)


def files_under(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()}


def fds_into(root: Path) -> list[str]:
    """This process's open file descriptors that point under `root` (deleted files included), but not the
    databases the maps keep open; the projection's memory map holds one too (compare with a baseline)."""
    out = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith(str(root)) and not target.endswith((".sqlite", "-wal", "-shm", "-journal")):
            out.append(target)
    return out


@pytest.fixture
def client(tmp_path):
    with make_client(tmp_path / "data") as c:
        yield c


def test_download_is_the_snapshot_files_verbatim_and_writes_nothing(client, tmp_path):
    sid, snap_dir = snapshot_with_frames(client)
    data_dir = tmp_path / "data"
    before, fds_before = files_under(data_dir), fds_into(data_dir)
    r = client.get(f"/v1/maps/default/snapshots/{sid}/download")
    assert r.status_code == 200 and int(r.headers["content-length"]) == len(r.content)
    with tarfile.open(fileobj=io.BytesIO(r.content)) as tar:
        got = {m.name: tar.extractfile(m).read() for m in tar.getmembers()}
    rt = client.app.state.registry.get("default")
    assert list(got) == ["manifest.json", "map.sqlite", "memory.npz", "projection.npy"]
    for name in ("manifest.json", "map.sqlite", "memory.npz"):
        assert got[name] == (snap_dir / name).read_bytes()
    assert got["projection.npy"] == rt.projection_path.read_bytes()
    assert files_under(data_dir) == before
    assert fds_into(data_dir) == fds_before


def test_an_aborted_download_holds_no_copy_and_releases_every_file(client, tmp_path):
    # A client that reads the first chunk, stalls, then goes away. While it stalls the server may hold
    # the snapshot's own files open, but no copy (the old code held a deleted temporary tar per client);
    # once it is gone, nothing under the data directory is held.
    sid, snap_dir = snapshot_with_frames(client)
    data_dir = tmp_path / "data"
    before, fds_before = files_under(data_dir), fds_into(data_dir)
    seen: dict[str, object] = {}

    async def stalled_then_gone() -> None:
        gone = anyio.Event()
        first_chunk = anyio.Event()

        async def receive() -> dict:
            await gone.wait()
            return {"type": "http.disconnect"}

        async def send(message: dict) -> None:
            if message["type"] == "http.response.start":
                seen["status"] = message["status"]
            elif message["type"] == "http.response.body" and message.get("body"):
                first_chunk.set()
                await anyio.sleep_forever()  # the client stopped reading: the socket buffer is full

        scope = {"type": "http", "asgi": {"version": "3.0", "spec_version": "2.3"}, "http_version": "1.1",
                 "method": "GET", "scheme": "http", "path": f"/v1/maps/default/snapshots/{sid}/download",
                 "raw_path": b"", "root_path": "", "query_string": b"", "headers": [],
                 "client": ("127.0.0.1", 1), "server": ("testserver", 80)}
        async with anyio.create_task_group() as tg:
            tg.start_soon(client.app, scope, receive, send)
            await first_chunk.wait()
            seen["stalled_fds"] = [t for t in fds_into(data_dir) if t not in fds_before]
            seen["stalled_files"] = files_under(data_dir)
            gone.set()

    client.portal.call(stalled_then_gone)
    assert seen["status"] == 200
    assert seen["stalled_fds"] and not [t for t in seen["stalled_fds"] if t.endswith("(deleted)")]
    assert all(Path(t).parent in (snap_dir, data_dir / "projections") for t in seen["stalled_fds"])
    assert seen["stalled_files"] == before
    assert fds_into(data_dir) == fds_before
    assert files_under(data_dir) == before


def test_api_key_reads_guards_downloads(tmp_path):
    key = {"X-API-Key": "s3cret"}
    with make_client(tmp_path / "open", api_key="s3cret") as c:
        sid, _ = snapshot_with_frames(c, 1, headers=key)
        assert c.get(f"/v1/maps/default/snapshots/{sid}/download").status_code == 200  # default: open
    with make_client(tmp_path / "open", api_key="s3cret", api_key_reads=True) as c:
        r = c.get(f"/v1/maps/default/snapshots/{sid}/download")
        assert r.status_code == 401 and r.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE)
        assert r.json()["type"].endswith("unauthorized")
        r = c.get(f"/v1/maps/default/snapshots/{sid}/download", headers={"Authorization": "Bearer s3cret"})
        assert r.status_code == 200 and r.content[:512].startswith(b"manifest.json")
        assert c.get("/v1/maps/default/snapshots").status_code == 401  # the listing too (issue 19 item 7)
        assert c.get("/v1/maps/default/snapshots", headers=key).status_code == 200
    with pytest.raises(ConfigError, match="CORTEXLOC_API_KEY_READS"):
        Settings.from_env({"CORTEXLOC_API_KEY_READS": "true"})


def _flip_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", ["memory.npz", "map.sqlite", "manifest garbage", "manifest missing"])
def test_a_damaged_snapshot_is_refused_with_its_reason(client, damage):
    sid, snap_dir = snapshot_with_frames(client)
    if damage == "manifest garbage":
        (snap_dir / "manifest.json").write_bytes(b"\x00garbage{")
    elif damage == "manifest missing":
        (snap_dir / "manifest.json").unlink()
    else:
        _flip_byte(snap_dir / damage)
    rt = client.app.state.registry.get("default")
    before = (rt.store.count(), tm_digest(rt.tm), [s["snapshot_id"] for s in client.get(
        "/v1/maps/default/snapshots").json()["snapshots"]])
    for r in (client.get(f"/v1/maps/default/snapshots/{sid}/download"),
              client.post(f"/v1/maps/default/snapshots/{sid}/restore")):
        assert r.status_code == 409, r.text
        assert r.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE)
        body = r.json()
        assert body["type"] == "urn:cortexloc:problem:snapshot-invalid"
        assert body["title"] == "Snapshot invalid"
        word = {"memory.npz": "memory.npz checksum", "map.sqlite": "map.sqlite checksum",
                "manifest garbage": "manifest is not JSON", "manifest missing": "manifest.json"}[damage]
        assert word in body["detail"]
        assert str(client.app.state.settings.data_dir.resolve()) not in body["detail"]
    after = (rt.store.count(), tm_digest(rt.tm), [s["snapshot_id"] for s in client.get(
        "/v1/maps/default/snapshots").json()["snapshots"]])
    assert after == before  # no pre-restore snapshot, nothing rolled back
    assert json.loads(client.get("/v1/maps/default").text)["state"] == "ready"


@pytest.mark.parametrize("bad", ["-abc", ".abc", "a" * 81, "a%20b"])
def test_a_malformed_snapshot_id_is_refused_like_any_bad_parameter(client, bad):
    # The route's pattern is the catalog's: a leading '.' or '-' (never a directory the catalog writes)
    # gets the same 400 as an over-long id, before any file is looked at.
    snapshot_with_frames(client, 1)
    for r in (client.get(f"/v1/maps/default/snapshots/{bad}/download"),
              client.post(f"/v1/maps/default/snapshots/{bad}/restore")):
        assert r.status_code == 400, r.text
        assert r.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE)
        assert r.json()["type"] == "urn:cortexloc:problem:invalid-parameter"


def test_head_on_a_download_checks_the_snapshot_and_streams_nothing(client, tmp_path, monkeypatch):
    # A review: HEAD ran the whole download server-side (every file read and streamed, then dropped).
    from storage.archive import TarExport

    sid, snap_dir = snapshot_with_frames(client)
    data_dir = tmp_path / "data"
    got = client.get(f"/v1/maps/default/snapshots/{sid}/download")
    fds_before = fds_into(data_dir)
    read: list[int] = []
    real = TarExport.chunks

    def counted(self, *args, **kwargs):
        for chunk in real(self, *args, **kwargs):
            read.append(len(chunk))
            yield chunk

    monkeypatch.setattr(TarExport, "chunks", counted)
    head = client.head(f"/v1/maps/default/snapshots/{sid}/download")
    assert head.status_code == 200 and head.content == b"" and read == []
    assert head.headers["content-length"] == got.headers["content-length"] == str(len(got.content))
    assert head.headers["content-disposition"] == got.headers["content-disposition"]
    assert fds_into(data_dir) == fds_before  # the export's files released
    data = bytearray((snap_dir / "memory.npz").read_bytes())
    data[len(data) // 2] ^= 1
    (snap_dir / "memory.npz").write_bytes(bytes(data))
    assert client.head(f"/v1/maps/default/snapshots/{sid}/download").status_code == 409  # as its GET
    assert client.get(f"/v1/maps/default/snapshots/{sid}/download").status_code == 409
    export = client.head("/v1/maps/default/loop-closures/export?format=csv")
    assert export.status_code == 200 and export.content == b""
