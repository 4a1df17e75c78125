"""Maps and observations through the HTTP API, in process: mapping, localisation, revisits, restart,
bad input, and what every one of them leaves stored."""

from __future__ import annotations

import io
import json
import tarfile
import time

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from models.evaluation import sequences
from service.errors import PROBLEM_MEDIA_TYPE
from service.maps.runtime.room import ROOM_RECHECK_SECONDS
from tests.service.helpers import frame, held_encoder, make_client, post, state_of


@pytest.fixture
def client(tmp_path):
    with make_client(tmp_path / "data") as c:
        yield c


def test_fresh_install_serves_the_default_map(client):
    r = client.get("/v1/maps")
    assert r.status_code == 200 and [m["map_id"] for m in r.json()["maps"]] == ["default"]
    r = post(client, frame(1))
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["learned"] is True and body["seq"] == 1 and body["observation_id"]
    assert body["matches"] == [] and body["versions"]["weights"] == "random"
    assert (body["versions"]["runtime"], body["versions"]["device"]) == ("onnxruntime", "cpu")
    assert set(body["timings_ms"]) >= {"decode", "encode", "tm", "search", "store", "total"}
    assert body["sequence"]["step"] == 0
    text = client.get("/metrics").text
    assert 'cortexloc_observations_total{learned="true",map="default"} 1.0' in text
    assert 'cortexloc_stage_duration_seconds_count{stage="tm"} 1.0' in text
    assert 'cortexloc_map_observations{map="default"} 1.0' in text
    assert 'cortexloc_map_memory_bytes{map="default"}' in text
    assert 'cortexloc_map_places{map="default"} 1.0' in text  # read off the runtime's `place_map`


def test_a_deleted_maps_series_leave_metrics(client):
    """An outside probe: `cortexloc_observations_total` kept a series for every map ever made (50 made
    and deleted: 100 series more), past `CORTEXLOC_MAX_MAPS`; the per-map gauges did not."""
    for round_ in range(3):
        assert client.post("/v1/maps", json={"map_id": f"gone{round_}"}).status_code == 201
        assert post(client, frame(1), map_id=f"gone{round_}").status_code == 200
        assert post(client, frame(2), map_id=f"gone{round_}", learn="false").status_code == 200
        assert f'map="gone{round_}"' in client.get("/metrics").text
        assert client.delete(f"/v1/maps/gone{round_}").status_code == 204
    assert post(client, frame(1)).status_code == 200
    text = client.get("/metrics").text
    assert "gone" not in text and 'cortexloc_observations_total{learned="true",map="default"} 1.0' in text
    # a map made again under a deleted id counts from its own start
    assert client.post("/v1/maps", json={"map_id": "gone0"}).status_code == 201
    assert post(client, frame(1), map_id="gone0").status_code == 200
    assert 'cortexloc_observations_total{learned="true",map="gone0"} 1.0' in client.get("/metrics").text


def test_a_revisited_place_ranks_first(client):
    route = [frame(p) for p in range(8)]
    for img in route:
        assert post(client, img, learn="true").status_code == 200
    client.post("/v1/maps/default/streams/default/reset")
    # Localising needs sequence context, as the paper's protocol: a few frames of the same route.
    for p in (1, 2):
        post(client, frame(p, noise=4.0), learn="false", top_k=0)
    r = post(client, frame(3, noise=4.0), learn="false", top_k=3)
    body = r.json()
    assert r.status_code == 200 and body["learned"] is False and body["seq"] is None
    assert body["sequence"]["predicted_columns"] > 0
    assert body["matches"][0]["seq"] == 4  # place 3 was the 4th observation
    assert body["matches"][0]["score"] >= body["matches"][1]["score"]
    assert 0 < body["matches"][0]["score"] <= 1


def test_localisation_changes_nothing_stored(client):
    for p in range(4):
        post(client, frame(p))
    before = state_of(client)
    for p in range(4):
        assert post(client, frame(p, noise=3.0), learn="false").status_code == 200
    assert state_of(client) == before


def test_restart_rebuilds_the_same_memory_by_replay(tmp_path):
    data = tmp_path / "data"
    with make_client(data) as c:
        for p in (0, 1, 2, 0, 1):
            post(c, frame(p), stream="robot-1")
        post(c, frame(5), stream="robot-2")
        before = state_of(c)
        answer = post(c, frame(2, noise=3.0), learn="false", stream="probe").json()["matches"]
    with make_client(data) as c:
        assert c.get("/readyz").status_code == 200
        assert state_of(c) == before
        # A new stream: "probe" itself comes back where it was (its context is in the shutdown snapshot).
        again = post(c, frame(2, noise=3.0), learn="false", stream="probe-2").json()["matches"]
    assert again == answer


def test_create_get_delete_a_map_and_memory_sizes(client):
    r = client.post("/v1/maps", json={"map_id": "lab", "tm": {"cellsPerColumn": 2}})
    assert r.status_code == 201, r.text
    assert r.headers["Location"] == "/v1/maps/lab"
    assert r.json()["params"]["tm"]["cellsPerColumn"] == 2
    assert client.post("/v1/maps", json={"map_id": "lab"}).status_code == 409
    post(client, frame(1), map_id="lab")
    mem = client.get("/v1/maps/lab/memory").json()
    assert mem["tm"]["cells"] == 128 * 2 and mem["index"]["observations"] == 1
    assert mem["tm"]["allocated_bytes"] > 0 and mem["storage"]["db_bytes"] > 0
    assert client.delete("/v1/maps/lab").status_code == 204
    assert client.get("/v1/maps/lab").status_code == 404


