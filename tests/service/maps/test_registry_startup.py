"""The map registry at startup and at creation (docs/design/service.md §1.1, §4.4): a map that cannot be
opened fails alone, and a refused creation never loads a network."""

from __future__ import annotations

import json
import sqlite3

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
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
        assert c.get("/v1/maps/lab/memory").status_code == 503
        assert c.get("/v1/maps/lab/snapshots").status_code == 200
        # (another stream: the default stream's own last row is not an answer to it, science.md §11.6)
        assert post(c, frame(2), learn="false", stream="probe").json()["matches"][0]["seq"] == 1
        assert post(c, frame(3)).status_code == 200
        assert c.delete("/v1/maps/lab").status_code == 204
        assert c.get("/v1/maps/lab").status_code == 404


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
