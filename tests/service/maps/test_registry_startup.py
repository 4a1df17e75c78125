"""The map registry at startup and at creation (docs/design/service.md §1.1, §4.4): a map that cannot be
opened fails alone, and a refused creation never loads a network."""

from __future__ import annotations

import json
import re
import sqlite3
import threading

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.maps.errors import DataDirectoryInUse
from service.maps.results import NOT_READ
from service.settings import Settings
from storage.catalog import Catalog
from storage.lock import DataDirLock
from tests.service.helpers import frame, make_client, post, tiny_encoder


def set_stored_params(data, map_id: str, **changes) -> None:
    """What an older version (or a hand edit) may have left in the catalog."""
    with sqlite3.connect(data / "catalog.sqlite") as db:
        (params,) = db.execute("SELECT params FROM maps WHERE map_id = ?", (map_id,)).fetchone()
        db.execute("UPDATE maps SET params = ? WHERE map_id = ?",
                   (json.dumps({**json.loads(params), **changes}), map_id))


@pytest.mark.parametrize("changes", [{"localiser": {"exclusion": "x"}}, {"localiser": {"beam": 10**9}},
                                     {"tm": {"columnDimensions": "x"}}],
                         ids=["exclusion-x", "beam-1e9", "tm-garbage"])
def test_a_map_that_cannot_be_opened_fails_alone(tmp_path, changes):
    data = tmp_path / "data"
    with make_client(data) as c:
        assert c.post("/v1/maps", json={"map_id": "lab"}).status_code == 201
        assert post(c, frame(1), map_id="lab").status_code == 200
        assert post(c, frame(2)).status_code == 200
    set_stored_params(data, "lab", **changes)
    with make_client(data) as c:
        r = post(c, frame(1), map_id="lab")
        assert r.status_code == 503, r.text
        assert r.json()["type"] == "urn:cortexloc:problem:map-unavailable"
        assert r.json()["state_reason"] == "open-failed"
        ready = c.get("/readyz")
        assert ready.status_code == 200, ready.text
        lab = ready.json()["checks"]["maps"]["maps"]["lab"]
        assert (lab["state"], lab["state_reason"]) == ("failed", "open-failed")
        assert any("lab" in w for w in ready.json()["warnings"])
        # Listed as it was stored; the rest of the service works.
        listed = {m["map_id"]: m for m in c.get("/v1/maps").json()["maps"]}
        assert listed["lab"]["state"] == "failed" and listed["default"]["state"] == "ready"
        # its counts are not read: it says so, not that the two frames it holds are gone
        assert listed["lab"]["observations"] == 0 and NOT_READ in listed["lab"]["warnings"]
        assert NOT_READ not in listed["default"]["warnings"]
        assert c.get("/v1/maps/lab/memory").status_code == 503
        assert c.get("/v1/maps/lab/snapshots").status_code == 200
        # (another stream: the default stream's own last row is not an answer to it, science.md §11.6)
        assert post(c, frame(2), learn="false", stream="probe").json()["matches"][0]["seq"] == 1
        assert post(c, frame(3)).status_code == 200
        every_route_answers_a_failed_map_without_a_500(c, "lab")
        assert c.delete("/v1/maps/lab").status_code == 204
        assert c.get("/v1/maps/lab").status_code == 404