@pytest.mark.parametrize("payload, status, slug", [
    ({"tm": {"minThreshold": 20, "activationThreshold": 4}}, 422, "invalid-configuration"),
    ({"tm": {"bogus": 1}}, 422, "invalid-configuration"),
    ({"preset": "no-such-preset"}, 422, "invalid-configuration"),
    ({"map_id": "Bad/Id"}, 400, "invalid-parameter"),
    ({"unknown_field": 1}, 400, "invalid-parameter"),
    ({"slsbh": {"adapt_tau": -1}}, 422, "invalid-configuration"),
    ({"preset": "cba2020-nordland"}, 422, "map-too-large"),
])
def test_bad_map_creation_is_refused(client, payload, status, slug):
    r = client.post("/v1/maps", json=payload)
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE)
    assert r.json()["type"] == f"urn:cortexloc:problem:{slug}"
    assert [m["map_id"] for m in client.get("/v1/maps").json()["maps"]] == ["default"]


def bad_inputs() -> list[tuple[str, bytes, str, dict, int, str]]:
    png = frame(1)
    jpg = frame(1, fmt=".jpg")
    sos = jpg.index(b"\xff\xda")
    scan = sos + 2 + int.from_bytes(jpg[sos + 2:sos + 4], "big")
    quarter = (len(jpg) - 2 - scan) // 4
    progressive = cv2.imencode(".jpg", cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR),
                               [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    second_scan = progressive.index(b"\xff\xda", progressive.index(b"\xff\xda") + 2)
    actl = b"acTL" + bytes(8)  # an animated PNG's control chunk (its CRC is not what is judged)
    animated_png = png[:33] + len(actl[4:]).to_bytes(4, "big") + actl + bytes(4) + png[33:]
    vp8x = b"VP8X" + (10).to_bytes(4, "little") + b"\x02" + bytes(3) + (127).to_bytes(3, "little") \
        + (95).to_bytes(3, "little")  # the animation flag set, a 128x96 canvas
    webp = frame(1, fmt=".webp")
    body = b"WEBP" + vp8x + webp[12:]
    animated_webp = b"RIFF" + len(body).to_bytes(4, "little") + body
    # an RLE8 bitmap of 128x96 cut after 10 rows, its end of bitmap appended, biSizeImage 0
    rle_rows = b"\x80\x07\x00\x00" * 10 + b"\x00\x01"
    rle_cut = (b"BM" + (1078 + len(rle_rows)).to_bytes(4, "little") + bytes(4) + (1078).to_bytes(4, "little")
               + (40).to_bytes(4, "little") + (128).to_bytes(4, "little") + (96).to_bytes(4, "little")
               + b"\x01\x00\x08\x00" + (1).to_bytes(4, "little") + bytes(20) + bytes(1024) + rle_rows)
    return [
        ("empty", b"", "image/png", {}, 422, "undecodable-image"),
        ("one byte", b"\x89", "image/png", {}, 422, "undecodable-image"),
        ("random bytes", bytes(range(256)) * 4, "application/octet-stream", {}, 415,
         "unsupported-media-type"),
        ("truncated png", png[: len(png) // 2], "image/png", {}, 422, "undecodable-image"),
        # a USB camera's broken MJPEG frame: a quarter of the scan data lost, EOI in place
        ("jpeg with scan data cut out", jpg[:scan + quarter] + jpg[scan + 2 * quarter:], "image/jpeg", {},
         422, "undecodable-image"),
        # found from outside: learned from its first scan alone (libjpeg warns of nothing)
        ("progressive jpeg cut at a scan boundary, EOI appended", progressive[:second_scan] + b"\xff\xd9",
         "image/jpeg", {}, 422, "undecodable-image"),
        ("jpeg declared as png", jpg, "image/png", {}, 415, "unsupported-media-type"),
        # found from outside: learned with the missing rows black
        ("rle bmp cut part way, end of bitmap appended", rle_cut, "image/bmp", {}, 422, "undecodable-image"),
        # found from outside: OpenCV decodes an animation's first frame, which no check had judged
        ("animated png", animated_png, "image/png", {}, 415, "unsupported-media-type"),
        ("animated webp", animated_webp, "image/webp", {}, 415, "unsupported-media-type"),
        ("text/plain", png, "text/plain", {}, 415, "unsupported-media-type"),
        ("gif", b"GIF89a" + bytes(64), "application/octet-stream", {}, 415, "unsupported-media-type"),
        ("bmp declared as webp", frame(1, fmt=".bmp"), "image/webp", {}, 415, "unsupported-media-type"),
        ("learn=maybe", png, "image/png", {"learn": "maybe"}, 400, "invalid-parameter"),
        ("top_k=-1", png, "image/png", {"top_k": -1}, 400, "invalid-parameter"),
        ("top_k too big", png, "image/png", {"top_k": 10_000}, 400, "invalid-parameter"),
        ("stream with //", png, "image/png", {"stream": "a//b"}, 400, "invalid-parameter"),
        ("stream with a leading /", png, "image/png", {"stream": "/a"}, 400, "invalid-parameter"),
        ("raw: one byte short", bytes(8 * 8 * 3 - 1), "application/octet-stream",
         {"encoding": "rgb8", "width": 8, "height": 8}, 422, "raw-frame-size-mismatch"),
        ("raw: mono16 as mono8", bytes(16 * 16), "application/octet-stream",
         {"encoding": "mono16", "width": 16, "height": 16}, 422, "raw-frame-size-mismatch"),
        ("raw: zero width", b"", "application/octet-stream",
         {"encoding": "mono8", "width": 0, "height": 16}, 400, "invalid-parameter"),
        ("raw: negative width", bytes(64 * 32 * 3), "application/octet-stream",
         {"encoding": "rgb8", "width": -64, "height": 32}, 400, "invalid-parameter"),
        ("raw: unknown encoding", bytes(64), "application/octet-stream",
         {"encoding": "yuv422", "width": 4, "height": 8}, 415, "unsupported-media-type"),
        ("raw: no height", bytes(64), "application/octet-stream", {"encoding": "mono8", "width": 8}, 400,
         "invalid-parameter"),
        ("raw: declared as png", bytes(64), "image/png", {"encoding": "mono8", "width": 8, "height": 8},
         400, "invalid-parameter"),
        ("raw: width without encoding", png, "image/png", {"width": 8}, 400, "invalid-parameter"),
        ("raw: 1x4000", bytes(4000), "application/octet-stream",
         {"encoding": "mono8", "width": 1, "height": 4000}, 422, "degenerate-image"),
        ("metadata not JSON", png, "image/png", {"metadata": "{stamp"}, 422, "invalid-metadata"),
        ("metadata a list", png, "image/png", {"metadata": "[1,2]"}, 422, "invalid-metadata"),
        ("metadata too large", png, "image/png", {"metadata": json.dumps({"note": "x" * 5000})}, 422,
         "invalid-metadata"),
        ("metadata too deep", png, "image/png", {"metadata": '{"a":' * 9 + "1" + "}" * 9}, 422,
         "invalid-metadata"),
        ("pose without y", png, "image/png", {"metadata": '{"pose":{"x":1}}'}, 422, "invalid-metadata"),
        ("pose x a string", png, "image/png", {"metadata": '{"pose":{"x":"1","y":2}}'}, 422,
         "invalid-metadata"),
        ("pose y beyond 1e9", png, "image/png", {"metadata": '{"pose":{"x":1,"y":1e12}}'}, 422,
         "invalid-metadata"),
        ("pose y NaN", png, "image/png", {"metadata": '{"pose":{"x":1,"y":NaN}}'}, 422, "invalid-metadata"),
        ("pose yaw beyond 1e6", png, "image/png", {"metadata": '{"pose":{"x":1,"y":2,"yaw":1e300}}'}, 422,
         "invalid-metadata"),
        ("pose yaw a string", png, "image/png", {"metadata": '{"pose":{"x":1,"y":2,"yaw":"1"}}'}, 422,
         "invalid-metadata"),
        ("trail not a stream name", png, "image/png", {"metadata": '{"trail":"a b"}'}, 422,
         "invalid-metadata"),
        ("trail a number", png, "image/png", {"metadata": '{"trail":3}'}, 422, "invalid-metadata"),
        # found from outside: stored as {"stamp": "x"}, the first stamp lost without a word
        ("metadata member twice", png, "image/png", {"metadata": '{"stamp":1,"stamp":"x"}'}, 422,
         "invalid-metadata"),
        ("metadata member twice, nested", png, "image/png", {"metadata": '{"pose":{"x":1,"y":2,"x":3}}'}, 422,
         "invalid-metadata"),
        # stamps are seconds: milliseconds and nanoseconds (as a string, past 2^53) read as seconds are not
        ("stamp in milliseconds", png, "image/png", {"metadata": '{"stamp":1700000000123}'}, 422,
         "invalid-metadata"),
        ("stamp in nanoseconds, a string", png, "image/png", {"metadata": '{"stamp":"1700000000123456789"}'},
         422, "invalid-metadata"),
        # a numeric string past a double reads as inf (and "nan" as NaN): once read as no stamp, now refused
        *[(f"stamp string {shown}", png, "image/png", {"metadata": json.dumps({"stamp": stamp})}, 422,
           "invalid-metadata") for shown, stamp in (("1e400", "1e400"), ("of 400 nines", "9" * 400),
                                                    ("inf", "inf"), ("-Infinity", "-Infinity"),
                                                    ("nan", "nan"),
                                                    # an outside probe: float() read these as seconds
                                                    ("in Arabic-Indic digits", "\u0661\u0667\u0660\u0660"),
                                                    ("with spaces", " 17 "), ("with an underscore", "1_7"),
                                                    # stored, then read as no stamp without a word
                                                    ("that is no time", "yesterday"))],
        ("png header claiming 100000x100000", huge_png_header(), "image/png", {}, 413, "image-too-large"),
        ("1x4000", frame_of_size(1, 4000), "image/png", {}, 422, "degenerate-image"),
        # found from outside: learned as views, a 2x2 checkerboard matched real ones at confidence 0.725
        ("2x2", frame_of_size(2, 2), "image/png", {}, 422, "degenerate-image"),
        ("16x8", frame_of_size(16, 8), "image/png", {}, 422, "degenerate-image"),
        ("raw: 8x8", bytes(8 * 8), "application/octet-stream", {"encoding": "mono8", "width": 8, "height": 8},
         422, "degenerate-image"),
    ]


def huge_png_header() -> bytes:
    import struct
    import zlib

    ihdr = struct.pack(">IIBBBBB", 100_000, 100_000, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    return b"\x89PNG\r\n\x1a\n" + chunk


def frame_of_size(w: int, h: int) -> bytes:
    ok, buf = cv2.imencode(".png", np.full((h, w, 3), 128, np.uint8))
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize("case", bad_inputs(), ids=lambda c: c[0])
def test_bad_input_gets_a_problem_and_changes_nothing(client, case):
    _, body, ctype, params, status, slug = case
    post(client, frame(7))
    before = state_of(client)
    r = post(client, body, ctype=ctype, **params)
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE)
    assert r.json()["type"] == f"urn:cortexloc:problem:{slug}"
    assert state_of(client) == before


def test_unknown_map_and_oversized_upload(client):
    r = post(client, frame(1), map_id="nope")
    assert r.status_code == 404 and r.json()["type"].endswith("map-not-found")
    with make_client(client.app.state.settings.data_dir.parent / "small", max_upload_bytes=1000) as c:
        r = post(c, frame(1))
        assert r.status_code == 413 and r.json()["type"].endswith("payload-too-large")
        assert c.app.state.registry.get("default").store.count() == 0


# ---------------------------------------------------------------------------------------- snapshots


def test_each_stream_is_adapted_on_its_own_as_the_evaluation_does(tmp_path):
    a_frames, b_frames = [frame(p) for p in range(7)], [frame(10 + p, noise=2.0) for p in range(6)]
    new_map = {"map_id": "adapted", "slsbh": {"adapt_tau": 4}}
    with make_client(tmp_path / "data") as c:
        assert c.post("/v1/maps", json=new_map).status_code == 201
        for fa, fb in zip(a_frames, b_frames, strict=False):  # two robots interleaved
            assert post(c, fa, "adapted", stream="a").status_code == 200
            assert post(c, fb, "adapted", stream="b").status_code == 200
    with make_client(tmp_path / "data") as c:  # the running means survive a restart (snapshot)
        assert post(c, a_frames[6], "adapted", stream="a").status_code == 200
        rt = c.app.state.registry.get("adapted")
        rows = list(rt.store.rows())
        enc = c.app.state.encoder
        for name, frames in (("a", a_frames), ("b", b_frames)):
            feats = np.concatenate([enc.embed([f], resize=rt.config.resize).features for f in frames])
            expected = sequences.codes(rt.hasher, feats, 4)  # what `cortexloc eval images --adapt 4` hashes
            got = [r.input_sdr for r in rows if r.stream == name]
            assert len(got) == len(frames)
            assert all(np.array_equal(g, e) for g, e in zip(got, expected, strict=True))
            assert np.array_equal(got[0], rt.hasher(feats[0]))  # no history yet: the plain code
            assert not all(np.array_equal(g, rt.hasher(f)) for g, f in zip(got[1:], feats[1:], strict=True))


def run_route(c: TestClient, places, stream: str = "default") -> list[list[int]]:
    """Post frames for mapping; return each reply's matched seqs (what a robot would see)."""
    return [[m["seq"] for m in post(c, frame(p), stream=stream, top_k=3).json()["matches"]] for p in places]


def test_snapshot_restore_continues_bit_identically(tmp_path):
    first, second = [0, 1, 2, 3], [4, 5, 1, 2, 6]
    with make_client(tmp_path / "a") as c:
        run_route(c, first)
        run_route(c, [7], stream="cam-2")
        snap = c.post("/v1/maps/default/snapshots")
        assert snap.status_code == 201, snap.text
        sid = snap.json()["snapshot_id"]
        a_replies = run_route(c, second)
        a_state = state_of(c)
        # Roll back and drive the same frames again: the same memory, replies and arrays.
        r = c.post(f"/v1/maps/default/snapshots/{sid}/restore")
        assert r.status_code == 200, r.text
        assert r.json()["discarded_observations"] == len(second)
        b_replies = run_route(c, second)
        b_state = state_of(c)
        kinds = [s["kind"] for s in c.get("/v1/maps/default/snapshots").json()["snapshots"]]
    # Matches to frames of the second drive carry new seqs (never reused): compare by position.
    offset = b_state[1] - a_state[1]
    first_of_b = a_state[1] - len(second) + 1 + offset
    b_as_a = [[s - offset if s >= first_of_b else s for s in reply] for reply in b_replies]
    assert b_as_a == a_replies
    assert b_state[2:] == a_state[2:]  # TM arrays, generator, index size
    assert b_state[1] > a_state[1]  # seqs are never reused after a restore
    assert kinds.count("pre-restore") == 1 and kinds.count("manual") == 1


def test_a_restore_counts_the_learned_frames_it_takes_away_and_brings_back_across_branches(tmp_path):
    """Found by an outside tester: `discarded_observations` was the rows held before less those after, so
    consolidated frames (visits) were not counted, a restore forward was negative, and branches netted
    out (15 for 25 dropped and 10 brought back). It counts learned frames by identity now."""
    def learn(c, places, stream: str) -> list[dict]:
        replies = [post(c, frame(p), stream=stream) for p in places]
        assert [r.status_code for r in replies] == [200] * len(places)
        return [r.json() for r in replies]

    def restore(c, sid: str) -> tuple[int, int]:
        r = c.post(f"/v1/maps/default/snapshots/{sid}/restore")
        assert r.status_code == 200, r.text
        return r.json()["discarded_observations"], r.json()["restored_observations"]

    def pre_restore(c) -> str:
        snaps = c.get("/v1/maps/default/snapshots").json()["snapshots"]
        newest = max((s for s in snaps if s["kind"] == "pre-restore"), key=lambda s: s["created_at"])
        return newest["snapshot_id"]

    with make_client(tmp_path / "a", snapshot_every=0) as c:
        # a threshold this short route's second drive reaches (the default's is over its confidence): its
        # frames are visits only on a path that called a revisit (docs/design/science.md §11.8)
        assert c.patch("/v1/maps/default", json={"revisit_threshold": 0.75}).status_code == 200
        learn(c, range(8), "a")
        s1 = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        b = learn(c, list(range(8)) * 2, "b")  # the route again: visits as well as rows
        visits = c.get("/v1/maps/default").json()["places"]["visits_logged"]
        assert visits > 0 and sum(r["learned"] for r in b) == 16
        assert restore(c, s1) == (16, 0)  # every learned post undone, rows and visits
        p1 = pre_restore(c)  # the branch B: the 8 rows of `a` and the 16 frames of `b`
        learn(c, range(20, 25), "c")  # the branch C, after S1
        assert restore(c, p1) == (5, 16)  # forward to B: C goes, B comes back
        assert restore(c, pre_restore(c)) == (16, 5)  # and back to C


def test_restart_recovers_from_snapshot_plus_replay(tmp_path):
    data = tmp_path / "data"
    with make_client(data, snapshot_every=3) as c:
        run_route(c, [0, 1, 2, 3, 4])  # an automatic snapshot at seq 3, replay of 4..5 at restart
        before = state_of(c)
        probe = post(c, frame(3), learn="false", stream="probe").json()["matches"]
        assert [s["kind"] for s in c.get("/v1/maps/default/snapshots").json()["snapshots"]] == ["auto"]
    with make_client(data, snapshot_every=3) as c:
        assert state_of(c) == before
        assert post(c, frame(3), learn="false", stream="probe-2").json()["matches"] == probe


def test_download_is_a_complete_tar(client):
    run_route(client, [0, 1])
    sid = client.post("/v1/maps/default/snapshots").json()["snapshot_id"]
    r = client.get(f"/v1/maps/default/snapshots/{sid}/download")
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-tar"
    assert int(r.headers["content-length"]) == len(r.content)
    with tarfile.open(fileobj=io.BytesIO(r.content)) as tar:
        names = tar.getnames()
    assert set(names) == {"manifest.json", "map.sqlite", "memory.npz", "projection.npy"}
    assert client.get("/v1/maps/default/snapshots/nope/download").status_code == 404
    assert client.post("/v1/maps/default/snapshots/nope/restore").status_code == 404


# -------------------------------------------------------------------------------------- concurrency


def test_concurrent_clients_get_distinct_increasing_seqs_and_none_is_lost(client):
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(8) as pool:
        replies = list(pool.map(lambda p: post(client, frame(p % 5), top_k=1), range(24)))
    assert all(r.status_code == 200 for r in replies)
    seqs = sorted(r.json()["seq"] for r in replies)
    assert seqs == list(range(1, 25))
    assert client.app.state.registry.get("default").store.count() == 24


def test_a_map_flooding_the_encoder_does_not_lock_another_map_out(tmp_path):
    """One client fills the encoder with one map's posts; another map's robot still gets its frame in:
    the flood's newest waiting post gives its slot back and is answered 503 overloaded (Retry-After),
    storing nothing. Before, the other map got 503 for as long as the flood lasted (`cortexloc bench
    fairness`, docs/benchmarks.md)."""
    from concurrent.futures import ThreadPoolExecutor

    with make_client(tmp_path / "d", encoder_workers=1, encoder_queue=3) as c:  # 4 in flight at most
        assert c.post("/v1/maps", json={"map_id": "other"}).status_code == 201
        pool = c.app.state.encoder_pool
        with held_encoder(c.app.state.encoder) as (gate, sizes), ThreadPoolExecutor(6) as threads:
            first = threads.submit(post, c, frame(0))
            deadline = time.monotonic() + 60
            while not sizes:  # the worker holds it in the backbone call
                assert time.monotonic() < deadline
                time.sleep(0.01)
            flood = [threads.submit(post, c, frame(p)) for p in (1, 2, 3)]
            while pool.pending < 4:
                assert time.monotonic() < deadline
                time.sleep(0.01)
            assert post(c, frame(4)).status_code == 503  # its own map holds every slot: refused at once
            other = threads.submit(post, c, frame(5), map_id="other")
            refused = None
            while refused is None:  # one of the flood's waiting posts is answered while the encoder is held
                assert time.monotonic() < deadline
                refused = next((f for f in flood if f.done()), None)
                time.sleep(0.01)
            assert refused.result().status_code == 503
            assert refused.result().headers["Retry-After"] == "1"
            assert refused.result().json()["type"].endswith("overloaded")
            gate.set()
            assert other.result().status_code == 200 and first.result().status_code == 200
            assert sorted(f.result().status_code for f in flood) == [200, 200, 503]
        registry = c.app.state.registry
        assert registry.get("default").store.count() == 3 and registry.get("other").store.count() == 1


def test_a_post_that_fails_before_its_turn_lets_no_later_post_pass_an_older_one(tmp_path):
    """Three posts to one map; the second's encoding fails (its slot taken back for another map) while
    the first is still encoding, the third's is done: the third still reaches the writer after the
    first (the memory sees frames in arrival order). Before, the failed post passed its turn on at once
    and the third was learned first (found in review)."""
    from concurrent.futures import Future, ThreadPoolExecutor

    from service.maps.errors import Overloaded

    class Gated:
        """The real pool, each future it returns released when the test says."""

        def __init__(self, real):
            self.real, self.encoders, self.calls = real, real.encoders, []

        def submit(self, body, **kw):
            proxy = Future()
            self.calls.append((self.real.submit(body, **kw), proxy))
            return proxy

    with make_client(tmp_path / "d") as c, ThreadPoolExecutor(3) as threads:
        gated = Gated(c.app.state.encoder_pool)
        c.app.state.encoder_pool = gated
        posts = []
        try:
            deadline = time.monotonic() + 60
            for i in (1, 2, 3):
                posts.append(threads.submit(post, c, frame(i)))
                while len(gated.calls) < i:
                    assert time.monotonic() < deadline
                    time.sleep(0.01)
            (real1, first), (_, second), (real3, third) = gated.calls
            second.set_running_or_notify_cancel()
            second.set_exception(Overloaded(4))
            third.set_result(real3.result(60))
            time.sleep(0.5)  # room for the third to overtake, as it did
            overtaken = posts[2].done()
            first.set_result(real1.result(60))
            a1, a2, a3 = (f.result(timeout=60) for f in posts)
        finally:  # whatever failed, no post's thread waits for ever on a future the test holds
            for _, proxy in gated.calls:
                if not proxy.done():
                    proxy.set_exception(Overloaded(4))
            c.app.state.encoder_pool = gated.real
    assert not overtaken
    assert (a1.status_code, a2.status_code, a3.status_code) == (200, 503, 200)
    assert a1.json()["seq"] < a3.json()["seq"]


def test_a_post_whose_client_went_away_is_not_encoded_and_gives_its_slot_back(tmp_path):
    """(Found from outside: 30 abandoned 25 MP posts delayed the next frame 8.5 s.) A client gone while
    its frame waits for the encoder: the post ends as ClientGone at once, its frame never reaches the
    backbone, and its slot comes back without waiting for the batch before it."""
    import functools

    from service.maps.departure import Departure
    from service.maps.errors import ClientGone

    with make_client(tmp_path / "d") as c:
        rt, pool = c.app.state.registry.get("default"), c.app.state.encoder_pool
        with held_encoder(c.app.state.encoder) as (gate, sizes):
            first = pool.submit(frame(0))
            deadline = time.monotonic() + 60
            while not sizes:  # the worker holds it in the backbone call
                assert time.monotonic() < deadline
                time.sleep(0.01)
            gone = Departure()
            observe = functools.partial(rt.observe, pool, c.app.state.extractions, frame(1), learn=True,
                                        stream="s", top_k=0, label=None, gone=gone)
            abandoned = c.portal.start_task_soon(observe)
            while pool.pending < 2:
                assert time.monotonic() < deadline
                time.sleep(0.01)
            gone.set()
            t_gone = time.monotonic()
            with pytest.raises(ClientGone):
                abandoned.result(timeout=30)  # while the backbone is still held
            while pool.pending > 1:  # its slot back, the first still in the backbone
                assert time.monotonic() < deadline
                time.sleep(0.01)
            assert time.monotonic() - t_gone < 10 and not gate.is_set()  # not at the held call's 30 s
            gate.set()
            first.result(timeout=60)
        assert sizes == [1] and rt.store.count() == 0  # the abandoned frame reached no batch


def test_a_full_encoder_queue_answers_503_and_stores_nothing(tmp_path):
    from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

    with make_client(tmp_path / "d", encoder_workers=1, encoder_queue=1) as c:  # 2 in flight at most
        with held_encoder(c.app.state.encoder) as (gate, _), ThreadPoolExecutor(4) as pool:
            futs = [pool.submit(post, c, frame(p)) for p in range(4)]
            done: set = set()
            while len(done) < 2:  # the two beyond the limit are answered while the encoder is held
                done |= wait(set(futs) - done, timeout=30, return_when=FIRST_COMPLETED).done
            early = sorted(f.result().status_code for f in done)
            gate.set()
            statuses = sorted(f.result().status_code for f in futs)
        assert early == [503, 503] and statuses == [200, 200, 503, 503]
        busy = next(f.result() for f in done)
        assert busy.headers["Retry-After"] == "1" and busy.json()["type"].endswith("overloaded")
        assert busy.json()["retry_after"] == 1
        assert c.app.state.registry.get("default").store.count() == 2


def test_restart_keeps_step_counts_and_the_switch_to_localisation(tmp_path):
    data = tmp_path / "data"
    with make_client(data) as c:
        for p in range(4):
            post(c, frame(p), stream="a")
        post(c, frame(9), stream="a", learn="false")  # a switch: the next mapping step starts anew
        cont = post(c, frame(5), stream="b").json()["sequence"]["step"]
    with make_client(data) as c:
        assert post(c, frame(6), stream="b").json()["sequence"]["step"] == cont + 1
        rt = c.app.state.registry.get("default")
        seq = post(c, frame(7), stream="a").json()["seq"]
        assert rt.store.get(seq).context_prev_seq is None


def test_disk_full_is_507_and_nothing_is_learned(client):
    post(client, frame(1))
    store = client.app.state.registry.get("default").store
    db = store._db()
    # The database may not grow: the first row that needs a new page meets a full disk (SQLITE_FULL).
    db.execute(f"PRAGMA max_page_count = {db.execute('PRAGMA page_count').fetchone()[0]}")
    for place in range(2, 200):
        before = state_of(client)
        r = post(client, frame(place))
        if r.status_code != 200:
            break
    assert r.status_code == 507 and r.json()["type"].endswith("insufficient-storage"), r.text
    assert state_of(client) == before
    # The failed commit rebuilt the memory from the store, once: the next learning posts are refused
    # before their step (no rebuild, the map ready), localising ones answered, until a probe finds room.
    rt = client.app.state.registry.get("default")
    now = [time.monotonic()]
    rt.room.clock = lambda: now[0]
    rebuilds = []
    real = rt.recover
    rt.recover = lambda **kw: (rebuilds.append(1), real(**kw))[1]
    for other in range(3):
        r = post(client, frame(place + 1 + other))
        assert r.status_code == 507 and r.json()["type"].endswith("insufficient-storage"), r.text
        assert "once room is made" in r.json()["detail"]
        assert post(client, frame(1), stream="q", learn="false").status_code == 200
        assert client.get("/v1/maps/default").json()["state"] == "ready"
    assert rebuilds == [] and state_of(client) == before
    now[0] += ROOM_RECHECK_SECONDS  # the probe is due, and finds room (the new connection has no cap)
    assert post(client, frame(place)).json()["seq"] == before[1] + 1
    assert rebuilds == []


def test_on_a_full_disk_a_retried_post_of_a_stored_row_still_gets_its_reply(client, monkeypatch):
    """The disk fills after a row was stored and before the robot heard its reply: its retry (the same
    Idempotency-Key) is answered from the store, not refused with the new posts."""
    from storage.mapstore import MapStore, StorageFull

    def keyed(place: int, key: str):
        return client.post("/v1/maps/default/observations", content=frame(place),
                           headers={"Content-Type": "image/png", "Idempotency-Key": key})

    first = keyed(1, "key-0001")
    assert first.status_code == 200

    def full(self, row, **kw):
        raise StorageFull("database or disk is full")

    monkeypatch.setattr(MapStore, "append", full)
    monkeypatch.setattr(MapStore, "has_room", lambda self, nbytes: False)
    assert keyed(2, "key-0002").status_code == 507  # the commit that finds the disk full
    assert keyed(3, "key-0003").status_code == 507  # refused before its step
    again = keyed(1, "key-0001")
    assert again.status_code == 200 and again.json()["seq"] == first.json()["seq"]


def test_a_store_refusing_writes_is_503_map_read_only_and_readyz_says_so(client):
    post(client, frame(1))
    before = state_of(client)
    # SQLite refuses the commit as for a file it holds read-only (an immutable map.sqlite: the probe's case)
    client.app.state.registry.get("default").store._db().execute("PRAGMA query_only = ON")
    r = client.post("/v1/maps/default/observations", content=frame(2), headers={"Content-Type": "image/png"})
    assert r.status_code == 503 and r.headers["content-type"] == PROBLEM_MEDIA_TYPE, r.text
    body = r.json()
    assert body["type"].endswith(":map-read-only") and body["map_id"] == "default"
    assert (body["state"], body["state_reason"]) == ("read-only", "storage-read-only")
    assert "read-only" in body["detail"] and "maps/default/map.sqlite" in body["detail"]
    assert state_of(client) == before  # nothing stored half, nothing learned
    assert client.get("/v1/maps/default").json()["state"] == "read-only"
    ready = client.get("/readyz")
    assert ready.status_code == 200  # it localises: a warning, not unready
    maps = ready.json()["checks"]["maps"]
    assert maps["status"] == "warn" and "default's storage refuses writes" in maps["warning"]
    assert post(client, frame(1), learn="false").status_code == 200


def test_a_map_whose_projection_changed_fails_alone(tmp_path):
    data = tmp_path / "data"
    with make_client(data) as c:
        post(c, frame(1))
        c.post("/v1/maps", json={"map_id": "other", "seed": 5})
        sha = c.get("/v1/maps/default").json()["projection_sha256"]
    path = data / "projections" / f"{sha}.npy"
    raw = bytearray(path.read_bytes())
    raw[-1] ^= 0xFF  # one flipped bit in the matrix
    path.write_bytes(bytes(raw))
    with make_client(data) as c:
        ready = c.get("/readyz")
        assert ready.status_code == 200  # a failed map does not make the service unready
        assert ready.json()["checks"]["maps"]["maps"]["default"]["state_reason"] == "projection-invalid"
        r = post(c, frame(1))
        assert r.status_code == 503 and r.json()["type"].endswith("map-unavailable")
        assert c.get("/v1/maps/other").json()["state"] == "ready"


def test_download_then_import_recreates_the_map_elsewhere(tmp_path):
    from typer.testing import CliRunner

    from service.cli import app as cli_app

    with make_client(tmp_path / "a") as c:
        c.post("/v1/maps", json={"map_id": "lab"})
        for p in range(5):
            post(c, frame(p), map_id="lab")
        sid = c.post("/v1/maps/lab/snapshots").json()["snapshot_id"]
        tar = tmp_path / "lab.tar"
        tar.write_bytes(c.get(f"/v1/maps/lab/snapshots/{sid}/download").content)
        expected = state_of(c, "lab")
        answer = post(c, frame(3), map_id="lab", learn="false", stream="q").json()["matches"]
    r = CliRunner().invoke(cli_app, ["import", str(tar), "--data-dir", str(tmp_path / "b")])
    assert r.exit_code == 0, r.output
    with make_client(tmp_path / "b") as c:
        assert c.get("/v1/maps/lab").json()["state"] == "ready"
        assert state_of(c, "lab") == expected
        assert post(c, frame(3), map_id="lab", learn="false", stream="q").json()["matches"] == answer
    again = CliRunner().invoke(cli_app, ["import", str(tar), "--data-dir", str(tmp_path / "b")])
    assert again.exit_code == 1 and "exists" in again.output
    bad = tmp_path / "bad.tar"
    raw = bytearray(tar.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    bad.write_bytes(bytes(raw))
    r = CliRunner().invoke(cli_app, ["import", str(bad), "--data-dir", str(tmp_path / "c")])
    assert r.exit_code == 1


def test_concurrent_requests_are_encoded_in_batches(tmp_path):
    import time
    from concurrent.futures import ThreadPoolExecutor

    with make_client(tmp_path / "d", encoder_workers=1) as c:
        pool = c.app.state.encoder_pool
        bad = bytearray(frame(1))
        at = bad.index(b"IDAT") + 200
        bad[at:at + 40] = bytes(x ^ 0xFF for x in bad[at:at + 40])  # passes the header probe, not the decode
        bodies = [frame(p) for p in range(11)] + [bytes(bad)]  # fails alone, in the pool
        with held_encoder(c.app.state.encoder) as (gate, sizes), ThreadPoolExecutor(len(bodies)) as ex:
            futs = [ex.submit(post, c, b, top_k=0) for b in bodies]
            # the first image holds the only worker until every request waits in the pool's queue
            for _ in range(3000):  # a condition, polled: the requests reach the pool in their own time
                if pool.pending == len(bodies) or any(f.done() for f in futs):
                    break
                time.sleep(0.01)
            assert pool.pending == len(bodies), [f.result().text for f in futs if f.done()]
            gate.set()
            replies = [f.result() for f in futs]
        assert sorted(r.status_code for r in replies) == [200] * 11 + [422]
        assert max(sizes) > 1  # the waiting requests went to the backbone together
        assert c.app.state.registry.get("default").store.count() == 11


def test_api_key_guards_every_write(tmp_path):
    with make_client(tmp_path / "d", api_key="s3cret") as c:
        r = post(c, frame(1))
        assert r.status_code == 401 and r.json()["type"].endswith("unauthorized")
        assert c.post("/v1/maps", json={"map_id": "x"}).status_code == 401
        assert c.get("/v1/maps").status_code == 200  # reads stay open
        ok = c.post("/v1/maps/default/observations", content=frame(1),
                    headers={"Content-Type": "image/png", "X-API-Key": "s3cret"})
        assert ok.status_code == 200
        assert c.app.state.registry.get("default").store.count() == 1


@pytest.mark.parametrize(("width", "height", "inflated"), [(100, 100, 100 << 20), (1000, 1000, 64 << 20)],
                         ids=["small raster", "large raster"])
def test_png_decompression_bomb_gets_a_problem_and_changes_nothing(client, png_bomb, width, height,
                                                                   inflated):
    # The 100x100 bomb at 1/100 scale (refused from its chunks), and one whose compressed size
    # fits its raster (refused by the bounded inflate in the encoder).
    post(client, frame(7))
    before = state_of(client)
    r = post(client, png_bomb(width, height, inflated))
    assert r.status_code == 422, r.text
    assert r.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE)
    body = r.json()
    assert body["type"] == "urn:cortexloc:problem:decompression-bomb"
    assert body["title"] == "Decompression bomb"
    assert body["width"] == width and body["raster_bytes"] == height * (1 + 3 * width)
    assert state_of(client) == before
    assert post(client, frame(8)).status_code == 200  # the encoder is free for the next frame
