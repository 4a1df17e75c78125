"""Keyframes and loop-closure exports that cannot break a map (issue 34 items 1, 2, 3, 8 and 9;
docs/design/service.md §1.2, §6; docs/design/science.md §12): extractions capped and skipped for a client
gone, cameras checked against the decoded frame, a failure of the geometry a failed verification, exports
rendered whole with finite numbers only and text cells no spreadsheet runs, cut off (never short) should
one fail anyway."""

from __future__ import annotations

import contextlib
import csv
import functools
import io
import json
import socket
import threading
import time

import cv2
import httpx
import numpy as np
import pytest

from service.maps import closures, keyframes
from service.maps.departure import Departure
from service.maps.errors import ClientGone
from service.routes import observations
from storage.mapschema import NewClosure, NewVisit
from tests.service.helpers import frame, make_app, make_client, post, served

pytest.importorskip("skimage", reason="scikit-image (dev extra) ships the real images")

from models.evaluation.geometry import rotation, warp
from tests.service.maps.test_keyframes import CAMERA, CAMERA_META, ROUTE, make_map, png, sized


def learn_route(c) -> list[int]:
    return [post(c, png(sized(n)), map_id="kf", stream="mapper", top_k=0,
                 metadata=json.dumps(CAMERA_META)).json()["seq"] for n in ROUTE]


def localise(c, stream: str, meta: dict | None = None) -> list[dict]:
    """The route turned 5 degrees, localised on `stream` (the camera on every frame, with `meta`)."""
    out = []
    for n in ROUTE:
        r = post(c, png(warp(sized(n), CAMERA, rotation(5, 0, 0))), map_id="kf", stream=stream, learn="false",
                 top_k=0, metadata=json.dumps({**CAMERA_META, **(meta or {})}))
        assert r.status_code == 200, r.text
        out.append(r.json())
    return out


# ---------------------------------------------------------------------------------------------- item 1


def test_an_extraction_past_the_cap_is_503_with_retry_after_and_nothing_changes(tmp_path):
    with make_client(tmp_path / "data", max_extractions=2) as c:
        make_map(c)
        extractions = c.app.state.extractions
        assert extractions.limit == 2
        for _ in range(2):  # two of this map's extractions in flight
            extractions.reserve("kf")
        r = post(c, png(sized("astronaut")), map_id="kf", top_k=0)
        assert r.status_code == 503 and r.headers["Retry-After"] == "1", r.text
        assert r.json()["type"].endswith("overloaded") and "keyframe extraction" in r.json()["detail"]
        rt = c.app.state.registry.get("kf")
        assert rt.store.count() == 0
        for _ in range(500):  # its encoding was cancelled: the pool gives its slot back in its own time
            if c.app.state.encoder_pool.pending == 0:
                break
            time.sleep(0.01)
        assert c.app.state.encoder_pool.pending == 0
        for _ in range(2):
            extractions.release("kf")
        assert post(c, png(sized("astronaut")), map_id="kf", top_k=0).status_code == 200
        assert extractions.pending == 0 and rt.store.count() == 1
        # A map without keyframes takes no extraction slot.
        for _ in range(2):
            extractions.reserve("kf")
        assert post(c, png(sized("astronaut")), top_k=0).status_code == 200
        # Another map with keyframes has its own: one map's extractions in flight do not refuse it.
        assert c.post("/v1/maps", json={"map_id": "kf2", "keyframes": {"features": "orb"}}).status_code == 201
        assert post(c, png(sized("astronaut")), map_id="kf2", top_k=0).status_code == 200
        assert extractions.pending == 2