def every_route_answers_a_failed_map_without_a_500(c, map_id: str) -> None:
    """Found from outside: `GET` and `POST .../repair` on a failed map were a 500 (`FailedMap` had no
    such method). Every operation the API declares on a map, each as a client might call it."""
    values = {"map_id": map_id, "seq": "1", "answer_id": "1", "stream": "s",
              "snapshot_id": "20261130T000000000000Z-00000000"}
    for path, ops in c.app.openapi()["paths"].items():
        if "{map_id}" not in path:
            continue
        url = re.sub(r"\{(\w+)\}", lambda m: values[m.group(1)], path)
        for method in ops:
            if (path, method) == ("/v1/maps/{map_id}", "delete"):
                continue  # (the caller deletes it last)
            kwargs = ({"content": frame(1), "headers": {"Content-Type": "image/png"}}
                      if path.endswith("/observations") and method == "post" else
                      {"json": {"revisit_threshold": 0.5}} if method == "patch" else {})
            r = c.request(method.upper(), url, **kwargs)
            assert r.status_code != 500 and r.headers["content-type"].split(";")[0] in (
                "application/json", "application/problem+json"), (method, path, r.status_code, r.text)
            # and declared: a client generated from the OpenAPI knows the answer (an outside probe found
            # a 503 the reset, memory and download routes did not declare)
            assert str(r.status_code) in ops[method]["responses"], (method, path, r.status_code)


@pytest.fixture
def counted(tmp_path):
    """A client whose encoder factory counts the networks it builds (by backbone)."""
    built: list[str] = []

    def factory(settings: Settings):
        built.append(settings.backbone)
        return tiny_encoder(settings)

    app = create_app(Settings(data_dir=tmp_path / "data", backbone="alexnet", max_maps=2),
                     encoder_factory=factory)
    with TestClient(app) as c:
        yield c, built


@pytest.mark.parametrize(("payload", "status", "slug"), [
    ({"map_id": "default"}, 409, "map-exists"),
    ({"map_id": "lab", "localiser": {"beam": 0}}, 422, "invalid-configuration"),
])
def test_a_refused_creation_never_loads_a_network(counted, payload, status, slug):
    c, built = counted
    assert built == ["alexnet"]
    r = c.post("/v1/maps", json={**payload, "backbone": "efficientnet-lite0-s5"})
    assert r.status_code == status, r.text
    assert r.json()["type"] == f"urn:cortexloc:problem:{slug}"
    assert built == ["alexnet"]


def test_the_map_limit_is_checked_before_a_network_is_loaded(counted):
    c, built = counted
    assert c.post("/v1/maps", json={"map_id": "lab"}).status_code == 201  # 2 of max_maps 2
    r = c.post("/v1/maps", json={"map_id": "more", "backbone": "efficientnet-lite0-s5"})
    assert r.status_code == 409 and r.json()["type"] == "urn:cortexloc:problem:map-limit", r.text
    assert built == ["alexnet"]


def map_files(data, map_id: str) -> dict[str, bytes]:
    """Every file of a map's directory, by path: what must be left as it is."""
    root = data / "maps" / map_id
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def a_map_with_rows(c, map_id: str) -> None:
    assert c.post("/v1/maps", json={"map_id": map_id}).status_code == 201
    for place in range(3):
        assert post(c, frame(place), map_id=map_id).status_code == 200
    assert c.post(f"/v1/maps/{map_id}/snapshots").status_code == 201


@pytest.mark.parametrize("catalog", ["deleted", "empty file"])
def test_a_lost_catalog_leaves_every_map_as_it_is_and_the_service_not_ready(tmp_path, catalog):
    # A fresh install has no map directories: a catalog that lists none beside maps that hold rows was
    # lost or replaced, and making `default` anew (or any map later) would wipe what the robot learned.
    data = tmp_path / "data"
    with make_client(data) as c:
        a_map_with_rows(c, "farm")
        assert post(c, frame(7)).status_code == 200  # and `default` holds a row too
    (data / "catalog.sqlite").unlink()
    for side in ("-wal", "-shm"):
        (data / f"catalog.sqlite{side}").unlink(missing_ok=True)
    if catalog == "empty file":
        (data / "catalog.sqlite").write_bytes(b"")
    before = {m: map_files(data, m) for m in ("farm", "default")}
    with make_client(data) as c:
        ready = c.get("/readyz")
        assert ready.status_code == 503
        assert "maps/default, maps/farm" in json.dumps(ready.json()) and "catalog" in json.dumps(ready.json())
    assert {m: map_files(data, m) for m in ("farm", "default")} == before


