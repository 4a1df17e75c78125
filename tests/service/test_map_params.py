"""Map creation overrides at the HTTP edge (issue 11, item 9): every `tm` and `slsbh` override is checked
for name, type and range where parameters are resolved, and a bad one is a 422 invalid-configuration
naming it, never a 500, and creates nothing."""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient

from models import presets
from service.errors import PROBLEM_MEDIA_TYPE
from service.maps.params import resolve_params
from tests.service.helpers import make_app


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


def test_every_bad_parameter_is_reported_at_once(client):
    r = client.post("/v1/maps", json={"tm": {"columnDimensions": "x", "seed": -1}, "slsbh": {"s": 2}})
    assert r.status_code == 422
    assert {e["name"] for e in r.json()["errors"]} == {"tm.columnDimensions", "tm.seed", "slsbh.s"}


def test_good_overrides_are_frozen_as_given(client):
    r = client.post("/v1/maps", json={"map_id": "lab", "seed": 7, "tm": {"cellsPerColumn": 2,
                                                                       "permanenceDecrement": 0},
                                      "slsbh": {"s": 0.2, "adapt_tau": 3}})
    assert r.status_code == 201, r.text
    params = r.json()["params"]
    assert params["seed"] == 7 and params["tm"]["seed"] == 7 and params["slsbh"]["seed"] == 7
    assert params["tm"]["cellsPerColumn"] == 2 and params["tm"]["permanenceDecrement"] == 0
    assert params["slsbh"] == {"k": 64, "s": 0.2, "seed": 7, "adapt_tau": 3}


def test_one_home_for_the_parameter_rules():
    # The defaults are the models'; the service resolves through the same checks as the TM itself.
    assert presets.TmParams().model_dump() == presets.TM_DEFAULTS
    with pytest.raises(presets.ParamsError) as info:
        presets.check_section(presets.TmParams, "tm", {"columnDimensions": "x"})
    assert info.value.errors[0][0] == "columnDimensions"
    assert resolve_params("cortexloc-grid", seed=3)["slsbh"] == {"k": 1024, "s": 0.25, "seed": 3,
                                                                 "adapt_tau": 0}
