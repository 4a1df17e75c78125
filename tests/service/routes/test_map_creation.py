"""Map creation overrides at the HTTP edge (issue 11, item 9): every `tm`, `slsbh` and `localiser`
override is checked for name, type and range where parameters are resolved, and a bad one is a 422
invalid-configuration naming it, never a 500, and creates nothing."""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient

from models import presets
from models.localisation import HYPOTHESIS_BYTES, SequenceLocaliser, default_conf
from models.localisation.short_term import ShortTerm
from models.memory.temporal_memory import planned_bytes
from service.errors import PROBLEM_MEDIA_TYPE
from service.maps.config import MapOptions, resolve
from service.maps.ids import new_map_id
from tests.service.helpers import frame, make_app, post


@pytest.fixture
def client(tmp_path):
    app = make_app(tmp_path / "data")
    with TestClient(app) as c:
        yield c


BAD_OVERRIDES = [
    ({"tm": {"columnDimensions": "x"}}, "tm.columnDimensions"),
    ({"tm": {"columnDimensions": "128"}}, "tm.columnDimensions"),  # a string, even a numeric one
    ({"tm": {"columnDimensions": 128.5}}, "tm.columnDimensions"),
    ({"tm": {"cellsPerColumn": True}}, "tm.cellsPerColumn"),
    ({"tm": {"cellsPerColumn": None}}, "tm.cellsPerColumn"),
    ({"tm": {"cellsPerColumn": 0}}, "tm.cellsPerColumn"),
    ({"tm": {"columnDimensions": 10**30}}, "tm.columnDimensions"),
    ({"tm": {"seed": 1e400}}, "tm.seed"),
    ({"tm": {"seed": -1}}, "tm.seed"),
    ({"tm": {"seed": 2**64}}, "tm.seed"),
    ({"tm": {"initialPermanence": 1.5}}, "tm.initialPermanence"),
    ({"tm": {"permanenceDecrement": "0.1"}}, "tm.permanenceDecrement"),
    ({"tm": {"maxSynapsesPerSegment": 70000}}, "tm.maxSynapsesPerSegment"),
    ({"tm": {"maxSegmentsPerCell": [1]}}, "tm.maxSegmentsPerCell"),
    ({"tm": {"bogus": 1}}, "tm.bogus"),
    ({"seed": 2**64}, "tm.seed"),
    ({"slsbh": {"k": "x"}}, "slsbh.k"),
    ({"slsbh": {"s": 0.9}}, "slsbh.s"),
    ({"slsbh": {"s": "0.1"}}, "slsbh.s"),
    ({"slsbh": {"seed": 1e400}}, "slsbh.seed"),
    ({"slsbh": {"adapt_tau": 1.5}}, "slsbh.adapt_tau"),
    ({"slsbh": {"projection": "sparse"}}, "slsbh.projection"),
    ({"slsbh": {"k": 32}}, "slsbh.k"),  # 2k must equal columnDimensions (128 in the tests' preset)
    ({"tm": {"minThreshold": 20, "activationThreshold": 4}}, "tm.minThreshold"),
    # The localiser's options (models.localisation.LocaliserParams, docs/design/science.md §11.3): each of
    # these once reached the catalog, then failed every learned frame, every restart or the memory.
    ({"localiser": {"exclusion": "x"}}, "localiser.exclusion"),
    ({"localiser": {"exclusion": -5}}, "localiser.exclusion"),
    ({"localiser": {"beam": 10**9}}, "localiser.beam"),
    ({"localiser": {"top_k": 10**6}}, "localiser.top_k"),
    ({"localiser": {"temperature": float("inf")}}, "localiser.temperature"),
    ({"localiser": {"jump_cost": float("inf")}}, "localiser.jump_cost"),
    ({"localiser": {"backward": "no"}}, "localiser.backward"),
    ({"localiser": {"move_costs": [3, "x"]}}, "localiser.move_costs.1"),
    ({"localiser": {"beams": 3}}, "localiser.beams"),
]