def test_the_extractions_take_the_maps_in_turn(monkeypatch):
    """One map's burst of extractions does not lock another map out: each map has `limit` in flight of
    its own, and the threads take the maps in turn (models/frontend/turns.py, tested there), so the
    robot's waits for one of the flood's to end, not for the flood. Before, a cap of `limit` over all maps
    refused the robot for as long as the flood held it."""
    from service.maps.errors import Overloaded

    order: list[str] = []
    gate, running = threading.Event(), threading.Semaphore(0)

    def extract(decode, body, *_):
        if body == "hold":
            running.release()
            gate.wait(30)
        order.append(body)

    monkeypatch.setattr(keyframes, "extract_frame", extract)
    ex = keyframes.Extractions(3)
    futs = []

    def start(key, body):
        ex.reserve(key)
        futs.append(ex.start(key, None, body, None, None, False, threading.Event()))

    for _ in range(3):
        start("flood", "hold")  # the flood's three run and hold every thread
    for _ in range(3):
        assert running.acquire(timeout=30)
    with pytest.raises(Overloaded):
        ex.reserve("flood")
    start("robot", "r0")
    start("robot", "r1")
    assert ex.pending == 5
    with pytest.raises(Overloaded):
        ex.reserve("flood")  # still three of its own in flight
    gate.set()
    for f in futs:
        f.result(timeout=30)
    assert sorted(order) == ["hold"] * 3 + ["r0", "r1"] and ex.pending == 0
    ex.close()


def test_a_post_the_encoder_refuses_runs_no_extraction_and_holds_no_slot(tmp_path, monkeypatch):
    """(From review.) The extraction's slot is taken before the encoding and given back when the encoder
    refuses the post (a map over its share under a flood): no decode and SIFT for a 503, no slot held
    after it. A version that submitted the extraction first ran it for every refused post."""
    from service.maps.encoding.pool import EmbeddingPool
    from service.maps.errors import Overloaded

    ran = []
    monkeypatch.setattr(keyframes, "extract_frame", lambda *a: ran.append(a))

    def refuse(self, *a, **kw):
        raise Overloaded(self.limit)

    with make_client(tmp_path / "data") as c:
        make_map(c)
        monkeypatch.setattr(EmbeddingPool, "submit", refuse)
        statuses = [post(c, png(sized("astronaut")), map_id="kf", top_k=0).status_code for _ in range(3)]
        assert statuses == [503, 503, 503]
        time.sleep(0.2)  # an extraction started anyway would have run by now
        assert ran == [] and c.app.state.extractions.pending == 0


def test_a_post_whose_client_went_away_is_skipped_before_the_writer(tmp_path, monkeypatch):
    ran = []
    monkeypatch.setattr(keyframes, "extract_frame", lambda *a: ran.append(a))
    with make_client(tmp_path / "data") as c:
        make_map(c)
        rt = c.app.state.registry.get("kf")
        gone = Departure()
        gone.set()
        observe = functools.partial(rt.observe, c.app.state.encoder_pool, c.app.state.extractions,
                                    png(sized("astronaut")), learn=True, stream="s", top_k=0, label=None,
                                    gone=gone)
        with pytest.raises(ClientGone):
            c.portal.call(observe)
        assert ran == [] and rt.store.count() == 0 and c.app.state.extractions.pending == 0


def test_a_client_that_hangs_up_during_its_extraction_changes_nothing(live, monkeypatch):
    """Over a real connection: the client closes it while its frame's features are being taken; the post
    never reaches the writer, and the next one is learned as usual."""
    base, app = live
    made = httpx.post(f"{base}/v1/maps", json={"map_id": "kf", "keyframes": {"features": "orb"}})
    assert made.status_code == 201, made.text
    started, release = threading.Event(), threading.Event()
    extract = keyframes.extract_frame

    def held(*args):
        started.set()
        assert release.wait(60)
        return extract(*args)

    monkeypatch.setattr(keyframes, "extract_frame", held)
    departures: list[threading.Event] = []  # each post's "the client went away" event
    departure = observations._departure

    @contextlib.asynccontextmanager
    async def recorded(request):
        async with departure(request) as gone:
            departures.append(gone)
            yield gone

    monkeypatch.setattr(observations, "_departure", recorded)
    body = png(sized("astronaut"))
    port = int(base.rsplit(":", 1)[1])
    with socket.create_connection(("127.0.0.1", port)) as sock:
        sock.sendall(b"POST /v1/maps/kf/observations HTTP/1.1\r\nHost: t\r\nContent-Type: image/png\r\n"
                     b"Content-Length: %d\r\n\r\n" % len(body) + body)
        assert started.wait(60)
    assert departures and departures[0].wait(30)  # the disconnect reached the server
    monkeypatch.setattr(keyframes, "extract_frame", extract)
    release.set()
    after = httpx.post(f"{base}/v1/maps/kf/observations", content=png(sized("coffee")),
                       headers={"Content-Type": "image/png"}, timeout=60)  # queued behind the first's turn
    assert after.status_code == 200 and after.json()["seq"] == 1, after.text
    assert app.state.registry.get("kf").store.count() == 1


