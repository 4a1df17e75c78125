"""The observation route for robots (issue 15; docs/design/service.md §1.2, §4.2): raw sensor frames,
WebP and BMP, idempotent posts, per-observation metadata, stored observations and thumbnails read
back, ROS-style stream names."""

from __future__ import annotations

import json
import sqlite3
import time
import uuid
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import pytest

from storage.mapschema import SCHEMA_VERSION
from tests.service.helpers import frame, held_encoder, make_client, post, state_of
from tests.storage.v1_files import downgrade


@pytest.fixture
def client(tmp_path):
    with make_client(tmp_path / "data") as c:
        yield c


def picture(place: int) -> np.ndarray:
    """(96, 128, 3) uint8 RGB: the pixels of `frame(place)`."""
    bgr = cv2.imdecode(np.frombuffer(frame(place), np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def post_raw(c, arr: np.ndarray, encoding: str, **params):
    h, w = arr.shape[:2]
    return post(c, np.ascontiguousarray(arr).tobytes(), ctype="application/octet-stream", encoding=encoding,
                width=w, height=h, **params)


def stored_code(c, seq: int, map_id: str = "default") -> list[int]:
    return c.app.state.registry.get(map_id).store.get(seq).input_sdr.tolist()


def keyed(c, body: bytes, key: str, **params):
    return c.post("/v1/maps/default/observations", content=body, params=params,
                  headers={"Content-Type": "image/png", "Idempotency-Key": key})


# ------------------------------------------------------------------------------------ raw frames


def test_bgr8_rgb8_and_png_of_one_picture_give_one_code(client):
    rgb = picture(2)
    seqs = [post(client, frame(2)).json()["seq"], post_raw(client, rgb, "rgb8").json()["seq"],
            post_raw(client, rgb[:, :, ::-1], "bgr8").json()["seq"]]
    codes = [stored_code(client, s) for s in seqs]
    assert codes[0] == codes[1] == codes[2]
    grey = rgb[:, :, 1]
    mono8 = post_raw(client, grey, "mono8").json()["seq"]
    mono16 = post_raw(client, grey.astype("<u2") * 257, "mono16").json()["seq"]
    assert stored_code(client, mono8) == stored_code(client, mono16)


def test_a_raw_frame_of_the_wrong_size_stores_nothing(client):
    post(client, frame(1))
    before = state_of(client)
    r = post(client, bytes(96 * 128 * 3 - 3), ctype="application/octet-stream", encoding="rgb8", width=128,
             height=96)
    assert r.status_code == 422 and r.json()["type"].endswith("raw-frame-size-mismatch")
    assert (r.json()["expected_bytes"], r.json()["received_bytes"]) == (96 * 128 * 3, 96 * 128 * 3 - 3)
    assert state_of(client) == before


@pytest.mark.parametrize(("ext", "ctype"), [(".webp", "image/webp"), (".bmp", "image/bmp"),
                                            (".bmp", "application/octet-stream")])
def test_webp_and_bmp_are_accepted(client, ext, ctype):
    r = post(client, frame(4, fmt=ext), ctype=ctype)
    assert r.status_code == 200, r.text
    assert r.json()["learned"] is True


# ----------------------------------------------------------------------------------- idempotency


def test_a_repeated_key_gets_the_first_reply_and_learns_once(client):
    key = uuid.uuid4().hex
    first = keyed(client, frame(1), key, label="dock")
    assert first.status_code == 200 and "idempotent-replayed" not in first.headers
    before = state_of(client)
    again = keyed(client, frame(1), key, label="dock")
    assert again.status_code == 200 and again.headers["idempotent-replayed"] == "true"
    assert again.content == first.content  # the same body, byte for byte
    assert state_of(client) == before
    fresh = keyed(client, frame(1), uuid.uuid4().hex, label="dock")
    assert fresh.json()["seq"] == first.json()["seq"] + 1


@pytest.mark.parametrize("change", [{"body": frame(2)}, {"label": "other"}, {"learn": "false"},
                                    {"metadata": '{"stamp": 1}'}, {"stream": "other"}])
def test_a_key_reused_for_another_request_is_refused(client, change):
    key = uuid.uuid4().hex
    assert keyed(client, frame(1), key, label="dock").status_code == 200
    before = state_of(client)
    params = {"label": "dock", **{k: v for k, v in change.items() if k != "body"}}
    r = keyed(client, change.get("body", frame(1)), key, **params)
    assert r.status_code == 422 and r.json()["type"].endswith("idempotency-key-reused")
    assert r.json()["key"] == key and state_of(client) == before


@pytest.mark.parametrize("key", ["short", "x" * 129, "has space 123", "slash/in/the/key"])
def test_a_malformed_key_is_a_400(client, key):
    before = state_of(client)
    r = client.post("/v1/maps/default/observations", content=frame(1),
                    headers={"Content-Type": "image/png", "Idempotency-Key": key})
    assert r.status_code == 400 and r.json()["type"].endswith("invalid-parameter")
    assert state_of(client) == before


def test_the_replay_survives_a_restart(tmp_path):
    data, key = tmp_path / "data", uuid.uuid4().hex
    with make_client(data) as c:
        post(c, frame(0))
        first = keyed(c, frame(1), key)
        assert first.status_code == 200
    with make_client(data) as c:
        before = state_of(c)
        again = keyed(c, frame(1), key)
        assert again.status_code == 200 and again.content == first.content
        assert again.headers["idempotent-replayed"] == "true" and state_of(c) == before


def test_two_posts_with_one_key_in_flight_learn_once(client):
    key, pool = uuid.uuid4().hex, client.app.state.encoder_pool
    with held_encoder(client.app.state.encoder) as (gate, _), ThreadPoolExecutor(2) as threads:
        futs = [threads.submit(keyed, client, frame(3), key) for _ in range(2)]
        deadline = time.monotonic() + 30
        while pool.pending < 2 and time.monotonic() < deadline:  # both past the route's own lookup
            time.sleep(0.01)
        assert pool.pending == 2
        gate.set()
        replies = [f.result() for f in futs]
    assert [r.status_code for r in replies] == [200, 200]
    assert replies[0].content == replies[1].content
    assert sorted("idempotent-replayed" in r.headers for r in replies) == [False, True]
    assert client.app.state.registry.get("default").store.count() == 1


def test_a_localisation_with_a_key_steps_once(client):
    post(client, frame(1))
    key = uuid.uuid4().hex
    first = keyed(client, frame(1), key, learn="false")
    steps = client.app.state.registry.get("default").streams["default"].step
    again = keyed(client, frame(1), key, learn="false")
    assert again.content == first.content and again.headers["idempotent-replayed"] == "true"
    assert client.app.state.registry.get("default").streams["default"].step == steps


def test_a_restore_drops_the_keys_of_the_rows_it_drops(client):
    post(client, frame(0))
    sid = client.post("/v1/maps/default/snapshots").json()["snapshot_id"]
    key = uuid.uuid4().hex
    first = keyed(client, frame(1), key)
    assert client.post(f"/v1/maps/default/snapshots/{sid}/restore").json()["discarded_observations"] == 1
    again = keyed(client, frame(1), key)  # its row is gone, so is its key: learned anew
    assert "idempotent-replayed" not in again.headers and again.json()["seq"] > first.json()["seq"]
    assert client.app.state.registry.get("default").store.count() == 2


# -------------------------------------------------------------------------------- where and what


def test_metadata_is_stored_and_returned_everywhere(client):
    pose = {"x": 1.5, "y": -2.0, "yaw": 0.25, "frame_id": "map"}
    for p in range(3):
        meta = {"stamp": 100.0 + p, "pose": {**pose, "x": float(p)}, "tags": ["a", {"b": p}]}
        r = post(client, frame(p), metadata=json.dumps(meta, separators=(",", ":")))
        assert r.status_code == 200 and r.json()["metadata"] == meta
    client.post("/v1/maps/default/streams/default/reset")
    for p in range(3):
        answer = post(client, frame(p), learn="false").json()
    assert answer["metadata"] is None
    best = answer["matches"][0]
    assert best["seq"] == 3 and best["metadata"]["stamp"] == 102.0 and best["metadata"]["pose"]["x"] == 2.0
    one = client.get("/v1/maps/default/observations/2").json()
    assert one["metadata"]["stamp"] == 101.0 and one["stream"] == "default" and one["has_thumbnail"] is False
    assert set(one) == {"seq", "observation_id", "stream", "label", "created_at", "image_sha256", "metadata",
                        "has_thumbnail", "joined_to"} and one["joined_to"] is None  # a row held
    page = client.get("/v1/maps/default/observations", params={"after_seq": 1, "limit": 1}).json()
    assert [o["seq"] for o in page["observations"]] == [2] and page["next_after_seq"] == 2
    last = client.get("/v1/maps/default/observations", params={"after_seq": 2}).json()
    assert [o["seq"] for o in last["observations"]] == [3] and last["next_after_seq"] is None
    assert client.get("/v1/maps/default/observations", params={"limit": 501}).status_code == 400
    missing = client.get("/v1/maps/default/observations/99")
    assert missing.status_code == 404 and missing.json()["type"].endswith("observation-not-found")
    assert client.get("/v1/maps/default/observations/2/thumbnail").status_code == 404


def test_thumbnails_are_kept_when_the_map_asks(client):
    r = client.post("/v1/maps", json={"map_id": "album", "thumbnails": True})
    assert r.status_code == 201 and r.json()["thumbnails"] is True
    assert client.get("/v1/maps/default").json()["thumbnails"] is False
    seq = post(client, frame(5, fmt=".jpg"), map_id="album", ctype="image/jpeg").json()["seq"]
    raw_seq = post_raw(client, picture(6), "rgb8", map_id="album").json()["seq"]
    assert post(client, frame(5), map_id="album", learn="false").status_code == 200
    for s in (seq, raw_seq):
        r = client.get(f"/v1/maps/album/observations/{s}/thumbnail")
        assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg"
        thumb = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
        assert thumb.shape[:2] == (96, 128)  # frames of 128 x 96: never enlarged
        assert client.get(f"/v1/maps/album/observations/{s}").json()["has_thumbnail"] is True
    listed = client.get("/v1/maps/album/observations").json()["observations"]
    assert [o["has_thumbnail"] for o in listed] == [True, True]  # the localisation stored nothing


def test_ros_stream_names_with_a_slash(client):
    r = post(client, frame(0), stream="robot1/cam0")
    assert r.status_code == 200 and r.json()["stream"] == "robot1/cam0"
    reset = client.post("/v1/maps/default/streams/robot1%2Fcam0/reset")
    assert reset.status_code == 200 and reset.json() == {"stream": "robot1/cam0", "had_context": True}
    assert client.post("/v1/maps/default/streams/robot1/cam0/reset").json()["had_context"] is False
    assert "robot1/cam0" in client.get("/v1/maps/default").json()["streams"]
    assert client.post("/v1/maps/default/streams/a//b/reset").status_code == 400


def test_an_old_map_file_still_opens_and_learns(tmp_path):
    data = tmp_path / "data"
    with make_client(data, snapshot_every=0) as c:
        for p in range(3):
            post(c, frame(p))
        probe = post(c, frame(1), learn="false", stream="probe").json()["matches"]
    path = data / "maps" / "default" / "map.sqlite"
    downgrade(path)
    with make_client(data, snapshot_every=0) as c:
        m = c.get("/v1/maps/default").json()
        assert m["state"] == "ready" and m["observations"] == 3
        assert post(c, frame(1), learn="false", stream="probe").json()["matches"] == probe
        r = post(c, frame(9), metadata='{"stamp": 9.0}')
        assert r.json()["seq"] == 4 and c.get("/v1/maps/default/observations/4").json()["metadata"] == {
            "stamp": 9.0}
    conn = sqlite3.connect(path)
    assert conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0] == str(
        SCHEMA_VERSION)
    conn.close()


@pytest.mark.parametrize("metadata", [
    '{"s": "\\ud800x"}',                       # a lone surrogate: not storable as UTF-8
    '{"a": ' + "[" * 2000 + "]" * 2000 + "}",  # deeper than any parser should recurse
    '{"stamp": NaN}', '{"pose": {"x": Infinity, "y": 1}}', '{"pose": {"x": 1e400, "y": 2}}',
    '{"pose": {"x": true, "y": 1}}', '{"stamp": true}',
    # beyond 2^53 - 1: JavaScript rounds them, or reads Infinity
    '{"n": ' + "9" * 400 + '}', '{"a": [-9007199254740992]}',
    '{"pose": {"x": 1e16, "y": 0}}', '{"pose": {"x": 0, "y": -1000000001}}',  # beyond the pose range
])
def test_metadata_that_cannot_be_stored_as_sent_is_refused_and_changes_nothing(client, metadata):
    """Found from outside: a lone surrogate stored a row no read could serve (500 on every read of it),
    2,000 brackets were a 500, NaN and 1e400 were stored as null."""
    before = state_of(client)
    r = post(client, frame(1), metadata=metadata)
    assert r.status_code == 422 and r.json()["type"].endswith("invalid-metadata"), r.text
    assert state_of(client) == before
    assert client.get("/v1/maps/default/recent").status_code == 200


def test_metadata_at_the_edges_of_its_ranges_is_stored_exactly(client):
    """Integers up to 2^53 - 1 (what a double holds exactly) and poses up to 1e9 are kept as sent."""
    meta = {"id": 2**53 - 1, "low": -(2**53 - 1), "pose": {"x": 1e9, "y": -1e9, "yaw": 3.0}}
    r = post(client, frame(1), metadata=json.dumps(meta))
    assert r.status_code == 200, r.text
    assert client.get(f"/v1/maps/default/observations/{r.json()['seq']}").json()["metadata"] == meta


def test_seqs_beyond_sqlites_integers_are_a_400(client):
    for path in ("/v1/maps/default/observations/9223372036854775808",
                 "/v1/maps/default/observations?after_seq=9223372036854775808"):
        r = client.get(path)
        assert r.status_code == 400 and r.headers["content-type"].startswith("application/problem+json")
