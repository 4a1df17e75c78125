"""`Client` against a real `cortexloc serve` (tests/conftest.py): maps, observations, snapshots, errors."""

from __future__ import annotations

import tarfile
import uuid

import numpy as np
import pytest

from cortexloc_client import (
    BadRequestError,
    Client,
    ConflictError,
    NotFoundError,
    UnauthorizedError,
    UnprocessableError,
    UnsupportedMediaTypeError,
    models,
)

# One pytest-xdist worker runs both files that use the session's server (`make test`): it starts once,
# not once per worker (a start exports the backbone: tens of seconds on two cores).
pytestmark = pytest.mark.xdist_group("client-server")


def test_health_and_readiness(client: Client) -> None:
    assert client.health().status == "ok"
    ready = client.ready()
    assert ready.status == "ready"
    # No AlexNet weights are installed for the tests' server, so its default backbone is the pretrained
    # EfficientNet-Lite0 (docs/design/service.md §8): nothing to warn about.
    assert ready.checks["encoder"].status == "pass"
    assert ready.checks["encoder"].model_extra["weights"] == "pretrained"


def test_a_map_is_created_listed_read_and_deleted(client: Client, tiny_map: str) -> None:
    got = client.get_map(tiny_map)
    assert isinstance(got, models.Map)
    assert (got.map_id, got.state, got.observations, got.last_seq) == (tiny_map, "ready", 0, 0)
    assert got.params.tm["columnDimensions"] == 128 and got.params.slsbh["k"] == 64
    assert tiny_map in [m.map_id for m in client.list_maps()]
    memory = client.memory(tiny_map)
    assert memory.tm.columns == 128 and memory.index.observations == 0 and memory.process_rss_bytes > 0

    client.delete_map(tiny_map)
    with pytest.raises(NotFoundError) as e:
        client.get_map(tiny_map)
    assert (e.value.status, e.value.slug, e.value.extra["map_id"]) == (404, "map-not-found", tiny_map)
    client.create_map(tiny_map, tm={"columnDimensions": 128}, slsbh={"k": 64})  # for the fixture's delete


def test_create_map_sends_the_memory_and_localiser_options(client: Client, tiny_params: dict) -> None:
    map_id = f"t-{uuid.uuid4().hex[:10]}"
    made = client.create_map(map_id, memory="none", localiser={"beam": 64, "warmup": 2}, resize="crop",
                             backbone=client.ready().checks["encoder"].model_extra["backbone"], **tiny_params)
    try:
        assert made.params.memory == "none" and made == client.get_map(map_id)
        assert made.params.resize == "crop" and made.encoder.endswith(":crop")
        assert (made.params.localiser["beam"], made.params.localiser["warmup"]) == (64, 2)
        with pytest.raises(UnprocessableError):
            client.create_map(f"{map_id}-b", backbone="resnet-9000", **tiny_params)
    finally:
        client.delete_map(map_id)


def test_keyframes_and_verify_revisit_round_trip(client: Client, tiny_params: dict) -> None:
    map_id = f"t-{uuid.uuid4().hex[:10]}"
    made = client.create_map(map_id, keyframes={"features": "orb", "max": 300}, **tiny_params)
    try:
        assert made.params.keyframes == {"features": "orb", "max": 300} and made.verify_revisit is False
        assert client.update_map(map_id, verify_revisit=True).verify_revisit is True
        assert client.get_map(map_id).revisit_threshold == made.revisit_threshold  # untouched
        assert client.memory(map_id).storage.keyframes == 0
    finally:
        client.delete_map(map_id)


def test_dot_segments_stay_one_segment(client: Client, tiny_map: str, make_frame) -> None:
    # httpx resolves a "." or ".." path segment (RFC 3986): a snapshot id ".." once deleted the whole map.
    client.observe(tiny_map, make_frame(0))
    with pytest.raises(BadRequestError):  # an id the service never hands out, not a path to the map
        client.delete_snapshot(tiny_map, "..")
    with pytest.raises(BadRequestError):
        client.restore_snapshot(tiny_map, ".")
    assert client.get_map(tiny_map).observations == 1
    for stream in (".", ".."):  # stream names the service accepts, reset as themselves
        client.observe(tiny_map, make_frame(1), stream=stream)
        assert client.reset_stream(tiny_map, stream) == models.StreamReset(stream=stream, had_context=True)
    for call in (lambda: client.delete_snapshot(tiny_map, ""), lambda: client.delete_map(""),
                 lambda: client.reset_stream(tiny_map, "")):
        with pytest.raises(ValueError):  # refused before any request
            call()
    assert client.get_map(tiny_map).observations == 3


