"""`CORTEXLOC_API_KEY_READS` (issue 19 item 7; docs/design/service.md §8): every `/v1` read and `/metrics`
need the key, the probes (/healthz, /readyz), the viewer's page and the API description stay open.
Found from outside: map lists, stream names (robot names), memory, the snapshot list and the map ids
in /metrics were open with the setting on."""

from __future__ import annotations

import re
import sqlite3

import pytest

from service.routes.health import UNNAMED_ERROR
from service.routing import iter_routes
from storage.catalog import StoreClosed
from tests.service.helpers import frame, make_client

KEY = {"X-API-Key": "k3y"}
#: Reads that stay open with the setting: the probes, the page of the viewer, the API's description.
OPEN = {"/healthz", "/readyz", "/docs", "/redoc", "/openapi.json", "/docs/oauth2-redirect", "/ui"}


def _filled(path: str, values: dict[str, str]) -> str:
    return re.sub(r"\{(\w+)(?::path)?\}", lambda m: values[m.group(1)], path)


@pytest.fixture(scope="module")
def guarded(tmp_path_factory):
    with make_client(tmp_path_factory.mktemp("reads") / "var", api_key="k3y", api_key_reads=True) as c:
        assert c.post("/v1/maps", json={"map_id": "yard", "thumbnails": True}, headers=KEY).status_code == 201
        r = c.post("/v1/maps/yard/observations", content=frame(0), params={"stream": "robot7/cam0"},
                   headers={"Content-Type": "image/png", **KEY})
        assert r.status_code == 200, r.text
        snap = c.post("/v1/maps/yard/snapshots", headers=KEY)
        assert snap.status_code == 201, snap.text
        recent = c.get("/v1/maps/yard/recent", headers=KEY).json()["answers"]
        values = {"map_id": "yard", "seq": str(r.json()["seq"]), "snapshot_id": snap.json()["snapshot_id"],
                  "stream": "robot7/cam0", "answer_id": str(recent[0]["answer_id"])}
        yield c, values


def _get_paths(c) -> list[str]:
    return sorted({route.path for route in iter_routes(c.app.router.routes)
                   if "GET" in (getattr(route, "methods", None) or ())})


def test_every_v1_read_and_metrics_need_the_key(guarded):
    c, values = guarded
    paths = _get_paths(c)
    assert {"/v1/maps", "/v1/maps/{map_id}/memory", "/v1/maps/{map_id}/snapshots", "/metrics"} <= set(paths)
    for path in paths:
        url = _filled(path, values)
        without = c.get(url)
        if path in OPEN:
            assert without.status_code == 200, (path, without.text)
            assert "robot7" not in without.text, path
            continue
        assert without.status_code == 401, (path, without.status_code)
        assert without.headers["content-type"].startswith("application/problem+json")
        assert "robot7" not in without.text and "yard" not in without.text.replace("/v1/maps/yard", "")
        wrong = c.get(url, headers={"X-API-Key": "nope"})
        assert wrong.status_code == 401, path
        assert c.get(url, headers=KEY).status_code == 200, path
        assert c.get(url, headers={"Authorization": "Bearer k3y"}).status_code == 200, path


def test_an_unknown_map_is_a_401_without_the_key_not_a_404(guarded):
    c, _ = guarded
    assert c.get("/v1/maps/nosuchmap").status_code == 401
    assert c.get("/v1/maps/nosuchmap", headers=KEY).status_code == 404


def test_readyz_stays_open_but_names_no_map_or_stream(guarded):
    c, values = guarded
    r = c.get("/readyz")
    assert r.status_code == 200, r.text
    maps = r.json()["checks"]["maps"]
    assert maps["count"] == 2 and maps["states"] == {"ready": 2}  # `yard` and the `default` map
    assert values["map_id"] not in r.text and "robot7" not in r.text and "default" not in r.text
    # nor a path of the host: the data directory, the catalog, the weights file
    assert all("path" not in check for check in r.json()["checks"].values()), r.json()["checks"]
    assert str(c.app.state.settings.data_dir) not in r.text


def test_a_failed_catalog_is_said_without_its_path_where_reads_need_the_key(tmp_path, caplog, monkeypatch):
    # found from outside: the reasons of a closed catalog and of one a newer version wrote named its path
    data = tmp_path / "var"
    with make_client(data, api_key="k3y", api_key_reads=True) as c:
        catalog = c.app.state.registry.catalog
        monkeypatch.setattr(catalog, "_tables", lambda: (_ for _ in ()).throw(StoreClosed(
            f"{catalog.path}: catalog is closed")))  # as `Catalog.close` leaves it, the app kept whole
        r = c.get("/readyz")
        assert r.status_code == 503 and r.json()["checks"]["catalog"]["error"] == UNNAMED_ERROR
        assert str(tmp_path) not in r.text
        assert any(str(data) in m for m in caplog.messages)  # the operator reads it in the log
        monkeypatch.undo()
    con = sqlite3.connect(data / "catalog.sqlite")
    con.execute("UPDATE meta SET value = '99' WHERE key = 'schema_version'")
    con.commit()
    con.close()
    for reads, shown in ((True, False), (False, True)):
        with make_client(data, api_key="k3y", api_key_reads=reads) as c:
            r = c.get("/readyz")
            assert r.status_code == 503 and (str(data) in r.text) is shown, r.text
            assert "newer" in r.text or not shown


def test_readyz_without_the_setting_shows_the_paths_an_operator_reads(tmp_path):
    with make_client(tmp_path / "var", api_key="k3y") as c:
        checks = c.get("/readyz").json()["checks"]
        assert checks["data_dir"]["path"] == str(c.app.state.settings.data_dir)
        assert checks["catalog"]["path"].endswith("catalog.sqlite")


def test_the_viewer_page_stays_open(guarded):
    c, _ = guarded
    assert c.get("/ui/").status_code == 200


def test_without_the_setting_reads_stay_open_and_writes_need_the_key(tmp_path):
    with make_client(tmp_path / "var", api_key="k3y") as c:
        for url in ("/v1/maps", "/v1/maps/default", "/v1/maps/default/memory", "/v1/maps/default/snapshots",
                    "/metrics"):
            assert c.get(url).status_code == 200, url
        assert c.post("/v1/maps", json={"map_id": "x"}).status_code == 401


def test_a_key_sent_with_whitespace_at_its_ends_is_the_key():
    """An outside probe: `X-API-Key: k3y ` (a trailing space) was refused while a leading one was taken:
    the HTTP parser drops only the leading whitespace of a field value, which has none at either end
    (RFC 9110 §5.5). Whitespace inside is part of the value: another key."""
    from fastapi.security import HTTPAuthorizationCredentials

    from service.deps import require_api_key
    from service.errors import Problem
    from service.settings import Settings

    s = Settings(api_key="k3y")
    for given in ("k3y", "k3y ", "k3y\t", " k3y \t"):
        require_api_key(s, given, None)
        require_api_key(s, None, HTTPAuthorizationCredentials(scheme="Bearer", credentials=given))
    for wrong in ("k3 y", "k3y x", "", " "):
        with pytest.raises(Problem):
            require_api_key(s, wrong or None, None)
    # a key set with whitespace at its ends (an env file's trailing space) is read as a client sends it
    require_api_key(Settings(api_key="k3y \t"), "k3y", None)
    assert Settings(api_key=" k3y").api_key == "k3y"
    with pytest.raises(ValueError):
        Settings(api_key=" \t")  # no key at all
