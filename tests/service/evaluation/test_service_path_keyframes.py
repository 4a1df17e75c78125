"""The evaluation's path verifies revisits as the service does (issue 38 item 4; docs/design/science.md
§12, §11.4): on a map with keyframes and `verify_revisit`, frames of 320 x 240 (verification needs
96 px or more; the 64 x 32 Nordland frames are too small), `replay` and `slam_replay` given the encoded
frames answer, verify and refuse exactly as HTTP does, beyond the map's row cap too."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from service.evaluation import service_path
from tests.service.helpers import make_client, post

pytest.importorskip("skimage", reason="scikit-image (dev extra) ships the real images")

from models.evaluation.geometry import rotation, warp
from tests.service.maps.test_keyframes import CAMERA, CAMERA_META, KEYFRAMES, ROUTE, UNRELATED, png, sized

#: A route of ten photographs is shorter than a stream's short-term memory (20 moves, §11.6): without it
#: the stream's laps can close on each other.
# no span gate (docs/design/science.md §11.11) nor lag gate (§11.13): at threshold 0 the verification
# alone decides, as in tests/service/maps/test_keyframes.py
NO_GATE = {"span_max": 4096, "lag_max": 1_000_000}
SHORT = {"short_term": 0, **NO_GATE}
MAP = {"keyframes": KEYFRAMES, "revisit_threshold": 0.0, "verify_revisit": True}


def _verification(v) -> tuple | None:
    """What a verification decided: verified, the keyframe, its inliers and why (not its milliseconds)."""
    if v is None:
        return None
    d = v if isinstance(v, dict) else dataclasses.asdict(v)
    return d["verified"], d["keyframe_seq"], d["inliers"], d["model"], d["reason"]


def _features(c, bodies: list[bytes]) -> tuple[np.ndarray, dict]:
    """The bodies' backbone features as the pool embeds them, and the `replay` keywords of map `kf`."""
    enc = c.app.state.encoder
    resize = c.app.state.registry.get("kf").config.resize
    feats = np.concatenate([enc.embed([b], resize=resize).features for b in bodies])
    return feats, {"encoder_id": enc.identity_for(resize), "backbone": "alexnet", "seed": 7,
                   "preset": c.app.state.settings.default_preset, "create": {"resize": resize, **MAP},
                   "localiser": NO_GATE, "camera": CAMERA_META["camera"]}


def test_replay_verifies_and_refuses_the_revisits_http_does(tmp_path):
    """A mapper's route learned, then a robot with its camera turned 5 degrees drives it and then
    unrelated frames: the evaluation's revisits are the service's verified ones, each verification alike
    (the keyframe, its inliers, its reason), and the refused candidates score confidence 0."""
    db = [png(sized(n)) for n in ROUTE]
    query = ([png(warp(sized(n), CAMERA, rotation(5, 0, 0))) for n in ROUTE]
             + [png(sized(n)) for n in UNRELATED * 2])
    meta = json.dumps(CAMERA_META)
    with make_client(tmp_path / "data") as c:
        made = c.post("/v1/maps", json={"map_id": "kf", "seed": 7, **MAP, "localiser": NO_GATE})
        assert made.status_code == 201
        for b in db:
            post(c, b, map_id="kf", stream="database", top_k=0, metadata=meta)
        http = [post(c, b, map_id="kf", stream="query", learn="false", top_k=0,
                     **({"metadata": meta} if i == 0 else {})).json()["place"] for i, b in enumerate(query)]
        db_feats, conf = _features(c, db)
        q_feats, _ = _features(c, query)
    trace: dict = {}
    found = service_path.replay(db_feats, q_feats, frames=db + query, trace=trace,
                                contrast=service_path.contrasts(db + query), **conf)
    answered = [p for p in http if p is not None]
    verified = [p for p in answered if p["verification"]["verified"]]
    assert len(verified) >= 4 and len(answered) - len(verified) >= 4  # both sides are exercised
    assert trace["revisit"].tolist() == [p is not None and p["revisit"] for p in http]
    assert [_verification(v) for v in trace["verification"]] == [
        None if p is None else _verification(p["verification"]) for p in http]
    want = [None if p is None else (p["seq"] - 1, p["confidence"] if p["revisit"] else 0.0, p["support"])
            for p in http]
    got = [None if b < 0 else (int(b), float(cf), int(s))
           for b, cf, s in zip(found.best, found.confidence, found.support, strict=True)]
    assert got == want


def test_slam_replay_beyond_its_cap_verifies_the_revisits_http_does(tmp_path):
    """One learning stream over the route, unrelated frames, the route turned, and the route again, into
    a map of 20 rows: forgetting at the cap and verifying against the keyframes held, `slam_replay`
    keeps the rows, answers and verifies (and refuses) as HTTP does."""
    turned = [png(warp(sized(n), CAMERA, rotation(0, 0, 8))) for n in ROUTE]
    laps = [png(sized(n)) for n in ROUTE] + [png(sized(n)) for n in UNRELATED] + turned + [
        png(sized(n)) for n in ROUTE]
    meta = json.dumps(CAMERA_META)
    with make_client(tmp_path / "data", max_observations=20) as c:
        made = c.post("/v1/maps", json={"map_id": "kf", "seed": 7, **MAP, "localiser": SHORT})
        assert made.status_code == 201
        http = [post(c, b, map_id="kf", stream="robot", top_k=0, metadata=meta).json() for b in laps]
        rt = c.app.state.registry.get("kf")
        dropped, forgotten = rt.store.dropped(), rt.forgotten
        held = [r.seq not in dropped for r in rt.store.rows()]
        feats, conf = _features(c, laps)
    trace: dict = {}
    found, _ = service_path.slam_replay(feats, frames=laps, trace=trace, max_observations=20,
                                        contrast=service_path.contrasts(laps), **{**conf, "localiser": SHORT})
    places = [b["place"] for b in http]
    assert forgotten > 0 and trace["row_held"].tolist() == held
    assert trace["revisit"].tolist() == [p is not None and p["revisit"] for p in places]
    assert [_verification(v) for v in trace["verification"]] == [
        None if p is None else _verification(p["verification"]) for p in places]
    assert any(p["verification"]["verified"] for p in places if p) and not all(
        p["revisit"] for p in places if p)
    frame_of = {b["seq"]: i for i, b in enumerate(http) if b["seq"] is not None}  # rows made, by frame
    want = [None if p is None else (frame_of[p["seq"]], p["confidence"] if p["revisit"] else 0.0,
                                    p["support"]) for p in places]
    got = [None if b < 0 else (int(b), float(cf), int(s))
           for b, cf, s in zip(found.best, found.confidence, found.support, strict=True)]
    assert got == want
