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
    # the evaluation reads the confidence the revisit decision compares: 0 where the span is wider than
    # span_max (docs/design/science.md §11.11) or the frame too flat (§11.7)
    wide = int(default_conf["span_max"])
    want = [None if p is None else (p["seq"] - 1, 0.0 if p["span"] > wide or p["low_information"]
                                    else p["confidence"], p["support"]) for p in http]
    got = [None if b < 0 else (int(b), float(cf), int(s))
           for b, cf, s in zip(found.best, found.confidence, found.support, strict=True)]
    assert got == want
    assert sum(p is not None for p in want) >= len(QUERY) - 4


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
    want = [None if b["place"] is None else (b["place"]["seq"] - 1, b["place"]["confidence"],
                                             b["place"]["support"]) for b in http]
    got = [None if b < 0 else (int(b), float(cf), int(s))
           for b, cf, s in zip(found.best, found.confidence, found.support, strict=True)]
    assert got == want
    assert threshold == map_threshold
    assert all(b < i for i, b in enumerate(found.best))  # never the frame's own row, nor a later one
    second = found.best[len(route) + 6:]
    assert np.mean(second == np.arange(6, len(route))) > 0.8  # lap 2 names lap 1


def test_the_evaluation_measures_and_decides_low_information_frames_as_the_service_does(tmp_path):
    """Dark frames in both laps: `slam_replay` with `contrasts` of the same images answers as HTTP, and
    scores a frame the service marks `low_information` at confidence 0 (never a revisit, §11.7)."""
    from tests.service.test_loop_closures import dark

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
    want = [None if p is None else (p["seq"] - 1, 0.0 if p["low_information"] else p["confidence"],
                                    p["support"]) for p in http]
    got = [None if b < 0 else (int(b), float(cf), int(s))
           for b, cf, s in zip(found.best, found.confidence, found.support, strict=True)]
    assert got == want