@pytest.mark.parametrize(("payload", "name"), BAD_OVERRIDES, ids=[str(p) for p, _ in BAD_OVERRIDES])
def test_every_bad_override_is_a_422_naming_it(client, payload, name):
    text = json.dumps({"map_id": "lab", **payload}).replace("Infinity", "1e400")  # as a client sends it
    r = client.post("/v1/maps", content=text, headers={"Content-Type": "application/json"})
    assert r.status_code == 422, r.text
    assert r.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE)
    body = r.json()
    assert body["type"] == "urn:cortexloc:problem:invalid-configuration"
    assert name in [e["name"] for e in body["errors"]], body
    assert name.split(".")[-1] in body["detail"]
    assert [m["map_id"] for m in client.get("/v1/maps").json()["maps"]] == ["default"]
    assert client.get("/v1/maps/lab").status_code == 404


@pytest.mark.parametrize("body", ['{"map_id": "lab", "seed": true}', '{"map_id": "lab", "thumbnails": "yes"}',
                                  '{"map_id": "lab", "thumbnails": 1}', '{"map_id": "lab", "seed": "3"}',
                                  '{"map_id": "lab", "map_id": "lab2"}',
                                  '{"map_id": "lab", "tm": {"seed": 1, "seed": 2}}'])
def test_a_wrong_type_or_a_member_twice_at_the_top_is_a_400_and_makes_no_map(client, body):
    """Found from outside: `"seed": true` made a map of seed 1 and `"thumbnails": "yes"` one with
    thumbnails (inside the sections such values were refused), and a member given twice was read as the
    last (`{"map_id": "lab", "map_id": "lab2"}` made lab2)."""
    r = client.post("/v1/maps", content=body, headers={"Content-Type": "application/json"})
    assert r.status_code == 400 and r.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE), r.text
    assert r.json()["type"].endswith("invalid-parameter")
    assert [m["map_id"] for m in client.get("/v1/maps").json()["maps"]] == ["default"]
    assert client.post("/v1/maps", json={"map_id": "lab", "seed": 3, "thumbnails": True,
                                         "revisit_threshold": 1}).status_code == 201


def test_every_bad_parameter_is_reported_at_once(client):
    r = client.post("/v1/maps", json={"tm": {"columnDimensions": "x", "seed": -1}, "slsbh": {"s": 2},
                                      "localiser": {"warmup": 0}})
    assert r.status_code == 422
    assert {e["name"] for e in r.json()["errors"]} == {"tm.columnDimensions", "tm.seed", "slsbh.s",
                                                       "localiser.warmup"}


def test_good_overrides_are_frozen_as_given(client):
    r = client.post("/v1/maps", json={"map_id": "lab", "seed": 7, "tm": {"cellsPerColumn": 2,
                                                                       "permanenceDecrement": 0},
                                      "slsbh": {"s": 0.2, "adapt_tau": 3}})
    assert r.status_code == 201, r.text
    params = r.json()["params"]
    assert params["seed"] == 7 and params["tm"]["seed"] == 7 and params["slsbh"]["seed"] == 7
    assert params["tm"]["cellsPerColumn"] == 2 and params["tm"]["permanenceDecrement"] == 0
    assert params["slsbh"] == {"k": 64, "s": 0.2, "seed": 7, "adapt_tau": 3}


def test_good_localiser_options_serve_and_come_back_after_a_restart(tmp_path):
    data = tmp_path / "data"
    options = {"exclusion": 0, "beam": 4096, "move_costs": [1, 0, 1], "backward": False, "warmup": 1}
    with TestClient(make_app(data)) as c:
        r = c.post("/v1/maps", json={"map_id": "lab", "localiser": options})
        assert r.status_code == 201, r.text
        for place in range(3):
            assert post(c, frame(place), map_id="lab").status_code == 200
    with TestClient(make_app(data)) as c:
        m = c.get("/v1/maps/lab").json()
        assert m["state"] == "ready" and m["params"]["localiser"]["beam"] == 4096
        assert m["params"]["localiser"]["move_costs"] == [1.0, 0.0, 1.0]
        # (another robot: the stream that learned them has them in its short-term memory, §11.6)
        assert post(c, frame(1), map_id="lab", learn="false", stream="other").json()["place"] is not None