def test_a_revisited_place_is_the_first_match(client: Client, tiny_map: str, make_frame) -> None:
    seqs = {}
    for place in range(5):
        answer = client.observe(tiny_map, make_frame(place), top_k=3, label=f"place {place}")
        assert answer.learned and answer.seq is not None and answer.observation_id is not None
        seqs[place] = answer.seq
    client.reset_stream(tiny_map, "default")
    for place in range(3):  # the robot drives the loop again, localising
        answer = client.observe(tiny_map, make_frame(place), learn=False, top_k=3)
        assert not answer.learned and answer.seq is None
        if place > 0:  # the first frame after a reset has no context to recall its successor with
            assert answer.matches[0].seq == seqs[place] and answer.matches[0].label == f"place {place}"
    assert [m.rank for m in answer.matches] == [1, 2, 3]
    assert answer.versions.api == "v1" and answer.versions.map_seq == seqs[4]
    assert client.get_map(tiny_map).observations == 5


def test_a_stream_reset_ends_its_context(client: Client, tiny_map: str, make_frame) -> None:
    client.observe(tiny_map, make_frame(0), stream="cam0")
    assert client.reset_stream(tiny_map, "cam0") == models.StreamReset(stream="cam0", had_context=True)
    assert client.reset_stream(tiny_map, "cam0").had_context is False
    assert client.observe(tiny_map, make_frame(1), stream="cam0").sequence.step == 0


def test_refusals_become_typed_exceptions(client: Client, server: str, tiny_map: str) -> None:
    with pytest.raises(UnsupportedMediaTypeError) as e:
        client.observe(tiny_map, b"not an image")
    assert e.value.status == 415 and e.value.slug == "unsupported-media-type"
    assert "image/jpeg" in e.value.extra["allowed"] and e.value.request_id
    assert e.value.problem is not None and e.value.problem.instance == f"/v1/maps/{tiny_map}/observations"

    with pytest.raises(ConflictError) as e:
        client.create_map(tiny_map)
    assert e.value.slug == "map-exists"
    # made with the same options by an earlier creation (each sends its own key): not this one's
    twice = f"t-{uuid.uuid4().hex[:10]}"
    client.create_map(twice, seed=5)
    with pytest.raises(ConflictError) as e:
        client.create_map(twice, seed=5)
    assert e.value.slug == "map-exists"
    client.delete_map(twice)

    with pytest.raises(UnprocessableError) as e:
        client.create_map(tm={"activationThreshold": 2, "minThreshold": 9})
    assert e.value.slug == "invalid-configuration" and e.value.extra["errors"]

    with pytest.raises(BadRequestError) as e:
        client.observe(tiny_map, b"", top_k=10_000)
    assert e.value.extra["errors"][0]["name"] == "top_k"

    with Client(server) as anonymous, pytest.raises(UnauthorizedError) as e:
        anonymous.create_snapshot(tiny_map)
    assert e.value.slug == "unauthorized"
    assert client.list_snapshots(tiny_map) == []  # nothing was taken


