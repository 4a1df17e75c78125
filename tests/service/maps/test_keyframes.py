"""Keyframes and the verification of a revisit over HTTP (issue 27 items 1 and 2; docs/design/science.md
§12, docs/design/service.md §1.1–§1.2): the `keyframes` option, `place.verification` with the relative
rotation from a camera given once per stream, refusal of unrelated frames and of frames too small, the
`verify_revisit` option (PATCH), the sizes, keyframes through a snapshot, a restore and a restart, and
(item 3) the loop-closure log and its exports, g2o included, carrying the verified relative pose."""

from __future__ import annotations

import csv
import dataclasses
import io
import json

import cv2
import numpy as np
import pytest

from service.maps.closures import VISIT_VERTEX_BASE
from storage.mapstore import MapStore
from tests.service.helpers import make_client, post

pytest.importorskip("skimage", reason="scikit-image (dev extra) ships the real images")

from models.evaluation.geometry import PHOTOS, photo, photo_camera, rotation, warp

KEYFRAMES = {"features": "orb", "max": 500}
# The featureless clock first: every later route row has features (a verification of the last one
# tries its neighbours, and the clock is one only of the first two).
ROUTE = ("clock", *(n for n in PHOTOS if n != "clock"))
UNRELATED = ("hubble_deep_field", "retina", "immunohistochemistry", "page")


