"""A map's `resize` option (issue 23 item 1; docs/design/service.md §1.1): crop or squash, chosen at
creation, frozen, shown in the map resource and every answer's `versions`, and what the map's frames are
encoded with."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.maps.config import DEFAULT_RESIZE
from tests.service.helpers import make_app, make_client, post


@pytest.fixture
def client(tmp_path):
    with TestClient(make_app(tmp_path / "data")) as c:
        yield c


def wide(sides: int) -> bytes:
    """A 2:1 PNG (256 x 128): the same middle for every `sides`, its outer quarters drawn from `sides`.
    A centre crop (short side to 256, then the middle 224) sees the middle only; a squash sees it all."""
    middle = cv2.resize(np.random.default_rng(7).integers(0, 256, (8, 8, 3), dtype=np.uint8), (128, 128),
                        interpolation=cv2.INTER_CUBIC)
    outer = np.random.default_rng(100 + sides).integers(0, 256, (128, 64, 3), dtype=np.uint8)
    ok, buf = cv2.imencode(".png", np.hstack([outer, middle, outer[:, ::-1]]))
    assert ok
    return buf.tobytes()


def test_a_map_freezes_its_resize_mode_and_shows_it(tmp_path):
    with make_client(tmp_path / "data") as c:
        made = c.post("/v1/maps", json={"map_id": "wide", "resize": "squash"})
        assert made.status_code == 201, made.text
        assert made.json()["params"]["resize"] == "squash" and made.json()["encoder"].endswith(":squash")
        default = c.get("/v1/maps/default").json()
        plain = c.post("/v1/maps", json={"map_id": "plain"}).json()
        assert plain["params"]["resize"] == default["params"]["resize"] == DEFAULT_RESIZE
        answer = post(c, wide(0), map_id="wide").json()
        assert answer["versions"]["resize"] == "squash" and answer["versions"]["encoder"].endswith(":squash")
        assert post(c, wide(0), map_id="plain").json()["versions"]["resize"] == plain["params"]["resize"]
        refused = c.patch("/v1/maps/wide", json={"resize": "crop"})  # frozen: not a PATCH field
        assert refused.status_code == 400 and "resize" in refused.text
    with make_client(tmp_path / "data") as c:  # reopened with its own mode, not the encoder's default
        again = c.get("/v1/maps/wide").json()
        assert (again["state"], again["params"]["resize"], again["observations"]) == ("ready", "squash", 1)
        assert post(c, wide(1), map_id="wide").json()["versions"]["resize"] == "squash"


@pytest.mark.parametrize(("value", "status"), [("stretch", 422), ("", 422), ("Squash", 422), (1, 400),
                                               (None, 201)])
def test_a_bad_resize_is_refused_naming_it(client, value, status):
    r = client.post("/v1/maps", json={"map_id": "bad", "resize": value})
    assert r.status_code == status, r.text
    if status == 201:  # null: the service's default
        assert r.json()["params"]["resize"] == DEFAULT_RESIZE
        return
    assert r.json()["type"].endswith(":invalid-configuration" if status == 422 else ":invalid-parameter")
    assert [e["name"].split(".")[-1] for e in r.json()["errors"]] == ["resize"]
    assert client.get("/v1/maps/bad").status_code == 404


def test_a_crop_map_cannot_tell_apart_frames_that_differ_outside_the_crop_and_a_squash_map_can(client):
    """The mode is the map's, frame by frame: two 2:1 frames with the same middle are one frame to a
    cropping map (the same code: overlap with itself) and two to a squashing one."""
    scores = {}
    for mode in ("crop", "squash"):
        # memory none: the code is the sLSBH code itself, no context to tell the frames apart
        made = client.post("/v1/maps", json={"map_id": mode, "resize": mode, "memory": "none"})
        assert made.status_code == 201, made.text
        assert post(client, wide(0), map_id=mode).status_code == 200
        # another stream: a stream's own trail is never its match (docs/design/science.md §11.6)
        answer = post(client, wide(1), map_id=mode, learn="false", top_k=1, stream="other").json()
        scores[mode] = answer["matches"][0]["score"]
    assert scores["crop"] == 1.0 and scores["squash"] < 1.0


def test_a_map_made_before_the_option_keeps_cropping():
    from service.maps.config import MapConfig, MapOptions, resolve

    params = resolve(MapOptions(), default_preset="cortexloc-default", default_backbone="alexnet").stored()
    assert params["resize"] == DEFAULT_RESIZE
    del params["resize"]  # stored before the option existed
    assert MapConfig.parse(params).resize == "crop"  # what the service did then