def test_snapshots_round_trip(client: Client, tiny_map: str, make_frame, tmp_path) -> None:
    for place in range(3):
        client.observe(tiny_map, make_frame(place))
    snap = client.create_snapshot(tiny_map)
    assert (snap.seq, snap.kind) == (3, "manual")
    for place in range(3, 5):
        client.observe(tiny_map, make_frame(place))
    assert [s.snapshot_id for s in client.list_snapshots(tiny_map)] == [snap.snapshot_id]

    tar_path = client.download_snapshot(tiny_map, snap.snapshot_id, tmp_path / "snap.tar")
    assert not (tmp_path / "snap.tar.part").exists()
    with tarfile.open(tar_path) as tar:
        assert {"manifest.json", "map.sqlite", "memory.npz", "projection.npy"} <= set(tar.getnames())

    epoch = client.list_observations(tiny_map).epoch
    assert epoch and client.loop_closures(tiny_map).epoch == epoch
    restored = client.restore_snapshot(tiny_map, snap.snapshot_id)
    assert (restored.map_id, restored.observations, restored.discarded_observations) == (tiny_map, 3, 2)
    # the epoch tells a client following the pages with a cursor to read them again from 0
    assert client.list_observations(tiny_map).epoch == client.loop_closures(tiny_map).epoch != epoch
    kinds = sorted(s.kind for s in client.list_snapshots(tiny_map))
    assert kinds == ["manual", "pre-restore"]
    with pytest.raises(NotFoundError) as e:
        client.restore_snapshot(tiny_map, "no-such-snapshot")
    assert e.value.slug == "snapshot-not-found"
    with pytest.raises(NotFoundError):
        client.download_snapshot(tiny_map, "no-such-snapshot", tmp_path / "none.tar")
    assert not (tmp_path / "none.tar").exists() and not (tmp_path / "none.tar.part").exists()
    # The pre-restore snapshot is on the branch the restore left: it may go; the restored one may not.
    pre = next(s.snapshot_id for s in client.list_snapshots(tiny_map) if s.kind == "pre-restore")
    client.delete_snapshot(tiny_map, pre)
    assert [s.snapshot_id for s in client.list_snapshots(tiny_map)] == [snap.snapshot_id]
    assert client.get_map(tiny_map).snapshot_count == 1
    budget = client.memory_budget()
    assert budget.used_bytes + budget.reserve_bytes + budget.free_bytes == budget.total_bytes
    assert budget.reserve_bytes == max(m.parts["tm"] for m in budget.maps if m.open)
    assert tiny_map in {m.map_id for m in budget.maps}


# ------------------------------------------------------------------ where and what, raw frames, retries


def _drive_a_route(client: Client, map_id: str, make_frame, places: int = 5) -> dict[int, int]:
    """Learn `places` frames as one route with poses; then break the stream's sequence."""
    seqs = {}
    for place in range(places):
        pose = {"x": float(place), "y": 0.0, "yaw": 0.0, "frame_id": "map"}
        answer = client.observe(map_id, make_frame(place), label=f"place {place}",
                                metadata={"stamp": 100.0 + place, "pose": pose})
        seqs[place] = answer.seq
    client.reset_stream(map_id, "default")
    return seqs


def test_metadata_is_stored_and_returned(client: Client, tiny_map: str, make_frame) -> None:
    seqs = _drive_a_route(client, tiny_map, make_frame)
    answer = client.observe(tiny_map, make_frame(9), metadata=models.Metadata(stamp=7.5, note="dock"))
    assert answer.metadata is not None and answer.metadata.stamp == 7.5
    assert answer.metadata.model_extra == {"note": "dock"}
    for place in range(3):
        answer = client.observe(tiny_map, make_frame(place), learn=False)
    best = answer.matches[0]
    assert best.seq == seqs[2] and best.metadata is not None and best.metadata.stamp == 102.0
    assert best.metadata.pose == models.Pose(x=2.0, y=0.0, yaw=0.0, frame_id="map")
    page = client.list_observations(tiny_map, after_seq=seqs[0], limit=2)
    assert [o.seq for o in page.observations] == [seqs[1], seqs[2]] and page.next_after_seq == seqs[2]
    assert [o.metadata.pose.x for o in page.observations if o.metadata and o.metadata.pose] == [1.0, 2.0]


def test_a_repeated_idempotency_key_learns_once(client: Client, tiny_map: str, make_frame) -> None:
    key = uuid.uuid4().hex
    first = client.observe(tiny_map, make_frame(0), idempotency_key=key)
    again = client.observe(tiny_map, make_frame(0), idempotency_key=key)
    assert again == first  # the first reply, as it was sent
    assert client.get_map(tiny_map).observations == 1
    other = client.observe(tiny_map, make_frame(0))  # a fresh key: a new observation
    assert other.seq != first.seq
    with pytest.raises(UnprocessableError) as refused:  # the key with another frame
        client.observe(tiny_map, make_frame(1), idempotency_key=key)
    assert refused.value.slug == "idempotency-key-reused"
    assert client.get_map(tiny_map).observations == 2


