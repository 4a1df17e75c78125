"""Client tests of server features that are being built (issue 15): typed response schemas, the
sequence-level `place`, per-observation metadata, idempotent posts, raw frames, stored observations and
thumbnails, `PATCH` of a map, stream names with `/`. They fail until the service has them; once it
does, they belong with the others (test_client.py, test_openapi_contract.py).
"""

from __future__ import annotations

import uuid

import numpy as np
import pytest

from cortexloc_client import Client, NotFoundError, models


def test_every_reply_matches_the_servers_schema(openapi, contract) -> None:
    assert contract(openapi) == []


def _drive_a_loop(client: Client, map_id: str, make_frame, **kw) -> dict[int, int]:
    seqs = {}
    for place in range(5):
        pose = {"x": float(place), "y": 0.0, "yaw": 0.0, "frame_id": "map"}
        answer = client.observe(map_id, make_frame(place), label=f"place {place}",
                                metadata={"stamp": 100.0 + place, "pose": pose}, **kw)
        seqs[place] = answer.seq
    client.reset_stream(map_id, "default")
    return seqs


def test_a_revisit_names_its_place(client: Client, tiny_map: str, make_frame) -> None:
    seqs = _drive_a_loop(client, tiny_map, make_frame)
    for place in range(3):
        answer = client.observe(tiny_map, make_frame(place), learn=False)
    place = answer.place
    assert isinstance(place, models.Place)
    assert place.seq == seqs[2] and place.label == "place 2" and place.stream == "default"
    assert 0.0 <= place.confidence <= 1.0 and place.revisit is True and (place.support or 0) >= 1
    assert place.metadata is not None and place.metadata.pose is not None and place.metadata.pose.x == 2.0


def test_metadata_is_stored_and_returned(client: Client, tiny_map: str, make_frame) -> None:
    seqs = _drive_a_loop(client, tiny_map, make_frame)
    answer = client.observe(tiny_map, make_frame(9), metadata=models.Metadata(stamp=7.5, note="dock"))
    assert answer.metadata is not None and answer.metadata.stamp == 7.5
    assert answer.metadata.model_extra == {"note": "dock"}
    for place in range(3):
        answer = client.observe(tiny_map, make_frame(place), learn=False)
    best = answer.matches[0]
    assert best.seq == seqs[2] and best.metadata is not None and best.metadata.stamp == 102.0
    assert best.metadata.pose == models.Pose(x=2.0, y=0.0, yaw=0.0, frame_id="map")


def test_a_repeated_idempotency_key_learns_once(client: Client, tiny_map: str, make_frame) -> None:
    key = uuid.uuid4().hex
    first = client.observe(tiny_map, make_frame(0), idempotency_key=key)
    again = client.observe(tiny_map, make_frame(0), idempotency_key=key)
    assert (again.observation_id, again.seq) == (first.observation_id, first.seq)
    assert client.get_map(tiny_map).observations == 1
    other = client.observe(tiny_map, make_frame(0))  # a fresh key: a new observation
    assert other.seq != first.seq


def test_arrays_are_accepted_as_raw_frames(client: Client, tiny_map: str, make_frame, make_picture) -> None:
    rgb = make_picture(3)
    learned = client.observe(tiny_map, rgb)
    assert learned.learned
    client.reset_stream(tiny_map, "default")
    # The same picture as BGR with colour="bgr8" is the same frame: it finds itself.
    as_bgr = client.observe(tiny_map, rgb[:, :, ::-1], colour="bgr8", learn=False)
    assert as_bgr.matches[0].seq == learned.seq and as_bgr.matches[0].score > 0.9
    grey = rgb.mean(axis=2)
    assert client.observe(tiny_map, grey.astype(np.uint8)).learned
    assert client.observe(tiny_map, (grey * 257).astype(np.uint16)).learned
    assert client.get_map(tiny_map).observations == 3


def test_a_stored_observation_and_its_thumbnail(client: Client, server: str, api_key: str,
                                               tiny_params: dict, make_frame) -> None:
    map_id = f"t-{uuid.uuid4().hex[:10]}"
    client.create_map(map_id, thumbnails=True, **tiny_params)
    try:
        posted = client.observe(map_id, make_frame(1), label="dock", metadata={"stamp": 1.5})
        assert posted.seq is not None
        stored = client.get_observation(map_id, posted.seq)
        assert (stored.observation_id, stored.seq) == (posted.observation_id, posted.seq)
        assert stored.label == "dock"
        assert stored.metadata is not None and stored.metadata.stamp == 1.5
        assert client.thumbnail(map_id, posted.seq)[:3] == b"\xff\xd8\xff"
        with pytest.raises(NotFoundError):
            client.get_observation(map_id, posted.seq + 100)
    finally:
        client.delete_map(map_id)


def test_the_revisit_threshold_can_be_changed(client: Client, tiny_map: str) -> None:
    changed = client.update_map(tiny_map, revisit_threshold=0.7)
    assert changed.revisit_threshold == 0.7
    assert client.get_map(tiny_map).revisit_threshold == 0.7


def test_ros_stream_names_with_a_slash(client: Client, tiny_map: str, make_frame) -> None:
    answer = client.observe(tiny_map, make_frame(0), stream="robot1/cam0")
    assert answer.stream == "robot1/cam0"
    assert client.reset_stream(tiny_map, "robot1/cam0").had_context is True
    assert "robot1/cam0" in client.get_map(tiny_map).streams
