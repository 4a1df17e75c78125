"""`--methods service` is the service's path: the same answers as HTTP for the same route
(service/evaluation/service_path.py), and the operating point read from per-query answers."""

from __future__ import annotations

import numpy as np
import pytest

from models.localisation import default_conf
from service.evaluation import service_path
from tests.service.helpers import frame, make_client, post

DB = list(range(14))
QUERY = [2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13]


@pytest.mark.parametrize("memory", ["tm", "none"])
def test_http_and_eval_give_the_same_places(tmp_path, memory):
    db_bodies = [frame(p) for p in DB]
    q_bodies = [frame(p, noise=4.0) for p in QUERY]
    with make_client(tmp_path / "data") as c:
        r = c.post("/v1/maps", json={"map_id": "route", "seed": 7, "memory": memory})
        assert r.status_code == 201
        for b in db_bodies:
            post(c, b, map_id="route", stream="database", top_k=0)
        http = [post(c, b, map_id="route", stream="query", learn="false", top_k=0).json()["place"]
                for b in q_bodies]
        enc = c.app.state.encoder
        preset = c.app.state.settings.default_preset
        # one image per call, as the pool embeds a lone request
        resize = c.app.state.registry.get("route").config.resize  # the map's mode, as the pool uses it
        db_feats = np.concatenate([enc.embed([b], resize=resize).features for b in db_bodies])
        q_feats = np.concatenate([enc.embed([b], resize=resize).features for b in q_bodies])
    found = service_path.replay(db_feats, q_feats, encoder_id=enc.identity_for(resize), backbone="alexnet",
                                preset=preset, seed=7, memory=memory, create={"resize": resize})
    assert _found(found) == _places(http)
    assert sum(p is not None for p in http) >= len(QUERY) - 4


def test_operating_point_is_the_lowest_threshold_reaching_the_precision():
    conf = np.array([0.9, 0.8, 0.7, 0.6, 0.5, 0.4])
    right = np.array([True, True, True, False, True, False])
    assert service_path.operating_point(conf, right, 1.0) == {"threshold": 0.7, "precision": 1.0,
                                                              "recall": 0.5}
    point = service_path.operating_point(conf, right, 0.8)
    assert point is not None and point["threshold"] == 0.5 and point["precision"] == 0.8
    assert service_path.operating_point(conf, ~right, 0.99) is None
    # equal confidences stand or fall together
    tied = service_path.operating_point(np.array([0.9, 0.9]), np.array([True, False]), 0.9)
    assert tied is None


def test_the_service_path_experiments_are_eval_commands():
    from typer.testing import CliRunner

    from service.cli import app

    out = CliRunner().invoke(app, ["eval", "--help"]).output
    assert all(name in out for name in ("grid", "images", "revisit", "unknown"))


@pytest.mark.parametrize("memory", ["tm", "none"])
def test_http_and_slam_replay_give_the_same_places_for_one_learning_stream(tmp_path, memory):
    """`service-slam`: two laps posted as one learning stream over HTTP and through `slam_replay` answer
    alike, frame for frame (the own-trail rule included). The lap is longer than the stream's short-term
    memory (docs/design/science.md §11.6): a shorter one does not close."""
    route = list(range(30))
    laps = [frame(p) for p in route] + [frame(p, noise=4.0) for p in route]
    with make_client(tmp_path / "data") as c:
        assert c.post("/v1/maps", json={"map_id": "route", "seed": 7, "memory": memory}).status_code == 201
        http = [post(c, b, map_id="route", stream="robot", top_k=0).json() for b in laps]
        map_threshold = c.get("/v1/maps/route").json()["revisit_threshold"]
        enc = c.app.state.encoder
        preset = c.app.state.settings.default_preset
        resize = c.app.state.registry.get("route").config.resize  # the map's mode, as the pool uses it
        feats = np.concatenate([enc.embed([b], resize=resize).features for b in laps])
    found, threshold = service_path.slam_replay(
        feats, encoder_id=enc.identity_for(resize), backbone="alexnet", preset=preset, seed=7, memory=memory,
        create={"resize": resize})
    assert _found(found) == _places(b["place"] for b in http)
    assert threshold == map_threshold
    assert all(b < i for i, b in enumerate(found.best))  # never the frame's own row, nor a later one
    second = found.best[len(route) + 6:]
    assert np.mean(second == np.arange(6, len(route))) > 0.8  # lap 2 names lap 1


def test_the_evaluation_measures_and_decides_low_information_frames_as_the_service_does(tmp_path):
    """Dark frames in both laps: `slam_replay` with `contrasts` of the same images answers as HTTP, and
    scores a frame the service marks `low_information` at confidence 0 (never a revisit, §11.7)."""
    from tests.service.maps.test_loop_closures import dark

    lap2 = [frame(p, noise=4.0) for p in DB]
    laps = ([frame(p) for p in DB[:7]] + [dark(0), dark(1)] + [frame(p) for p in DB[7:]]
            + lap2[:7] + [dark(2), dark(3)] + lap2[7:])
    with make_client(tmp_path / "data") as c:
        assert c.post("/v1/maps", json={"map_id": "route", "seed": 7}).status_code == 201
        http = [post(c, b, map_id="route", stream="robot", top_k=0).json()["place"] for b in laps]
        enc = c.app.state.encoder
        preset = c.app.state.settings.default_preset
        resize = c.app.state.registry.get("route").config.resize
        feats = np.concatenate([enc.embed([b], resize=resize).features for b in laps])
    contrast = service_path.contrasts(laps)
    found, _ = service_path.slam_replay(feats, encoder_id=enc.identity_for(resize), backbone="alexnet",
                                        preset=preset, seed=7, create={"resize": resize}, contrast=contrast)
    flat = [i for i, p in enumerate(http) if p is not None and p["low_information"]]
    assert flat == [i for i in (7, 8, 23, 24) if http[i] is not None] and flat[-2:] == [23, 24]
    assert _found(found) == _places(http)