def test_arrays_are_accepted_as_raw_frames(client: Client, tiny_map: str, make_picture) -> None:
    rgb = make_picture(3)
    learned = client.observe(tiny_map, rgb)
    assert learned.learned
    client.reset_stream(tiny_map, "default")
    as_rgb = client.observe(tiny_map, rgb, learn=False)
    client.reset_stream(tiny_map, "default")
    # The same picture as BGR with colour="bgr8" is the same frame: the same answer.
    as_bgr = client.observe(tiny_map, np.ascontiguousarray(rgb[:, :, ::-1]), colour="bgr8", learn=False)
    assert as_bgr.matches[0].seq == learned.seq
    assert as_bgr.sequence == as_rgb.sequence and as_bgr.matches == as_rgb.matches
    # BGRA from a camera driver (alpha is padding, here noise): the same frame again.
    alpha = np.random.default_rng(0).integers(0, 256, rgb.shape[:2], dtype=np.uint8)
    client.reset_stream(tiny_map, "default")
    as_bgra = client.observe(tiny_map, np.dstack([rgb[:, :, ::-1], alpha]), colour="bgra8", learn=False)
    assert as_bgra.sequence == as_rgb.sequence and as_bgra.matches == as_rgb.matches
    grey = rgb.mean(axis=2)
    assert client.observe(tiny_map, grey.astype(np.uint8)).learned
    assert client.observe(tiny_map, (grey * 257).astype(np.uint16)).learned
    assert client.observe(tiny_map, grey.astype(np.uint8)[:, :, None]).learned  # (H, W, 1)
    assert client.get_map(tiny_map).observations == 4


def test_a_stored_observation_and_its_thumbnail(client: Client, tiny_params: dict, make_frame) -> None:
    map_id = f"t-{uuid.uuid4().hex[:10]}"
    assert client.create_map(map_id, thumbnails=True, **tiny_params).thumbnails is True
    try:
        posted = client.observe(map_id, make_frame(1), label="dock", metadata={"stamp": 1.5})
        assert posted.seq is not None
        stored = client.get_observation(map_id, posted.seq)
        assert (stored.observation_id, stored.seq) == (posted.observation_id, posted.seq)
        assert stored.label == "dock" and stored.has_thumbnail is True
        assert stored.metadata is not None and stored.metadata.stamp == 1.5
        assert client.thumbnail(map_id, posted.seq)[:3] == b"\xff\xd8\xff"
        client.observe(map_id, make_frame(2), learn=False)  # a localisation: its image kept in memory only
        answer = client.recent(map_id).answers[-1]
        assert answer.has_thumbnail and answer.answer_id is not None
        assert client.recent_thumbnail(map_id, answer.answer_id)[:3] == b"\xff\xd8\xff"
        with pytest.raises(NotFoundError):
            client.get_observation(map_id, posted.seq + 100)
    finally:
        client.delete_map(map_id)


def test_ros_stream_names_with_a_slash(client: Client, tiny_map: str, make_frame) -> None:
    answer = client.observe(tiny_map, make_frame(0), stream="robot1/cam0")
    assert answer.stream == "robot1/cam0"
    assert client.reset_stream(tiny_map, "robot1/cam0").had_context is True
    assert "robot1/cam0" in client.get_map(tiny_map).streams


def test_a_revisit_names_its_place(client: Client, tiny_map: str, make_frame) -> None:
    seqs = _drive_a_route(client, tiny_map, make_frame, 12)
    # another robot (the stream that learned the route has it in its short-term memory, science §11.6)
    answers = [client.observe(tiny_map, make_frame(place), learn=False, stream="query") for place in range(9)]
    assert answers[0].place is None  # a stream's first frame claims nothing (warm-up)
    place = answers[-1].place
    assert isinstance(place, models.Place)
    assert place.seq == seqs[8] and place.label == "place 8" and place.stream == "default"
    assert 0.0 <= place.confidence <= 1.0 and place.support is not None and place.support >= 1
    assert place.revisit is (place.confidence >= client.get_map(tiny_map).revisit_threshold)
    assert place.metadata is not None and place.metadata.pose is not None and place.metadata.pose.x == 8.0
    window = client.recent(tiny_map, limit=3)
    assert [a.reply.place.seq if a.reply.place else None for a in window.answers][-1] == seqs[8]
    # the place's id and the frame's information are typed fields, as is the map's places block
    assert place.place_id == place.seq and place.low_information is False
    places = client.get_map(tiny_map).places
    assert isinstance(places, models.PlacesInfo)
    assert places.appearances == len(seqs) and places.visits_logged == 0