def test_creating_a_map_over_a_directory_the_catalog_does_not_list_is_refused_and_changes_nothing(tmp_path):
    data = tmp_path / "data"
    with make_client(data) as c:
        a_map_with_rows(c, "farm")
    with sqlite3.connect(data / "catalog.sqlite") as db:  # the catalog forgot it (another process's map)
        db.execute("DELETE FROM snapshots WHERE map_id = 'farm'")
        db.execute("DELETE FROM maps WHERE map_id = 'farm'")
    before = map_files(data, "farm")
    with make_client(data) as c:
        ready = c.get("/readyz")  # `default` is listed: the service serves it, and warns of farm
        assert ready.status_code == 200 and ready.json()["checks"]["catalog"]["unlisted_maps"] == ["farm"]
        assert any("catalog does not list" in w for w in ready.json()["warnings"])
        r = c.post("/v1/maps", json={"map_id": "farm"})
        assert r.status_code == 409 and r.json()["type"].endswith("map-exists")
        assert "maps/farm" in r.json()["detail"]
    assert map_files(data, "farm") == before


def test_leftovers_of_a_creation_that_never_reached_the_catalog_are_cleared(tmp_path):
    # MapStore.create wrote the empty store, the catalog row never came (a crash between the two)
    data = tmp_path / "data"
    with make_client(data) as c:
        assert c.post("/v1/maps", json={"map_id": "yard"}).status_code == 201
    with sqlite3.connect(data / "catalog.sqlite") as db:
        db.execute("DELETE FROM maps WHERE map_id = 'yard'")
    with make_client(data) as c:
        assert c.post("/v1/maps", json={"map_id": "yard"}).status_code == 201
        assert post(c, frame(1), map_id="yard").status_code == 200


def test_a_second_process_on_the_data_directory_waits_for_it_then_gives_up_touching_nothing(tmp_path):
    data = tmp_path / "data"
    with make_client(data) as first:
        assert post(first, frame(1)).status_code == 200
        before = map_files(data, "default")
        # another open of the directory, as another process's: it waits `lock_wait_s`, then fails to start
        with (pytest.raises(DataDirectoryInUse, match="in use by another cortexloc process"),
              make_client(data, lock_wait_s=0.5)):
            pass
        assert map_files(data, "default") == before
        assert post(first, frame(2)).status_code == 200  # the first serves on
    with make_client(data, lock_wait_s=0) as again:  # the lock went with the first
        assert again.get("/readyz").status_code == 200
        assert again.get("/v1/maps/default").json()["observations"] == 2


def test_a_restart_that_overlaps_the_old_process_starts_once_it_lets_go(tmp_path):
    # a rolling update: the new process starts while the old one still closes its maps
    data = tmp_path / "data"
    old = make_client(data)
    old.__enter__()
    assert post(old, frame(1)).status_code == 200
    closer = threading.Timer(1.0, old.__exit__, (None, None, None))
    closer.start()
    try:
        with make_client(data, lock_wait_s=60) as new:  # waits for the lock, then starts
            assert new.get("/readyz").status_code == 200
            assert new.get("/v1/maps/default").json()["observations"] == 1
    finally:
        closer.join()


def test_a_start_that_fails_lets_the_directory_go(tmp_path):
    data = tmp_path / "data"
    with make_client(data) as c:
        a_map_with_rows(c, "farm")
    (data / "catalog.sqlite").unlink()
    with make_client(data) as c:  # not ready (a lost catalog)
        assert c.get("/readyz").status_code == 503
        # the failed start let the lock go: the directory can be opened again in this process
        DataDirLock(data / ".lock").acquire().release()


