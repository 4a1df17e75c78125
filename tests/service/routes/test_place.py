"""The sequence-level answer of every observation reply: `place` (docs/design/service.md §1.2,
docs/design/science.md §11), the revisit threshold (PATCH) and the backbone frozen per map."""

from __future__ import annotations

import math

from models.localisation import default_conf
from service.maps.config import DEFAULT_REVISIT_THRESHOLD
from tests.service.helpers import frame, make_client, post

ROUTE = list(range(12))
WARMUP = int(default_conf["warmup"])


def learn_route(c, places=ROUTE, stream="mapper") -> list[int]:
    return [post(c, frame(p), stream=stream, top_k=0).json()["seq"] for p in places]


def drive(c, places, stream="robot", noise=3.0) -> list[dict | None]:
    return [post(c, frame(p, noise=noise), learn="false", stream=stream, top_k=1).json()["place"]
            for p in places]


def test_place_is_null_during_warm_up_then_answers(tmp_path):
    with make_client(tmp_path / "data") as c:
        learn_route(c)
        places = drive(c, ROUTE[:WARMUP + 1])
    assert places[:WARMUP - 1] == [None] * (WARMUP - 1)
    assert all(p is not None for p in places[WARMUP - 1:])


def test_a_revisit_of_a_learned_route_answers_its_rows(tmp_path):
    with make_client(tmp_path / "data") as c:
        seqs = learn_route(c)
        places = drive(c, ROUTE)
        body = post(c, frame(ROUTE[-1], noise=3.0), learn="false", stream="robot").json()
    answered = [(i, p) for i, p in enumerate(places) if p is not None]
    assert len(answered) == len(ROUTE) - WARMUP + 1
    for i, p in answered[2:]:  # two frames after the warm-up the path is established
        assert p["seq"] == seqs[i] and p["stream"] == "mapper", (i, p)
        assert 1 <= p["support"] <= i + 1
    # On 12 stored rows each frame's evidence is small (docs/design/science.md §11.5): confidence rises
    # with every frame on the route and the last ones are revisits.
    conf = [p["confidence"] for _, p in answered]
    assert conf == sorted(conf) and conf[-1] <= 1.0
    assert all(p["revisit"] == (p["confidence"] >= DEFAULT_REVISIT_THRESHOLD) for _, p in answered)
    assert answered[-1][1]["revisit"] is True
    assert body["versions"]["backbone"] == "alexnet"
    assert set(body["place"]) == {"seq", "observation_id", "stream", "label", "confidence", "revisit",
                                  "support", "metadata", "verification", "low_information", "place_id",
                                  "span", "span_seqs", "lagging"}
    assert body["place"]["verification"] is None  # a map without keyframes verifies nothing
    assert body["place"]["low_information"] is False  # smooth scenes: every frame informative


def test_a_learning_stream_localises_against_what_was_stored_before(tmp_path):
    # a lap longer than the stream's short-term memory (docs/design/science.md §11.6)
    route = list(range(30))
    with make_client(tmp_path / "data") as c:
        first = learn_route(c, route)
        again = [post(c, frame(p, noise=3.0), stream="mapper", top_k=0).json() for p in route]
    late = [(b["place"], first[i]) for i, b in enumerate(again) if i >= WARMUP + 1]
    assert all(p is not None and p["seq"] == want for p, want in late), late
    # The stream's null led through the first traverse (nothing stored yet was a match): confidence
    # has to be earned again over the second (docs/design/science.md §11.5).
    conf = [p["confidence"] for p, _ in late]
    rising = conf[:8]  # (once sure, it stays sure: small moves near 1)
    assert rising == sorted(rising) and min(conf[8:]) > conf[0] + 0.5