def test_a_second_pass_is_consolidated_into_known_rows(client: Client, tiny_map: str, make_frame) -> None:
    seqs = _drive_a_route(client, tiny_map, make_frame, 12)
    again = [client.observe(tiny_map, make_frame(place), stream="second") for place in range(12)]
    visits = [o for o in again if o.consolidated_into is not None]
    assert visits and all(o.seq is None and o.observation_id is None and o.consolidated_into in seqs.values()
                          for o in visits)
    # the pass's warm-up rows, joined to the places it then found, are visits of them now (schema 12)
    listed = client.list_observations(tiny_map, limit=500).observations
    joined = [o.seq for o in listed if o.joined_to is not None]  # listed still, with the place's row
    assert {o.seq for o in again if o.seq is not None} <= {o.seq for o in listed}
    assert client.get_map(tiny_map).places.visits_logged == len(visits) + len(joined)


def test_the_revisit_threshold_can_be_changed(client: Client, tiny_map: str) -> None:
    changed = client.update_map(tiny_map, revisit_threshold=0.7)
    assert changed.revisit_threshold == 0.7
    assert client.get_map(tiny_map).revisit_threshold == 0.7
    with pytest.raises(UnprocessableError):
        client.update_map(tiny_map, revisit_threshold=1.5)


def test_loop_closures_are_paged_and_exported(client: Client, tiny_map: str, make_frame) -> None:
    seqs = _drive_a_route(client, tiny_map, make_frame, 12)
    client.update_map(tiny_map, revisit_threshold=0.0)  # every answer a revisit: the log fills
    answers = [client.observe(tiny_map, make_frame(place), learn=False, stream="robot") for place in range(9)]
    told = [a for a in answers if a.place is not None and a.place.revisit]
    page = client.loop_closures(tiny_map, limit=2)
    assert len(page.loop_closures) == 2 and page.next_after == page.loop_closures[-1].id
    rest = client.loop_closures(tiny_map, after=page.next_after, limit=500)
    log = page.loop_closures + rest.loop_closures
    assert [(c.stream, c.seq, c.place.seq) for c in log] == [("robot", None, a.place.seq) for a in told]
    assert all(c.place.seq in seqs for c in log)
    csv_text = client.export_loop_closures(tiny_map, "csv").decode()
    assert csv_text.splitlines()[0].startswith("stamp,observation_id,seq,stream,place_stamp")
    assert len(csv_text.splitlines()) == len(log) + 1
    assert len(client.export_loop_closures(tiny_map, "jsonl").decode().splitlines()) == len(log)
    assert isinstance(client.export_loop_closures(tiny_map, "g2o"), bytes)  # its media type, read live too
    assert all(c.retracts is None for c in log)  # closures, no retraction entry yet
    # the end for now: next_after is None, and the next poll goes on from the last id read, not from 0
    assert rest.next_after is None and rest.cursor(page.next_after) == log[-1].id
    polled = client.loop_closures(tiny_map, after=rest.cursor(page.next_after))
    assert polled.loop_closures == [] and polled.cursor(log[-1].id) == log[-1].id
    # nothing pruned: the oldest id kept is the first, and no follower missed anything
    assert rest.oldest == polled.oldest == log[0].id and not page.missed(0) and not rest.missed(log[0].id)


def test_a_page_tells_a_follower_it_fell_behind_the_prune() -> None:
    page = models.LoopClosureList(loop_closures=[], next_after=None, oldest=10, epoch="e")
    assert page.missed(8) and page.missed(0)  # ids 9 (or 1..9) were pruned before they were read
    assert not page.missed(9) and not page.missed(12)
    assert not models.LoopClosureList(loop_closures=[], oldest=None).missed(0)  # an empty log
    assert page.cursor(12) == 12  # an empty page: poll again from the same id


def test_a_repair_lists_then_undoes_and_a_second_finds_nothing(client: Client, tiny_map: str,
                                                              make_frame) -> None:
    _drive_a_route(client, tiny_map, make_frame, 12)
    listed = client.repair(tiny_map)
    assert listed.map_id == tiny_map and not listed.repaired and listed.window >= 1
    done = client.repair(tiny_map, undo=True)
    assert done.repaired and done.rows_added == len(listed.splits)
    assert [s.visit for s in done.splits] == [s.visit for s in listed.splits]
    again = client.repair(tiny_map, undo=True)
    assert again.repaired and again.splits == [] and again.unjoins == [] and again.retractions == []