# ---------------------------------------------------------------------------------------------- item 2


@pytest.mark.parametrize(("camera", "field"), [
    ({"fx": 1e-300, "fy": 1e-300, "cx": 0, "cy": 0}, "metadata.camera.fx"),  # the issue's
    ({"fx": 300.0, "fy": 1e-6, "cx": 160.0, "cy": 120.0}, "metadata.camera.fy"),
    ({"fx": 300.0, "fy": 300.0, "cx": 400.0, "cy": 120.0}, "metadata.camera.cx"),  # outside 320 x 240
    ({"fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0, "distortion": [1000.0] * 14},
     "metadata.camera.distortion"),  # the 500s
])
def test_a_camera_without_geometric_sense_is_422_naming_the_field(tmp_path, camera, field):
    with make_client(tmp_path / "data") as c:
        make_map(c)
        for learn in ("true", "false"):
            r = post(c, png(sized("astronaut")), map_id="kf", top_k=0, learn=learn,
                     metadata=json.dumps({"camera": camera}))
            assert r.status_code == 422, r.text
            body = r.json()
            assert body["type"].endswith("invalid-metadata") and field in [e["name"] for e in body["errors"]]
        rt = c.app.state.registry.get("kf")
        assert rt.store.count() == 0 and rt.cameras == {} and rt.store.closure_count() == 0


def test_closures_without_a_finite_pose_export_whole_and_finite(tmp_path):
    """Entries logged before verification refused them (the issue's: a null rotation, 'verified') export
    in every format, their pose left empty; no body stops short."""
    with make_client(tmp_path / "data") as c:
        make_map(c)
        seqs = learn_route(c)
        store = c.app.state.registry.get("kf").store
        nan = float("nan")
        for rot in ([[None] * 3] * 3, [[nan] * 3] * 3, [[0.0] * 3] * 3, "garbage"):
            store.add_closure(NewClosure(stream="robot", place_seq=seqs[1], confidence=0.9, support=2,
                                         metadata={"stamp": 12.5}, verification={
                                             "verified": True, "keyframe_seq": seqs[1], "rotation": rot,
                                             "translation": [nan, 0.0, 1.0]}))
        csv_text = c.get("/v1/maps/kf/loop-closures/export", params={"format": "csv"})
        jsonl = c.get("/v1/maps/kf/loop-closures/export", params={"format": "jsonl"})
        g2o = c.get("/v1/maps/kf/loop-closures/export", params={"format": "g2o"})
    assert csv_text.status_code == jsonl.status_code == g2o.status_code == 200
    rows = list(csv.DictReader(io.StringIO(csv_text.text)))
    records = [json.loads(line) for line in jsonl.text.splitlines()]
    assert len(rows) == len(records) == 4
    for row, rec in zip(rows, records, strict=True):
        assert [row[k] for k in ("qx", "qy", "qz", "qw", "tx")] == [""] * 5 and row["stamp"] == "12.5"
        assert rec["qw"] is None and rec["tx"] is None and rec["verified"] is True
    assert g2o.text == ""  # no finite rotation: no edge


@pytest.fixture
def live(tmp_path):
    """The app on a real uvicorn server on loopback, in a thread; yields (base URL, app)."""
    app = make_app(tmp_path / "var")
    with served(app, log_level="critical") as base:
        yield base, app


def test_an_export_that_fails_midway_is_cut_off_without_its_last_chunk(live, monkeypatch):
    base, app = live
    learned = httpx.post(f"{base}/v1/maps/default/observations", content=frame(1),
                         headers={"Content-Type": "image/png"})
    assert learned.status_code == 200, learned.text
    store, seq = app.state.registry.get("default").store, learned.json()["seq"]
    for i in range(3):
        store.add_closure(NewClosure(stream=f"s{i}", place_seq=seq, confidence=0.9, support=1))

    def failing(spool, chunk_bytes=0):
        with spool:
            yield spool.read(40)
            raise OSError("the disk went away")

    monkeypatch.setattr(closures, "chunks", failing)
    port = int(base.rsplit(":", 1)[1])
    with socket.create_connection(("127.0.0.1", port)) as sock:
        sock.sendall(b"GET /v1/maps/default/loop-closures/export?format=csv HTTP/1.1\r\nHost: t\r\n\r\n")
        sock.settimeout(30)
        got = b""
        while chunk := sock.recv(65536):
            got += chunk
    head, _, body = got.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 200") and b"transfer-encoding: chunked" in head.lower()
    assert body and not body.endswith(b"0\r\n\r\n")  # the connection closed with the body unfinished


# ---------------------------------------------------------------------------------------------- item 3


def test_a_failure_of_the_geometry_is_a_failed_verification_not_a_500(tmp_path, monkeypatch):
    with make_client(tmp_path / "data") as c:
        make_map(c)
        seqs = learn_route(c)
        rt = c.app.state.registry.get("kf")
        recovered = rt.recovery

        def fail(*args, **kwargs):
            raise cv2.error("OpenCV(5.0.0) lapack.cpp: error: (-215) SVD did not converge")

        monkeypatch.setattr(cv2, "findHomography", fail)
        learned = [post(c, png(warp(sized(n), CAMERA, rotation(5, 0, 0))), map_id="kf", stream="second",
                        top_k=0, metadata=json.dumps(CAMERA_META)) for n in ROUTE]
        localised = localise(c, "robot")
        assert [r.status_code for r in learned] == [200] * len(ROUTE), [r.text for r in learned]
        told = [r.json()["place"]["verification"] for r in learned if r.json()["place"]]
        told += [b["place"]["verification"] for b in localised if b["place"]]
        # (a frame with few features fails before any fit, with its own reason)
        assert told and not any(v["verified"] for v in told), told
        assert sum(v["reason"] == "geometry-failed" for v in told) >= len(told) // 2, told
        # Nothing was rebuilt: the map stayed ready, its rows all stored.
        assert rt.state == "ready" and rt.recovery is recovered
        joined = sum(v.row is not None for v in rt.store.visits())  # warm-up rows turned into visits
        assert rt.store.count() == len(seqs) + sum(1 for r in learned if r.json()["seq"] is not None) - joined


# ------------------------------------------------------------------------------------------ items 8, 9


def test_csv_text_cells_are_neutralised_and_numbers_stay_numbers(tmp_path):
    with make_client(tmp_path / "data") as c:
        make_map(c)
        learn_route(c)
        for stream in ("-1-1", "-A1", "-cmd"):
            localise(c, stream, {"pose": {"x": -1.5, "y": 2.0, "yaw": -0.25}})
        text = c.get("/v1/maps/kf/loop-closures/export", params={"format": "csv"}).text
        jsonl = c.get("/v1/maps/kf/loop-closures/export", params={"format": "jsonl"}).text
    rows = [r for r in csv.DictReader(io.StringIO(text)) if r["stream"] != "mapper"]
    assert {r["stream"] for r in rows} == {"'-1-1", "'-A1", "'-cmd"}
    assert all((r["x"], r["y"], r["yaw"]) == ("-1.5", "2.0", "-0.25") for r in rows)
    assert not any(cell.startswith(("=", "+", "-", "@", "\t", "\r"))
                   for r in rows for k, cell in r.items() if k not in ("x", "yaw", "qx", "qy", "qz", "qw",
                                                                      "tx", "ty", "tz"))
    # JSON keeps the text as it is (no spreadsheet reads it).
    assert {json.loads(line)["stream"] for line in jsonl.splitlines()} >= {"-1-1", "-A1", "-cmd"}


@pytest.mark.parametrize(("value", "cell"), [
    ("=1+1", "'=1+1"), ("+1", "'+1"), ("-cmd", "'-cmd"), ("@A", "'@A"), ("\tx", "'\tx"), ("\rx", "'\rx"),
    ("ok-1", "ok-1"), (-1.5, -1.5), (None, ""), (True, True)])
def test_csv_cell(value, cell):
    assert closures.csv_cell(value) == cell


def test_a_visit_closure_reaches_the_g2o_export_as_its_own_vertex(tmp_path):
    """A consolidated frame (a visit) has no row: its verified closure is a g2o vertex, VISIT_VERTEX_BASE +
    its log id, at its pose, with its edge; a localising stream's closure has neither; the CSV and JSON
    exports give every closure's vertex id, and the log names the row a visit joined."""
    turn = rotation(5, 0, 0)
    with make_client(tmp_path / "data") as c:
        make_map(c)
        seqs = learn_route(c)
        store = c.app.state.registry.get("kf").store
        row = store.get(seqs[2])
        verification = {"verified": True, "keyframe_seq": seqs[2], "rotation": turn.tolist(),
                        "translation": None, "model": "homography", "inliers": 80}
        meta = {"stamp": 1700000000.5, "pose": {"x": 3.0, "y": -4.0, "yaw": 0.5}}
        store.add_visit(NewVisit(stream="mapper", seq=seqs[2], context_prev_seq=seqs[1],
                                 input_sdr=row.input_sdr, winner_cells=row.winner_cells, metadata=meta,
                                 closure=NewClosure(
                                     stream="mapper", place_seq=seqs[2], confidence=0.9, support=3,
                                     metadata=meta, verification=verification)))
        store.add_closure(NewClosure(stream="robot", place_seq=seqs[2], confidence=0.9, support=3,
                                     metadata=meta, verification=verification))  # a localising stream's
        log = c.get("/v1/maps/kf/loop-closures", params={"limit": 500}).json()["loop_closures"]
        g2o = c.get("/v1/maps/kf/loop-closures/export", params={"format": "g2o"}).text
        rows = list(csv.DictReader(io.StringIO(c.get("/v1/maps/kf/loop-closures/export",
                                                     params={"format": "csv"}).text)))
    visit, localising = log[-2], log[-1]
    assert (visit["seq"], visit["consolidated_into"]) == (None, seqs[2])
    assert (localising["seq"], localising["consolidated_into"]) == (None, None)
    vertex = closures.VISIT_VERTEX_BASE + visit["id"]
    lines = [line.split() for line in g2o.splitlines()]
    # the keyframe's row is declared too (learn_route posts no pose: a placeholder, said), then the visit
    assert lines[:2] == [["#", "NOPOSE", str(seqs[2])], ["VERTEX_SE3:QUAT", str(seqs[2])] + ["0"] * 6 + ["1"]]
    assert len(lines) == 4 and lines[2][:2] == ["VERTEX_SE3:QUAT", str(vertex)]
    x, y, z, qx, qy, qz, qw = map(float, lines[2][2:])
    assert (x, y, z, qx, qy) == (3.0, -4.0, 0.0, 0.0, 0.0) and np.isclose(2 * np.arctan2(qz, qw), 0.5)
    assert lines[3][:3] == ["EDGE_SE3:QUAT", str(seqs[2]), str(vertex)] and len(lines[3]) == 3 + 7 + 21
    assert [r["vertex"] for r in rows[-2:]] == [str(vertex), ""] and rows[-2]["stamp"] == "1700000000.5"