def test_every_streams_localiser_state_counts_in_the_map_size(tmp_path):
    # The beam is the state of each of max_streams streams (docs/design/service.md §1.1): a map whose
    # memory fits but whose streams' hypotheses would not is refused before anything is written.
    tm = resolve(MapOptions(), default_preset="cortexloc-default", default_backbone="alexnet").tm
    # each stream also keeps its condition: at most 2 + 2 x columns 8-byte values (science.md §11.10)
    condition = 8 * (2 * tm["columnDimensions"] + 2)
    # and its short-term memory (§11.6), two per stream slot
    condition += 2 * ShortTerm.nbytes(int(default_conf["short_term"]), tm["columnDimensions"])
    default_streams = 64 * (SequenceLocaliser().state_bytes() + condition)
    with TestClient(make_app(tmp_path / "data", max_streams=64,
                             max_map_bytes=planned_bytes(presets.TmOptions.of(tm)) + default_streams)) as c:
        r = c.post("/v1/maps", json={"map_id": "lab", "localiser": {"beam": 4096}})
        assert r.status_code == 422 and r.json()["type"] == "urn:cortexloc:problem:map-too-large", r.text
        tm_bytes = planned_bytes(presets.TmOptions.of(tm))
        assert str(tm_bytes + 64 * (4096 * HYPOTHESIS_BYTES + condition)) in r.json()["detail"]
        assert c.get("/v1/maps/lab").status_code == 404
        assert c.post("/v1/maps", json={"map_id": "lab", "localiser": {"beam": 256}}).status_code == 201


def test_one_home_for_the_parameter_rules():
    # The defaults are the models'; the service resolves through the same checks as the TM itself.
    assert presets.TmParams().model_dump() == presets.TM_DEFAULTS
    with pytest.raises(presets.ParamsError) as info:
        presets.check_section(presets.TmParams, "tm", {"columnDimensions": "x"})
    assert info.value.errors[0][0] == "columnDimensions"
    grid = resolve(MapOptions(preset="cortexloc-grid", seed=3), default_preset="x",
                   default_backbone="alexnet")
    assert grid.slsbh == {"k": 1024, "s": 0.25, "seed": 3, "adapt_tau": 0}


# ------------------------------------------------------------------ a full disk


def no_room_for_new_map_files(monkeypatch) -> None:
    """A new map.sqlite meets a full disk: its connection may not grow past one page, so the schema's
    script fails with SQLite's own SQLITE_FULL, outside any transaction (as a full disk fails it)."""
    import storage.mapschema as mapschema

    real = mapschema.connect

    def capped(path, **kw):
        conn = real(path, **kw)
        conn.execute("PRAGMA max_page_count = 1")
        return conn

    monkeypatch.setattr(mapschema, "connect", capped)


def test_a_map_created_on_a_full_disk_is_507_and_leaves_no_directory(client, monkeypatch):
    no_room_for_new_map_files(monkeypatch)
    r = client.post("/v1/maps", json={"map_id": "x2"})
    assert r.status_code == 507 and r.json()["type"].endswith("insufficient-storage"), r.text
    assert "nothing was created" in r.json()["detail"]
    maps_dir = client.app.state.registry.layout.maps
    assert not (maps_dir / "x2").exists() and sorted(p.name for p in maps_dir.iterdir()) == ["default"]
    assert [m["map_id"] for m in client.get("/v1/maps").json()["maps"]] == ["default"]
    monkeypatch.undo()  # room made: the same creation succeeds
    assert client.post("/v1/maps", json={"map_id": "x2"}).status_code == 201


def test_a_patch_on_a_full_disk_is_507_and_changes_nothing(client, monkeypatch):
    from storage.catalog import Catalog
    from storage.mapstore import StorageFull

    before = client.get("/v1/maps/default").json()

    def full(self, map_id, **changes):  # as the catalog's transaction raises SQLITE_FULL
        raise StorageFull("database or disk is full")

    monkeypatch.setattr(Catalog, "update_params", full)
    r = client.patch("/v1/maps/default", json={"revisit_threshold": 0.9})
    assert r.status_code == 507 and r.json()["type"].endswith("insufficient-storage"), r.text
    assert client.get("/v1/maps/default").json()["revisit_threshold"] == before["revisit_threshold"] != 0.9
    monkeypatch.undo()
    r = client.patch("/v1/maps/default", json={"revisit_threshold": 0.9})
    assert r.status_code == 200 and r.json()["revisit_threshold"] == 0.9