def test_a_delete_cut_short_blocks_neither_the_id_nor_the_next_start(tmp_path, monkeypatch):
    # killed during a large map's removal: the directory was left holding rows with no catalog row, so
    # the id was refused for good (409), and as the last map it kept every start not ready
    data = tmp_path / "data"
    with make_client(data) as c:
        a_map_with_rows(c, "farm")
        assert c.delete("/v1/maps/default").status_code == 204
        monkeypatch.setattr("service.maps.registry.shutil.rmtree", lambda *a, **k: None)  # the kill
        assert c.delete("/v1/maps/farm").status_code == 204
        monkeypatch.undo()
        assert c.post("/v1/maps", json={"map_id": "farm"}).status_code == 201  # the id is free again
        assert c.get("/v1/maps/farm").json()["observations"] == 0
        assert c.delete("/v1/maps/farm").status_code == 204
    assert list((data / "maps").glob(".deleted-*"))  # what the cut-short removal left
    with make_client(data) as c:  # the next start (no map listed): ready, and the leftovers gone
        assert c.get("/readyz").status_code == 200
    assert not list((data / "maps").glob(".deleted-*"))


class _Killed(BaseException):
    """The process dies here (a kill -9: nothing after it runs, no handler sees it)."""


def test_a_delete_killed_after_its_directory_moved_is_finished_at_the_next_start(tmp_path, monkeypatch):
    """Found from outside: a kill -9 during `DELETE /v1/maps/{id}` left the map's directory under its own
    name with no catalog row (the entry went first), so every start logged an unlisted map and the id
    was refused (409) for good. The directory now moves out of the maps' names first; killed before the
    entry goes, the next start finishes the delete, which was never answered."""
    data = tmp_path / "data"
    with make_client(data) as c:
        a_map_with_rows(c, "farm")
        a_map_with_rows(c, "farm-b")
        real = Catalog.delete_map

        def killed(self, map_id):
            raise _Killed

        monkeypatch.setattr(Catalog, "delete_map", killed)
        with pytest.raises(_Killed):
            c.app.state.registry.delete("farm")
        monkeypatch.setattr(Catalog, "delete_map", real)
        # the kill left the catalog row and the map's files under a discarded name
        assert (data / "maps" / "farm").is_dir()  # (put back: nothing answered the delete)
        (data / "maps" / "farm").rename(data / "maps" / f".deleted-farm-{'0' * 32}")  # as at the kill
    with make_client(data) as c:
        assert c.get("/readyz").status_code == 200
        assert c.get("/v1/maps/farm").status_code == 404
        assert c.get("/v1/maps/farm-b").json()["observations"] > 0
        assert c.post("/v1/maps", json={"map_id": "farm"}).status_code == 201  # the id is free
    assert not list((data / "maps").glob(".deleted-*"))
    # Another id's discarded directory is not this map's, though its name begins with it: farm, its
    # files gone some other way (not by a delete) beside farm-b's discarded directory, stays listed.
    (data / "maps" / "farm").rename(tmp_path / "farm-moved")
    (data / "maps" / f".deleted-farm-b-{'1' * 32}").mkdir()
    with make_client(data) as c:
        assert c.get("/v1/maps/farm").status_code == 200


def test_a_start_removes_what_a_killed_import_left_but_not_while_another_process_holds_the_directory(
        tmp_path):
    """Found by an outside tester: a killed `cortexloc import` left its staging directories (the snapshot's
    unpacked size) in maps/ for good: neither a new import nor a start removed them."""
    data = tmp_path / "data"
    with make_client(data):
        pass
    staging = data / "maps" / ".import-20261129T000000000000Z-0badf00d"  # killed after unpacking
    unpacking = data / "maps" / "..import-20261129T000001000000Z-0badf00d.tmp-x1y2"  # killed while unpacking
    for d in (staging, unpacking):
        d.mkdir()
        (d / "map.sqlite").write_bytes(b"\0" * 1024)
    other = DataDirLock(data / ".lock").acquire()  # an import still running: its files are in use
    try:
        with pytest.raises(DataDirectoryInUse), make_client(data, lock_wait_s=0):
            pass
        assert staging.is_dir() and unpacking.is_dir()
    finally:
        other.release()
    with make_client(data) as c:
        assert c.get("/readyz").status_code == 200
    assert not staging.exists() and not unpacking.exists()
    assert sorted(p.name for p in (data / "maps").iterdir()) == ["default"]