def png(rgb: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    return buf.tobytes()


def sized(name: str, w: int = 320, h: int = 240) -> np.ndarray:
    return cv2.resize(photo(name), (w, h), interpolation=cv2.INTER_AREA)


CAMERA = photo_camera(np.zeros((240, 320, 3), np.uint8))
CAMERA_META = {"camera": {"fx": CAMERA.fx, "fy": CAMERA.fy, "cx": CAMERA.cx, "cy": CAMERA.cy,
                          "distortion": [0.0, 0.0, 0.0, 0.0]}}


def make_map(c, map_id: str = "kf", **more) -> dict:
    # Threshold 0, no span gate (docs/design/science.md §11.11) and no lag gate (§11.13: these tests
    # drive unlike frames over a few rows, which no path keeps pace with): every answer is a revisit
    # candidate, so the verification is what these tests see decide.
    body = {"map_id": map_id, "keyframes": KEYFRAMES, "revisit_threshold": 0.0,
            "localiser": {"span_max": 4096, "lag_max": 1_000_000}, **more}
    r = c.post("/v1/maps", json=body)
    assert r.status_code == 201, r.text
    return r.json()


def learn(c, frames, map_id: str = "kf", meta: dict = CAMERA_META) -> list[int]:
    return [post(c, png(f), map_id=map_id, stream="mapper", top_k=0,
                 metadata=json.dumps(meta)).json()["seq"] for f in frames]


def drive(c, frames, map_id: str = "kf", camera_once: bool = True,
          meta: dict = CAMERA_META) -> list[dict | None]:
    """Localise `frames` on stream `robot`; the camera rides on the first frame only (once per stream)."""
    out = []
    for i, f in enumerate(frames):
        given = {} if (camera_once and i) else {"metadata": json.dumps(meta)}
        r = post(c, png(f), map_id=map_id, stream="robot", learn="false", top_k=0, **given)
        assert r.status_code == 200, r.text
        out.append(r.json()["place"])
    return out


def test_a_revisit_is_verified_with_the_relative_rotation_of_the_stream_camera(tmp_path):
    turn = rotation(5, 0, 0)  # the robot's camera is turned 5 degrees to the right of the mapper's
    with make_client(tmp_path / "data") as c:
        made = make_map(c)
        assert made["params"]["keyframes"] == KEYFRAMES and made["verify_revisit"] is False
        seqs = learn(c, [sized(n) for n in ROUTE])
        places = drive(c, [warp(sized(n), CAMERA, turn) for n in ROUTE])
        sizes = c.get("/v1/maps/kf/memory").json()["storage"]
    answered = [(i, p) for i, p in enumerate(places) if p is not None]
    assert len(answered) >= 4
    for i, p in answered[1:]:  # the path is established: the right row, verified with its pose
        v = p["verification"]
        assert p["seq"] == seqs[i] and p["revisit"] and v["verified"], (i, p)
        assert v["keyframe_seq"] == seqs[i] and v["model"] == "homography" and v["inliers"] >= 25
        assert abs(v["rotation_deg"] - 5.0) < 1.0 and np.allclose(np.array(v["rotation"]), turn, atol=0.03)
        assert v["translation"] is None and v["reason"] == "translation-unobservable"
    # Every learned row's features are stored, and counted where the map's sizes are reported.
    assert sizes["keyframes"] == len(ROUTE) and 0 < sizes["keyframe_bytes"] <= len(ROUTE) * (16 + 500 * 40)


def test_unrelated_frames_are_refused_and_verify_revisit_makes_them_no_revisit(tmp_path):
    with make_client(tmp_path / "data") as c:
        make_map(c)
        learn(c, [sized(n) for n in ROUTE])
        frames = [sized(n) for n in UNRELATED * 3]  # beyond the localiser's warm-up
        loose = drive(c, frames)  # verification only reports
        patched = c.patch("/v1/maps/kf", json={"verify_revisit": True})
        assert patched.status_code == 200 and patched.json()["verify_revisit"] is True, patched.text
        strict = drive(c, frames)
    for p in [p for p in loose + strict if p is not None]:
        assert p["verification"]["verified"] is False and p["verification"]["reason"], p
    # Every answer is a revisit candidate (threshold 0); only the verification can refuse it.
    assert [p["revisit"] for p in loose if p] and all(p["revisit"] for p in loose if p)
    assert [p for p in strict if p] and not any(p["revisit"] for p in strict if p)


def test_verify_revisit_is_durable_and_checked(tmp_path):
    data = tmp_path / "data"
    with make_client(data) as c:
        make_map(c, verify_revisit=True)
        assert c.patch("/v1/maps/kf", json={"verify_revisit": False}).json()["verify_revisit"] is False
        both = {"verify_revisit": True, "revisit_threshold": 0.5}
        assert c.patch("/v1/maps/kf", json=both).status_code == 200
        plain = c.post("/v1/maps", json={"map_id": "plain"}).json()
        assert plain["verify_revisit"] is False and plain["params"]["keyframes"] is None
        refused = c.patch("/v1/maps/plain", json={"verify_revisit": True, "revisit_threshold": 0.5})
        assert refused.status_code == 422 and "keyframes" in refused.text
        assert c.get("/v1/maps/plain").json()["revisit_threshold"] != 0.5  # nothing changed
        assert c.patch("/v1/maps/kf", json={}).status_code in (400, 422)
        assert c.patch("/v1/maps/kf", json={"verify_revisit": "yes"}).status_code in (400, 422)
        made = c.post("/v1/maps", json={"map_id": "nokf", "verify_revisit": True})
        assert made.status_code == 422 and made.json()["errors"][0]["name"] == "verify_revisit"
    with make_client(data) as c:
        again = c.get("/v1/maps/kf").json()
        assert (again["verify_revisit"], again["revisit_threshold"]) == (True, 0.5)


@pytest.mark.parametrize(("value", "name"), [({"features": "surf"}, "keyframes.features"),
                                             ({"features": "orb", "max": 10}, "keyframes.max"),
                                             ({"features": "orb", "count": 5}, "keyframes.count"),
                                             ({"max": "500"}, "keyframes.max")])
def test_a_bad_keyframes_option_is_refused_naming_it(tmp_path, value, name):
    with make_client(tmp_path / "data") as c:
        r = c.post("/v1/maps", json={"map_id": "bad", "keyframes": value})
        assert r.status_code == 422, r.text
        assert name in [e["name"] for e in r.json()["errors"]]
        assert c.get("/v1/maps/bad").status_code == 404


def test_frames_too_small_are_not_verifiable(tmp_path):
    frames = [sized(n, 64, 32) for n in ROUTE]
    # The camera of these frames (one for 320 x 240 ones is refused: its principal point is outside).
    meta = {"camera": {"fx": 57.6, "fy": 57.6, "cx": 32.0, "cy": 16.0, "distortion": [0.0, 0.0, 0.0, 0.0]}}
    with make_client(tmp_path / "data") as c:
        make_map(c)
        learn(c, frames, meta=meta)
        places = drive(c, frames, meta=meta)
        sizes = c.get("/v1/maps/kf/memory").json()["storage"]
    answered = [p for p in places if p is not None]
    assert answered and all(not p["verification"]["verified"] and p["verification"]["reason"] == "too-small"
                            for p in answered), answered
    # Stored with a header and no features (and the camera).
    camera = len(json.dumps(meta["camera"], separators=(",", ":")))
    assert sizes["keyframes"] == len(ROUTE) and sizes["keyframe_bytes"] == (16 + camera) * len(ROUTE)


@pytest.mark.parametrize("camera", [{"fx": 0, "fy": 300, "cx": 160, "cy": 120},
                                    {"fx": 300, "fy": 300, "cx": 160},
                                    {"fx": 300, "fy": 300, "cx": 160, "cy": 120,
                                     "distortion": [0.1, 0.2, 0.3]},
                                    {"fx": "300", "fy": 300, "cx": 160, "cy": 120},
                                    {"fx": 300, "fy": 300, "cx": 160, "cy": 120, "skew": 1}])
def test_a_bad_camera_is_refused_and_nothing_is_stored(tmp_path, camera):
    with make_client(tmp_path / "data") as c:
        make_map(c)
        r = post(c, png(sized("coffee")), map_id="kf", stream="mapper",
                 metadata=json.dumps({"camera": camera}))
        assert r.status_code == 422 and r.json()["type"].endswith(":invalid-metadata"), r.text
        assert c.get("/v1/maps/kf").json()["observations"] == 0


def test_keyframes_travel_with_a_snapshot_its_restore_and_a_restart(tmp_path):
    data = tmp_path / "data"
    turn = rotation(0, 0, 8)
    with make_client(data, snapshot_every=0) as c:
        make_map(c)
        seqs = learn(c, [sized(n) for n in ROUTE])
        snap = c.post("/v1/maps/kf/snapshots").json()["snapshot_id"]
        learn(c, [sized(n) for n in UNRELATED])
        assert c.post(f"/v1/maps/kf/snapshots/{snap}/restore").status_code == 200
        assert c.get("/v1/maps/kf/memory").json()["storage"]["keyframes"] == len(ROUTE)
        restored = drive(c, [warp(sized(n), CAMERA, turn) for n in ROUTE])
    with MapStore.open(data / "maps" / "kf" / "snapshots" / snap / "map.sqlite", readonly=True) as copy:
        assert copy.keyframe_bytes()[0] == len(ROUTE) and set(copy.keyframes(seqs)) == set(seqs)
    with make_client(data, snapshot_every=0) as c:
        restarted = drive(c, [warp(sized(n), CAMERA, turn) for n in ROUTE])
    for places in (restored, restarted):
        v = places[-1]["verification"]
        assert v["verified"] and v["keyframe_seq"] == seqs[-1] and abs(v["rotation_deg"] - 8.0) < 1.0, v


def test_the_loop_closure_log_and_its_exports_carry_the_verified_relative_pose(tmp_path):
    turn = rotation(5, 0, 0)
    data = tmp_path / "data"
    with make_client(data) as c:
        make_map(c)
        learn(c, [sized(n) for n in ROUTE])
        # A second robot maps the same route with its camera turned: its rows close loops on the first's.
        second = [post(c, png(warp(sized(n), CAMERA, turn)), map_id="kf", stream="second", top_k=0,
                       metadata=json.dumps(CAMERA_META)).json() for n in ROUTE]
        drive(c, [warp(sized(n), CAMERA, turn) for n in ROUTE])  # and a localising stream's closures
    with make_client(data) as c:  # durable: read back after a restart
        log = c.get("/v1/maps/kf/loop-closures", params={"limit": 500}).json()["loop_closures"]
        rows = list(csv.DictReader(io.StringIO(c.get("/v1/maps/kf/loop-closures/export",
                                                     params={"format": "csv"}).text)))
        g2o = c.get("/v1/maps/kf/loop-closures/export", params={"format": "g2o"})
        # whose keyframe each verification used (the place's row or a route neighbour of it, which
        # since places may be another robot's appearance of the same place)
        keyframe_stream = {e["verification"]["keyframe_seq"]: c.get(
            f"/v1/maps/kf/observations/{e['verification']['keyframe_seq']}").json()["stream"]
            for e in log if e["verification"]["verified"]}
    told = [b for b in second if b["place"] is not None and b["place"]["revisit"]]
    assert told and [e["verification"] for e in log if e["stream"] == "second"] == [
        b["place"]["verification"] for b in told]  # the log keeps what the reply said
    verified = [e for e in log if e["verification"]["verified"]]
    # Against the first robot's keyframes the camera is turned 5 degrees; against the second's, not at all.
    expect = {"mapper": 5.0, "second": 0.0}
    turned = [(e["verification"]["rotation_deg"], expect[keyframe_stream[e["verification"]["keyframe_seq"]]])
              for e in verified]
    assert verified and all(abs(got - want) < 1.0 for got, want in turned), turned
    assert len(rows) == len(log) and {r["verified"] for r in rows} <= {"True", "False"}
    row = next(r for r, e in zip(rows, log, strict=True)
               if e["verification"]["verified"] and e["place"]["stream"] == "mapper")
    q = np.array([float(row[k]) for k in ("qx", "qy", "qz", "qw")])
    assert abs(np.degrees(2 * np.arccos(min(1.0, abs(q[3])))) - 5.0) < 1.0 and row["tx"] == ""
    # g2o: one edge per verified closure of the learning stream, to its row or, for a consolidated
    # frame (a visit: no row), to a vertex of its own declared before it (issue 34 item 9); none for the
    # localising stream's.
    lines = [line.split() for line in g2o.text.splitlines()]
    edges = [line for line in lines if line[0] == "EDGE_SE3:QUAT"]
    want = [e for e in verified if e["seq"] is not None or e["consolidated_into"] is not None]
    assert all(e["place"]["stream"] == "mapper" for e in want)
    assert g2o.headers["content-type"].startswith("text/plain") and len(edges) == len(want) > 0
    visits = {VISIT_VERTEX_BASE + e["id"] for e in want if e["seq"] is None}
    assert visits  # the second robot's consolidated frames
    # every vertex an edge names is declared once, before its first edge (rows too, issue: outside probe)
    declared = []
    for line in lines:
        if line[0] == "VERTEX_SE3:QUAT":
            declared.append(int(line[1]))
        elif line[0] == "EDGE_SE3:QUAT":
            assert {int(line[1]), int(line[2])} <= set(declared), line[:3]
    assert len(declared) == len(set(declared)) and visits <= set(declared)
    assert set(declared) == {int(v) for edge in edges for v in edge[1:3]}
    for edge, e in zip(edges, want, strict=True):
        assert edge[0] == "EDGE_SE3:QUAT" and len(edge) == 3 + 7 + 21
        vertex = e["seq"] if e["seq"] is not None else VISIT_VERTEX_BASE + e["id"]
        assert (int(edge[1]), int(edge[2])) == (e["verification"]["keyframe_seq"], vertex)
        qx, qy, qz, qw = map(float, edge[6:10])
        # The query camera's pose in the keyframe's, in the vertices' body axes (x ahead, y left, z up): the
        # camera turned left 5 degrees (R = Ry(5) in optical axes: X_query = R X_keyframe) is yaw +5 about z.
        assert qz > 0 and abs(np.degrees(2 * np.arctan2(qz, qw)) - 5.0) < 1.0
        assert np.hypot(qx, qy) < np.sin(np.radians(1.0) / 2)
        info = list(map(float, edge[10:]))
        # translation unknown in length, rotation weighted and divided by the closure's span (§11.11)
        assert info[0] == 0.0 and info[-1] == pytest.approx(1e4 / e["span"]) and e["span"] >= 1


def test_a_route_neighbour_verifies_when_the_place_itself_does_not(tmp_path):
    """The place is a sequence answer: the right keyframe may be a link away (CORTEXLOC_VERIFY_NEIGHBOURS);
    the nearest verified one answers, and a row off the route is never tried."""
    from models.geometry import extract, pack
    from service.maps.keyframes import QueryFrame, verify_place
    from storage.mapstore import MapMeta
    from tests.storage.conftest import make_row

    scenes = {1: "coins", 2: "clock", 3: "astronaut", 4: "coffee"}  # 2: the place, featureless
    meta = MapMeta(map_id="kf", params={}, projection_sha256="ab" * 32, encoder_id="e", cell_dtype="uint32")
    with MapStore.create(tmp_path / "map.sqlite", meta) as store:
        for seq, name in scenes.items():
            kf = (pack(extract(sized(name))), CAMERA_META["camera"])
            store.append(dataclasses.replace(make_row(seq, prev=seq - 1 if seq > 1 else None), keyframe=kf))
        query = QueryFrame(extract(warp(sized("astronaut"), CAMERA, rotation(3, 0, 0))),
                           CAMERA_META["camera"], 0.0)
        on_route = verify_place(store, 2, "default", [1, 2, 3], query, stream="robot")
        off_route = verify_place(store, 2, "default", [1, 2], query, stream="robot")
    assert on_route.verified and on_route.keyframe_seq == 3 and abs(on_route.rotation_deg - 3.0) < 1.0
    assert not off_route.verified and off_route.keyframe_seq in (1, 2)


def test_a_frame_within_raised_upload_limits_keeps_its_keyframe(tmp_path):
    """The keyframe is decoded within the service's own limits (the encoder's), not the defaults: with
    `CORTEXLOC_MAX_UPLOAD_BYTES` raised, a frame over the default 10 MiB is learned with its features."""
    rgb = np.random.default_rng(5).integers(0, 256, (1900, 2000, 3), dtype=np.uint8)  # noise: PNG > 10 MiB
    body = png(rgb)
    assert len(body) > 10 * 2**20
    with make_client(tmp_path / "data", max_upload_bytes=16 * 2**20) as c:
        make_map(c)
        r = post(c, body, map_id="kf", stream="mapper", top_k=0)
        assert r.status_code == 200, r.text
        sizes = c.get("/v1/maps/kf/memory").json()["storage"]
        assert sizes["keyframes"] == 1 and sizes["keyframe_bytes"] > 16


def test_a_path_that_falls_behind_the_robot_is_lagging_and_no_revisit(tmp_path):
    # docs/design/science.md §11.13, service.md §1.2: 24 unlike frames driven over a route of 10 rows are
    # moves no path keeps pace with (it walks to the route's end and stays there); the reply says
    # `lagging` and no revisit, at any confidence (threshold 0 here). With the rule off (`lag_max`
    # 1000000) the same frames are all revisit candidates.
    for lag_max in (3, 1_000_000):
        with make_client(tmp_path / str(lag_max)) as c:
            made = make_map(c, localiser={"span_max": 4096, "lag_max": lag_max})
            assert made["params"]["localiser"]["lag_max"] == lag_max
            learn(c, [sized(n) for n in ROUTE])
            answers = [p for p in drive(c, [sized(n) for n in UNRELATED * 6]) if p]
        lagging = [p for p in answers if p["lagging"]]
        if lag_max == 3:
            assert lagging and not any(p["revisit"] for p in lagging)
        else:
            assert not lagging and answers and all(p["revisit"] for p in answers)