def _places(places, frame_of: dict[int, int] | None = None) -> list[tuple[int, float, int] | None]:
    """HTTP `place` answers as (row seq - 1, or the frame that made the row, confidence, support), None
    in warm-up."""
    return [None if p is None else (p["seq"] - 1 if frame_of is None else frame_of[p["seq"]],
                                    _decided(p), p["support"]) for p in places]


def _decided(p: dict) -> float:
    """The confidence the revisit decision compares, as the evaluation reads it: 0 where the span is wider
    than span_max (docs/design/science.md §11.11), the frame too flat (§11.7) or the path lagging
    (§11.13)."""
    gated = p["span"] > int(default_conf["span_max"]) or p["low_information"] or p["lagging"]
    return 0.0 if gated else p["confidence"]


def _found(found) -> list[tuple[int, float, int] | None]:
    return [None if b < 0 else (int(b), float(cf), int(s))
            for b, cf, s in zip(found.best, found.confidence, found.support, strict=True)]


def _held(rt) -> list[bool]:
    """Each stored row of the served map: still held (neither forgotten nor dropped over its place's cap)."""
    dropped = rt.store.dropped()
    return [r.seq not in dropped for r in rt.store.rows()]


@pytest.mark.parametrize("memory", ["tm", "none"])
def test_beyond_its_cap_the_slam_replay_forgets_the_rows_the_service_forgets(tmp_path, memory):
    """Issue 38 item 4: a map of 12 rows driven over three laps of 20 places as one learning stream
    forgets at its cap; the evaluation's path (`slam_replay` with the same cap) forgets the same rows,
    keeps the same ones and answers the same, frame for frame."""
    route = list(range(20))
    laps = [frame(p) for p in route] + [frame(p, noise=4.0) for p in route] + [frame(p, noise=6.0)
                                                                             for p in route]
    with make_client(tmp_path / "data", max_observations=12) as c:
        assert c.post("/v1/maps", json={"map_id": "route", "seed": 7, "memory": memory}).status_code == 201
        http = [post(c, b, map_id="route", stream="robot", top_k=0).json() for b in laps]
        rt = c.app.state.registry.get("route")
        held, forgotten = _held(rt), rt.forgotten
        places = c.get("/v1/maps/route").json()["places"]
        enc = c.app.state.encoder
        preset = c.app.state.settings.default_preset
        resize = rt.config.resize
        feats = np.concatenate([enc.embed([b], resize=resize).features for b in laps])
    trace: dict = {}
    found, _ = service_path.slam_replay(
        feats, encoder_id=enc.identity_for(resize), backbone="alexnet", preset=preset, seed=7, memory=memory,
        create={"resize": resize}, max_observations=12, trace=trace)
    assert forgotten >= 12 and places["forgotten"] == forgotten and places["max_rows"] == 12
    frame_of = {b["seq"]: i for i, b in enumerate(http) if b["seq"] is not None}  # rows made, by frame
    assert _found(found) == _places((b["place"] for b in http), frame_of)
    assert trace["row_held"].tolist() == held and sum(held) <= 12
    assert trace["revisit"].tolist() == [b["place"] is not None and b["place"]["revisit"] for b in http]


@pytest.mark.parametrize("memory", ["tm", "none"])
def test_beyond_its_cap_the_replay_localises_on_the_rows_the_service_keeps(tmp_path, memory):
    """Issue 38 item 4: a database traverse of 24 places into a map of 10 rows (forgetting at the cap),
    then a query traverse: `replay` with the same cap keeps the same rows and answers as HTTP."""
    db_places = list(range(24))
    db_bodies = [frame(p) for p in db_places]
    q_bodies = [frame(p, noise=4.0) for p in db_places[10:]]
    with make_client(tmp_path / "data", max_observations=10) as c:
        assert c.post("/v1/maps", json={"map_id": "route", "seed": 7, "memory": memory}).status_code == 201
        for b in db_bodies:
            post(c, b, map_id="route", stream="database", top_k=0)
        http = [post(c, b, map_id="route", stream="query", learn="false", top_k=0).json()["place"]
                for b in q_bodies]
        rt = c.app.state.registry.get("route")
        held, forgotten = _held(rt), rt.forgotten
        enc = c.app.state.encoder
        preset = c.app.state.settings.default_preset
        resize = rt.config.resize
        db_feats = np.concatenate([enc.embed([b], resize=resize).features for b in db_bodies])
        q_feats = np.concatenate([enc.embed([b], resize=resize).features for b in q_bodies])
    trace: dict = {}
    found = service_path.replay(db_feats, q_feats, encoder_id=enc.identity_for(resize), backbone="alexnet",
                                preset=preset, seed=7, memory=memory, create={"resize": resize},
                                max_observations=10, trace=trace)
    assert forgotten >= 14 and sum(held) <= 10 and held[-1]
    assert trace["row_held"].tolist() == held
    assert _found(found) == _places(http)
    assert sum(p is not None for p in http) >= len(q_bodies) - 4
    assert np.mean(found.best[4:] == np.arange(14, 24)) >= 0.8  # the rows kept: the route's last places