def test_a_keyed_creation_retried_answers_the_map_its_first_try_made(tmp_path):
    # A robot whose reply to POST /v1/maps was lost retries it: without a key that made a second map under
    # a new random id (or, with its own id, a 409 that did not say the map was its own).
    data = tmp_path / "data"
    body = {"seed": 3, "localiser": {"warmup": 2}}
    with TestClient(make_app(data)) as c:
        first = c.post("/v1/maps", json=body, headers={"Idempotency-Key": "create-key-1"})
        assert first.status_code == 201 and "Idempotent-Replayed" not in first.headers, first.text
        map_id = first.json()["map_id"]
        assert first.headers["Location"] == f"/v1/maps/{map_id}"
        assert c.patch(f"/v1/maps/{map_id}", json={"revisit_threshold": 0.5}).status_code == 200
        assert post(c, frame(0), map_id=map_id).status_code == 200
    with TestClient(make_app(data)) as c:  # across a restart: the key names the id, nothing is stored
        again = c.post("/v1/maps", json=body, headers={"Idempotency-Key": "create-key-1"})
        assert again.status_code == 200 and again.headers["Idempotent-Replayed"] == "true", again.text
        assert again.json()["map_id"] == map_id and again.headers["Location"] == f"/v1/maps/{map_id}"
        # the map as it is now: PATCHed since (not compared), its observation kept
        assert again.json()["revisit_threshold"] == 0.5 and again.json()["observations"] == 1
        assert [m["map_id"] for m in c.get("/v1/maps").json()["maps"]] == ["default", map_id]
        # the key again with other options: not this creation; nothing made, the map untouched
        other = c.post("/v1/maps", json={"seed": 4}, headers={"Idempotency-Key": "create-key-1"})
        assert other.status_code == 422, other.text
        assert other.json()["type"].endswith("idempotency-key-reused")
        assert other.json()["key"] == "create-key-1"
        # another key is another map; no key, a map each time
        assert c.post("/v1/maps", json=body, headers={"Idempotency-Key": "create-key-2"}).status_code == 201
        assert c.post("/v1/maps", json=body).status_code == 201
        assert c.post("/v1/maps", json=body).status_code == 201
        assert len(c.get("/v1/maps").json()["maps"]) == 5  # the service's "default" among them
        assert c.get(f"/v1/maps/{map_id}").json()["observations"] == 1


def test_a_keyed_creation_with_its_own_id(client):
    body = {"map_id": "lab", "seed": 3}
    assert client.post("/v1/maps", json=body, headers={"Idempotency-Key": "lab-key-01"}).status_code == 201
    again = client.post("/v1/maps", json=body, headers={"Idempotency-Key": "lab-key-01"})
    assert again.status_code == 200 and again.headers["Idempotent-Replayed"] == "true"
    # the key again with other options, the threshold (which PATCH changes) among them: reused, 422
    for changed in ({"seed": 4}, {"revisit_threshold": 0.2}, {"thumbnails": True}):
        other = client.post("/v1/maps", json={**body, **changed}, headers={"Idempotency-Key": "lab-key-01"})
        assert other.status_code == 422, other.text
        assert other.json()["type"].endswith("idempotency-key-reused")
    # another client's creation of the id, with the same options: its map is not this one's, 409 as
    # without a key (a robot told "created" would think the map its own)
    mine = client.post("/v1/maps", json=body, headers={"Idempotency-Key": "lab-key-02"})
    assert mine.status_code == 409 and mine.json()["type"].endswith("map-exists"), mine.text
    assert client.post("/v1/maps", json=body).status_code == 409  # no key: as before
    assert client.get("/v1/maps/lab").json()["params"]["seed"] == 3
    # a map made without a key is no keyed creation's, even under the id a key would give
    derived = new_map_id("late-key-01")
    assert client.post("/v1/maps", json={"map_id": derived, "seed": 3}).status_code == 201
    late = client.post("/v1/maps", json={"seed": 3}, headers={"Idempotency-Key": "late-key-01"})
    assert late.status_code == 409 and late.json()["type"].endswith("map-exists"), late.text
    client.delete(f"/v1/maps/{derived}")
    for bad in ("short", "x" * 129, "has space"):  # the observations' key rule
        r = client.post("/v1/maps", json={"seed": 5}, headers={"Idempotency-Key": bad})
        assert r.status_code in (400, 422) and r.headers["content-type"] == PROBLEM_MEDIA_TYPE, r.text
    assert [m["map_id"] for m in client.get("/v1/maps").json()["maps"]] == ["default", "lab"]