def test_patch_revisit_threshold_is_durable_and_checked(tmp_path):
    data = tmp_path / "data"
    with make_client(data) as c:
        r = c.patch("/v1/maps/default", json={"revisit_threshold": 0.97})
        assert r.status_code == 200 and r.json()["revisit_threshold"] == 0.97
        for bad in (1.5, -0.1):
            r = c.patch("/v1/maps/default", json={"revisit_threshold": bad})
            assert r.status_code == 422, bad
            assert r.headers["content-type"].startswith("application/problem+json")
        for not_a_number in ("x", "0.5", True):  # strict: a string or a boolean is not a threshold
            assert c.patch("/v1/maps/default", json={"revisit_threshold": not_a_number}).status_code == 400
        assert c.get("/v1/maps/default").json()["revisit_threshold"] == 0.97
        assert c.patch("/v1/maps/nope", json={"revisit_threshold": 0.2}).status_code == 404
        zero = c.patch("/v1/maps/default", json={"revisit_threshold": -0.0})  # in range, stored as 0.0
        assert zero.status_code == 200 and '"revisit_threshold":0.0' in zero.text
        stored = c.app.state.registry.get("default").record.params["revisit_threshold"]
        assert math.copysign(1.0, stored) == 1.0
        c.patch("/v1/maps/default", json={"revisit_threshold": 0.97})
        learn_route(c)
        places = drive(c, ROUTE)
    assert all(p["revisit"] == (p["confidence"] >= 0.97) for p in places if p is not None)
    with make_client(data) as c:
        assert c.get("/v1/maps/default").json()["revisit_threshold"] == 0.97


def test_localiser_state_survives_snapshot_and_restart(tmp_path):
    def answers(c, places):
        return [None if p is None else (p["seq"], round(p["confidence"], 9), p["support"])
                for p in drive(c, places)]

    with make_client(tmp_path / "twin") as c:
        learn_route(c)
        expected = answers(c, ROUTE)
    data = tmp_path / "restarted"
    with make_client(data) as c:
        learn_route(c)
        got = answers(c, ROUTE[:7])
    with make_client(data) as c:  # the clean shutdown's snapshot holds the stream
        got += answers(c, ROUTE[7:])
    assert got == expected


def test_backbone_is_frozen_with_the_map_and_shown(tmp_path):
    with make_client(tmp_path / "data") as c:
        m = c.get("/v1/maps/default").json()
        assert m["backbone"] == "alexnet" and m["params"]["memory"] == "tm"
        r = c.post("/v1/maps", json={"map_id": "ablation", "memory": "none", "backbone": "alexnet"})
        assert r.status_code == 201 and r.json()["params"]["memory"] == "none"
        bad = c.post("/v1/maps", json={"map_id": "bad", "backbone": "vgg"})
        assert bad.status_code == 422 and bad.json()["errors"][0]["name"] == "backbone"
        assert c.post("/v1/maps", json={"map_id": "bad", "memory": "lstm"}).status_code == 422
        assert c.get("/v1/maps/bad").status_code == 404


def test_the_default_backbone_is_resolved_once_at_startup(tmp_path):
    from service.frontend import resolve_backbone
    from service.maps.config import MapConfig
    from service.settings import Settings

    # no AlexNet weights are installed in the tests (conftest): EfficientNet-Lite0's stage 5, pooled 2x2
    assert resolve_backbone(Settings(data_dir=tmp_path)).backbone == "efficientnet-lite0-s5"
    weights = tmp_path / "alexnet.pth"
    weights.write_bytes(b"not read here")
    assert resolve_backbone(Settings(data_dir=tmp_path, weights_path=weights)).backbone == "alexnet"
    assert resolve_backbone(Settings(data_dir=tmp_path, backbone="alexnet")).backbone == "alexnet"
    assert MapConfig.model_fields["backbone"].default == "alexnet"  # a map made before the option


def test_a_never_learned_route_is_never_a_revisit(tmp_path):
    # A robot on a new route must not be told it has been here, not even on its first answers (a false
    # loop closure corrupts a SLAM graph); the same robot back on the learned route is (§11.5).
    with make_client(tmp_path / "data") as c:
        learn_route(c)
        unknown = drive(c, range(100, 125), stream="explorer")
        known = drive(c, ROUTE, stream="robot")
    answered = [p for p in unknown if p is not None]
    assert len(answered) == 25 - WARMUP + 1
    assert not any(p["revisit"] for p in answered), [round(p["confidence"], 2) for p in answered]
    assert max(p["confidence"] for p in answered) < 0.5
    assert known[-1]["revisit"] is True
