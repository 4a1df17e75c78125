"""`cortexloc_node` on real rclpy against a real `cortexloc serve`, all inside a loopback-only network
namespace (harness.py): a real Nordland route with odometry and camera_info gives places and loop
closures on the output topics; a service stopped and started again is recovered from without posting an
answered frame twice; a slow service makes the queue drop by its policy, reported on diagnostics; bad
parameters stop the node at start with a clear error. The README's three commands: test_readme_ros.py.
"""

from __future__ import annotations

import math
import os
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.clients.ros2.harness import TINY_MAP, NodeProcess, Relay, Service, in_loopback_netns, node_params

NORDLAND = (Path(os.environ["CORTEXLOC_SHARED_DATA"]) if os.environ.get("CORTEXLOC_SHARED_DATA")
            else Path(__file__).resolve().parents[3].parent / "shared" / "data") / "nordland_tiny_64x32"
#: 30 places of the line, driven in summer then in winter (the frames are aligned by name).
PLACES = range(100, 130)
T0_NS = 1_700_000_000 * 1_000_000_000
PERIOD_NS = 100_000_000
SPACING_M, DRIFT_M = 10.0, 5.0
PORT = 18000


#: The tests that drive the real route skip before their namespace, service and node start where the
#: route is not (a clone without ../shared, as CI runs it: otherwise each started them only to skip).
needs_nordland = pytest.mark.skipif(not NORDLAND.is_dir(), reason=f"the Nordland route is not in {NORDLAND} "
                                    "(set CORTEXLOC_SHARED_DATA)")


def _frame(season: str, place: int) -> np.ndarray:
    path = NORDLAND / season / f"images-{(place + 1) * 10:05d}.png"
    if not path.is_file():
        pytest.skip(f"the Nordland route is not in {NORDLAND} (set CORTEXLOC_SHARED_DATA)")
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


def _route(n: int | None = None) -> list[tuple[np.ndarray, int, float, float]]:
    """(frame, stamp_ns, x, y): the summer pass then the winter pass, 5 m to the side (odometry drift)."""
    out = []
    for lap, season in enumerate(("summer", "winter")):
        for j, place in enumerate(PLACES):
            i = lap * len(PLACES) + j
            out.append((_frame(season, place), T0_NS + i * PERIOD_NS, j * SPACING_M, lap * DRIFT_M))
    return out[:n]


class World:
    """The service, a relay in front of it, a tiny map, the probe; closed in reverse."""

    def __init__(self, tmp: Path, map_params: dict | None = None) -> None:
        """`map_params`: the map's creation parameters (default `TINY_MAP`)."""
        from cortexloc_client import Client
        from tests.clients.ros2.probe import start_probe

        self.tmp = tmp
        self.service = Service(tmp, PORT).start()
        self.relay = Relay(self.service.url)
        self.client = Client(self.service.url)
        self.map_id = "ros-test"
        self.client.create_map(self.map_id, **(TINY_MAP if map_params is None else map_params))
        self.probe = start_probe()
        self.nodes: list[NodeProcess] = []

    def node(self, **params: object) -> NodeProcess:
        node = NodeProcess(self.tmp, node_params(self.relay.url, self.map_id, **params),
                           f"node{len(self.nodes)}")
        self.nodes.append(node)
        return node

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        from tests.clients.ros2.probe import stop_probe

        for node in self.nodes:
            node.stop()
        stop_probe(self.probe)
        self.relay.close()
        self.client.close()
        self.service.stop()


def _stamps(docs: list[dict]) -> list[int]:
    return [d["stamp"]["sec"] * 1_000_000_000 + d["stamp"]["nanosec"] for d in docs]


@needs_nordland
@in_loopback_netns
def test_a_route_with_odometry_and_camera_info_gives_places_and_loop_closures_on_topics(tmp_path):
    route = _route()
    # the service's default map: the tiny one closes these loops at some seeds only
    w = World(tmp_path, map_params={})
    try:
        node = w.node(trail="robot1")
        w.probe.wait_connected()
        for i, (frame, stamp, x, y) in enumerate(route):
            if i < len(PLACES):  # summer: rgb8, rows padded past the width
                w.probe.publish(frame, stamp, x, y, encoding="rgb8", pad=8)
            else:  # winter: mono16 from a big-endian camera, padded too (the service reads it as 8-bit x 257)
                grey = (frame[:, :, 0].astype(np.uint16) * 257).astype(">u2")
                # each message delivered twice (a camera bridged twice): the same stamp and bytes are one
                # frame; before, the second was answered from the service's store and its place and loop
                # closure published again under the same closure id
                for _ in range(2):
                    w.probe.publish(grey, stamp, x, y, encoding="mono16", pad=6)
            w.probe.spin(0.01)
        w.probe.wait(lambda: len(w.probe.places) >= len(route), 120, "an answer per frame")
        w.probe.wait(lambda: w.probe.last_diagnostics().get("answered") == str(len(route)), 10,
                     "diagnostics counting every answer")
        places, closures = w.probe.places, w.probe.closures
        revisits = [p for p in places if p["place"] and p["place"]["revisit"]]
        w.probe.wait(lambda: len(closures) >= len(revisits), 10, "a loop closure per revisit")
        assert _stamps(places) == [s for _, s, _, _ in route]  # every frame once, in order
        assert all(p["frame_id"] == "cam_optical" and p["map_id"] == w.map_id for p in places)
        assert [(p["pose"]["x"], p["pose"]["y"], p["pose"]["frame_id"]) for p in places] == \
            [(x, y, "odom") for _, _, x, y in route]  # each frame's odometry, matched by stamp

        # loop closures: winter frames naming summer rows, with both stamps and both poses
        assert len(closures) >= 3, [p["place"] for p in places[len(PLACES):]]
        summer = {s: x for _, s, x, y in route[: len(PLACES)]}
        print(f"{len(closures)} loop closures of {len(PLACES)} winter frames; place error (m): "
              f"{[round(c['pose']['x'] - c['place_pose']['x']) for c in closures]}")
        for c in closures:
            stamp, place_stamp = _stamps([c])[0], _stamps([{"stamp": c["place_stamp"]}])[0]
            assert stamp >= route[len(PLACES)][1] and place_stamp in summer
            assert c["pose"]["y"] == DRIFT_M and c["place_pose"]["y"] == 0.0
            assert c["place_pose"]["x"] == summer[place_stamp]
            assert abs(c["pose"]["x"] - c["place_pose"]["x"]) <= 2 * SPACING_M  # the same place, +-2 frames
            assert c["confidence"] >= 0.5 and c["stream"] == "test/cam"
        assert _stamps(closures) == _stamps(revisits)
        ids = [c["id"] for c in closures]
        assert None not in ids and len(set(ids)) == len(ids)  # a back end gets each closure once

        # the place's stored pose as PoseWithCovarianceStamped, stamped with the frame's stamp
        with_pose = [p for p in places if p["place"] and p["place"]["pose"]]
        assert [(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, m.pose.pose.position.x,
                 m.pose.pose.position.y, m.header.frame_id) for m in w.probe.poses] == \
            [(s, p["place"]["pose"]["x"], p["place"]["pose"]["y"], "odom")
             for s, p in zip(_stamps(with_pose), with_pose, strict=True)]
        # RViz: every closure's edge in the last marker array
        w.probe.wait(lambda: len(w.probe.markers) == len(closures), 10, "a marker array per closure")
        marker = w.probe.markers[-1].markers[0]
        assert marker.header.frame_id == "odom" and len(marker.points) == 2 * len(closures)
        # each edge red at the map's revisit_threshold, green at 1 (before: green = confidence, all ~green)
        from cortexloc_ros.answers import closure_colour

        threshold = w.client.get_map(w.map_id).revisit_threshold
        assert np.allclose([(k.r, k.g) for k in marker.colors[0::2]],
                           [closure_colour(c["confidence"], threshold) for c in closures], atol=1e-6)
        # camera_info's intrinsics stored with the learned rows (what geometric verification reads)
        stored = w.client.list_observations(w.map_id, limit=5).observations[0].metadata
        assert stored.model_extra["camera"] == {"fx": 60.0, "fy": 60.0, "cx": 32.0, "cy": 16.0,
                                                "distortion": [0.01, -0.02, 0.0, 0.0, 0.0]}
        assert stored.model_extra["stamp_ns"] == str(route[0][1])
        assert stored.model_extra["trail"] == "robot1"  # the trail parameter, on the frames posted
        d = w.probe.last_diagnostics()
        assert (d["service"], d["dropped"], d["refused"], d["unsupported"]) == ("up", "0", "0", "0")
        assert (d["received"], d["duplicates"]) == (str(len(route) + len(PLACES)), str(len(PLACES)))
        assert d["revisits"] == str(len(closures))  # each revisit counted once
        assert node.stop() == 0
        assert node.log().count("a camera message came twice") == 1, node.log()
    finally:
        w.close()


@needs_nordland
@in_loopback_netns
def test_the_node_recovers_from_a_service_restart_and_posts_no_answered_frame_twice(tmp_path):
    route = _route(20)
    w = World(tmp_path)
    try:
        node = w.node(image_transport="compressed")  # PNGs as CompressedImage, posted as they are
        w.probe.wait_connected(compressed=True)
        for frame, stamp, x, y in route[:10]:
            w.probe.publish(frame, stamp, x, y, png=True)
        w.probe.wait(lambda: len(w.probe.places) == 10, 60, "answers before the outage")

        w.service.stop()
        down_from = len(w.probe.diagnostics)
        for frame, stamp, x, y in route[10:]:
            w.probe.publish(frame, stamp, x, y, png=True)
        # while it is down the executor is free: diagnostics keep coming, saying so
        w.probe.wait(lambda: sum(d[1].get("service") == "down" for d in w.probe.diagnostics[down_from:]) >= 4,
                     30, "diagnostics during the outage")
        down = [d for d in w.probe.diagnostics[down_from:] if d[1].get("service") == "down"]
        gaps = np.diff([t for t, _, _ in down])
        print(f"diagnostics while the service was down: {len(down)}, "
              f"intervals {np.round(gaps, 3).tolist()} s")
        assert all(level == 2 for _, _, level in down)  # ERROR
        assert int(down[-1][1]["received"]) == 20 and int(down[-1][1]["retries"]) >= 1

        w.relay.lose_next_reply()  # the first post after the restart is stored, its reply lost
        w.service.start()
        w.probe.wait(lambda: len(w.probe.places) == 20, 120, "answers after the restart")
        w.probe.spin(0.5)
        assert _stamps(w.probe.places) == [s for _, s, _, _ in route]  # each frame answered once

        posts = w.relay.posts
        outcomes = Counter(o for _, o in posts)
        assert outcomes["lost"] == 1 and outcomes["down"] >= 1 and outcomes["200"] == 20, outcomes
        for i, (key, outcome) in enumerate(posts):
            if outcome == "200":  # answered: never posted again
                assert key not in [k for k, _ in posts[i + 1:]], key
        lost = next(k for k, o in posts if o == "lost")
        tries = [o for k, o in posts if k == lost]  # the frame in flight: refused while down, then ...
        assert tries[-2:] == ["lost", "200"] and set(tries[:-2]) <= {"down"}  # retried with its key: replayed
        stamps = [o.metadata.model_extra["stamp_ns"]
                  for o in w.client.list_observations(w.map_id, limit=100).observations]
        assert len(stamps) == len(set(stamps))  # no frame learned twice
        assert node.stop() == 0
    finally:
        w.close()


@needs_nordland
@in_loopback_netns
def test_a_slow_service_makes_the_queue_drop_by_its_policy_and_diagnostics_say_so(tmp_path):
    route = _route(8)
    w = World(tmp_path)
    try:
        w.node(queue__size=2, queue__policy="drop_oldest")
        w.probe.wait_connected()
        w.relay.hold()  # the service takes its time
        w.probe.publish(*route[0])
        w.probe.wait(lambda: w.relay.held == 1, 30, "the first frame in flight")
        for r in route[1:]:
            w.probe.publish(*r)
        w.probe.wait(lambda: w.probe.last_diagnostics().get("received") == "8", 30, "every frame received")
        d = w.probe.last_diagnostics()
        assert (d["queue_depth"], d["queue_size"], d["dropped"], d["answered"]) == ("2", "2", "5", "0")
        assert w.probe.diagnostics[-1][2] == 1  # WARN
        w.relay.release()
        w.probe.wait(lambda: len(w.probe.places) == 3, 60, "the frames kept")
        # drop_oldest: the one in flight, then the newest two
        assert _stamps(w.probe.places) == [route[0][1], route[6][1], route[7][1]]
        w.probe.wait(lambda: w.probe.last_diagnostics().get("answered") == "3", 10, "diagnostics")
        assert w.probe.last_diagnostics()["dropped"] == "5"
    finally:
        w.close()


@in_loopback_netns
def test_frames_the_transport_loses_to_a_best_effort_subscription_are_counted_and_told(tmp_path):
    """Large raw frames over UDP with the default best-effort image subscription: some never reach the node
    (an outside probe: 1-4 of 5 at 640x480 and over). Diagnostics count them as `lost` (the middleware's
    message-lost event), the level is WARN, and the log says once what to do; before, `received` counted
    only what arrived and nothing showed the loss."""
    rng = np.random.default_rng(0)
    big = rng.integers(0, 256, (1080, 1920, 3), dtype=np.uint8)
    with World(tmp_path) as w:
        node = w.node(**{"qos_overrides./cam/image_raw.subscription.reliability": "best_effort",
                         "rate.every_n": 1000})  # only what reaches the node matters here, not the posts
        w.probe.wait_connected()
        sent = 0
        for i in range(40):
            w.probe.publish(big, T0_NS + i * PERIOD_NS, 0.0, 0.0)
            sent += 1
            w.probe.spin(0.0)
            d = w.probe.last_diagnostics()
            if d.get("lost", "0") != "0":
                break
        w.probe.wait(lambda: int(w.probe.last_diagnostics().get("received", "0"))
                     + int(w.probe.last_diagnostics().get("lost", "0")) >= 1, 30, "diagnostics of the frames")
        d = w.probe.last_diagnostics()
        received, lost = int(d["received"]), int(d["lost"])
        assert lost > 0 and received < sent, (sent, d)
        w.probe.wait(lambda: w.probe.diagnostics[-1][2] == 1, 10, "a WARN")  # WARN
        assert node.stop() == 0
        assert node.log().count("lost in transport") == 1, node.log()


@needs_nordland
@in_loopback_netns
def test_a_camera_that_does_not_stamp_has_every_frame_answered_without_a_pose_and_is_told_once(tmp_path):
    # Before, each frame stamped 0 took the odometry pose of stamp 0: distinct images at one pose, which the
    # service merged as a robot standing still. A stamp that is zero, or the previous frame's, identifies
    # no frame: the frame goes without a pose, and the service judges the move by appearance.
    route = _route(7)
    with World(tmp_path) as w:
        node = w.node()
        w.probe.wait_connected()
        for frame, _, x, y in route[:5]:  # five frames, all stamped 0 (a driver that does not stamp)
            w.probe.publish(frame, 0, x, y)
            w.probe.spin(0.01)
        # then a stamping camera that stamps one frame twice: the second goes without a pose
        for frame, _, x, y in route[5:]:
            w.probe.publish(frame, route[5][1], x, y)
            w.probe.spin(0.01)
        w.probe.wait(lambda: len(w.probe.places) == 7, 60, "an answer per frame")
        assert all(p["stamp"] == {"sec": 0, "nanosec": 0} for p in w.probe.places[:5])
        assert [p["pose"] is None for p in w.probe.places] == [True] * 5 + [False, True]
        assert w.probe.places[5]["pose"]["x"] == route[5][2]
        keys = [k for k, _ in w.relay.posts]
        assert len(set(keys)) == 7 and [o for _, o in w.relay.posts] == ["200"] * 7  # none refused 422
        w.probe.wait(lambda: w.probe.last_diagnostics().get("answered") == "7", 10, "diagnostics")
        assert (w.probe.last_diagnostics()["refused"], w.probe.last_diagnostics()["no_pose"]) == ("0", "6")
        stored = [o.metadata for o in w.client.list_observations(w.map_id, limit=100).observations]
        assert all(m.pose is None for m in stored if m.model_extra["stamp_ns"] == "0")
        assert node.stop() == 0
        assert node.log().count("the camera's stamps do not tell its frames apart") == 1, node.log()


@in_loopback_netns
def test_a_bag_played_again_is_a_new_drive_whose_frames_are_posted_and_told(tmp_path):
    # `ros2 bag play --loop`: the stamps jump back to the start and every frame of the second pass repeats
    # one of the first. Before, each had the first pass's key, was answered from the service's store
    # (nothing learned or localised) and no log line said so. Now: a new drive, the stream reset, new keys,
    # from the third message of the pass (the third in a row to go back): the first two are repeats of the
    # first pass's messages, not posted.
    rng = np.random.default_rng(5)
    frames = [rng.integers(0, 256, (32, 64, 3), dtype=np.uint8) for _ in range(10)]  # a pass of 2.7 s
    passes = 2
    with World(tmp_path) as w:
        node = w.node()
        w.probe.wait_connected()
        for _ in range(passes):
            for i, frame in enumerate(frames):
                w.probe.publish(frame, T0_NS + i * 3 * PERIOD_NS, i * SPACING_M, 0.0)
                w.probe.spin(0.01)
        n = passes * len(frames) - 2
        w.probe.wait(lambda: len(w.probe.places) == n, 60, "an answer per frame of both passes")
        keys = [k for k, _ in w.relay.posts]
        assert len(set(keys)) == n and [o for _, o in w.relay.posts] == ["200"] * n  # posted, not replayed
        # the second pass matches its own pass's odometry, at the poses published with it
        assert [p["pose"]["x"] for p in w.probe.places] == [i * SPACING_M for i in range(10)] + \
            [i * SPACING_M for i in range(2, 10)]
        w.probe.wait(lambda: w.probe.last_diagnostics().get("answered") == str(n), 10, "diagnostics")
        assert w.probe.last_diagnostics()["duplicates"] == "2"
        assert node.stop() == 0
        log = node.log()
        assert log.count("the camera's stamps went back 2.700 s (3 frames in a row") == 1, log
        assert log.count("a new drive, the camera's stamps went back") == 1, log  # the stream reset


@in_loopback_netns
def test_a_spoilt_reply_and_odometry_that_is_not_finite_leave_every_frame_posted_once(tmp_path):
    # An outside probe: one reply a proxy answered 200 text/html ended the node's poster thread (nothing was
    # posted after it, and diagnostics still said "service up"); and each frame matched to odometry with NaN
    # or Inf (an EKF before it converged) was refused 422 and lost. Now the spoilt reply is retried with its
    # key (answered from the service's store: learned once), and such odometry is ignored: those frames go
    # without a pose.
    rng = np.random.default_rng(7)
    frames = [rng.integers(0, 256, (32, 64, 3), dtype=np.uint8) for _ in range(8)]
    bad = {2: (math.nan, 0.0), 3: (math.inf, 0.0), 4: (0.0, math.nan), 5: (1e12, 0.0)}  # frame: (x, yaw)
    with World(tmp_path) as w:
        node = w.node()
        w.probe.wait_connected()
        w.relay.spoil_next_reply()
        for i, frame in enumerate(frames):
            x, yaw = bad.get(i, (i * SPACING_M, 0.0))
            w.probe.publish(frame, T0_NS + i * PERIOD_NS, x, 0.0, yaw=yaw)
            w.probe.spin(0.01)
        w.probe.wait(lambda: len(w.probe.places) == len(frames), 60, "an answer per frame")
        keys, outcomes = zip(*w.relay.posts, strict=True)
        assert outcomes == ("spoilt",) + ("200",) * len(frames), outcomes
        assert keys[0] == keys[1] and len(set(keys)) == len(frames)  # the spoilt one again, with its key
        assert [p["pose"] is None for p in w.probe.places] == [i in bad for i in range(len(frames))]
        assert len(w.client.list_observations(w.map_id, limit=100).observations) == len(frames)  # once each
        n = str(len(frames))
        w.probe.wait(lambda: w.probe.last_diagnostics().get("answered") == n, 10, "diagnostics")
        d = w.probe.last_diagnostics()
        assert (d["refused"], d["failed"], d["no_pose"], d["service"]) == ("0", "0", "4", "up"), d
        assert node.stop() == 0
        log = node.log()
        # once a minute, not each time
        assert log.count("odometry ignored: its pose is not finite or beyond") == 1, log
        assert log.count("that is not the service's answer") == 1 and "Traceback" not in log, log


@in_loopback_netns
def test_bad_parameters_stop_the_node_at_start_with_a_clear_error(tmp_path):
    import subprocess
    import sys

    runs = iter(range(100))

    def start(**params: object) -> tuple[int, str]:
        node = NodeProcess(tmp_path, {k.replace("__", "."): v for k, v in params.items()}, f"bad{next(runs)}")
        node.proc.wait(timeout=60)
        return node.proc.returncode, node.log()

    rc, log = start(service_url="ftp://robot", map="Bad Map", top_k=-1, queue__policy="sometimes",
                    **{"rate.every_n": 0, "rate.min_distance": 2.0})
    assert rc == 2, log
    for line in ("service_url: 'ftp://robot' is not an http(s)://host[:port] URL", "map: 'Bad Map'",
                 "top_k: -1 must be 0 or more",
                 "queue.policy: 'sometimes' is not one of drop_oldest, drop_newest",
                 "rate.every_n: 0 must be >= 1", "rate.min_distance needs odometry"):
        assert line in log, log
    rc, log = start(api_key="s3cret")
    assert rc == 2 and "api_key: the API key is never a parameter" in log, log
    rc, log = start(**{"queue.size": "ten", "qeue.size": 3})
    assert rc == 2 and "queue.size: 'ten' is not an integer" in log and "qeue.size: no such parameter" in log
    rc, log = start(api_key_file=str(tmp_path / "missing-key"))
    assert rc == 2 and "api_key_file: cannot read a key from" in log, log
    assert "Traceback" not in log
    # an empty value rcl cannot parse, and a port out of range: one line each, exit 2 (the first was an
    # RCLError traceback and exit 1; the second was retried forever)
    p = subprocess.run([sys.executable, "-m", "cortexloc_ros", "--ros-args", "-p", "map:="],
                       capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert p.returncode == 2 and "map: -p map:= gives no value" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr
    rc, log = start(service_url="http://127.0.0.1:99999", place_covariance="[1.0, .nan, 0.1]")
    assert rc == 2 and "service_url: 'http://127.0.0.1:99999' has no port 1-65535" in log, log
    assert "place_covariance: [1.0, nan, 0.1] must be 3 finite numbers" in log, log
    # a stray word after --ros-args (an unquoted value with a space): one line, not rclpy's traceback
    p = subprocess.run([sys.executable, "-m", "cortexloc_ros", "--ros-args", "-p", "stream:=front", "cam"],
                       capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert p.returncode == 2 and "unknown ROS arguments" in p.stderr and "['cam']" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr


@in_loopback_netns
def test_a_bad_topic_name_or_a_value_the_service_refuses_exits_2_in_one_line_and_help_prints_usage(tmp_path):
    import subprocess
    import sys

    runs = iter(range(100))

    def start(**params: object) -> tuple[int, str]:
        node = NodeProcess(tmp_path, params, f"refused{next(runs)}")
        node.proc.wait(timeout=60)
        return node.proc.returncode, node.log()

    rc, log = start(**{"topics.place": "1bad", "topics.markers": "a b"})
    assert rc == 2, log
    assert "topics.place: '1bad' is not a ROS topic name (topic name token must not start with a number)" \
        in log, log
    assert "topics.markers: 'a b' is not a ROS topic name" in log and "Traceback" not in log, log
    rc, log = start(top_k=-1, stream="front cam")
    assert rc == 2 and "top_k: -1 must be 0 or more" in log and "stream: 'front cam' is not a stream name" \
        in log and "Traceback" not in log, log
    # a stream taken from an image topic the service would refuse (9 parts): refused at start, not per frame
    rc, log = start(**{"topics.image": "/a/b/c/d/e/f/g/h/image_raw"})
    assert rc == 2 and "stream: 'a/b/c/d/e/f/g/h/image_raw' is not a stream name" in log, log
    # --help: the usage, each parameter with its default, the README; the node is not started
    p = subprocess.run([sys.executable, "-m", "cortexloc_ros", "--help"], capture_output=True, text=True,
                       timeout=60, cwd=tmp_path)
    assert p.returncode == 0 and p.stdout.startswith("usage: cortexloc-ros"), p.stdout + p.stderr
    assert "  top_k (default 5)" in p.stdout and "README.md" in p.stdout and "cortexloc_node" not in p.stderr


def _wait_for_log(node: NodeProcess, text: str, timeout_s: float = 60) -> str:
    import time

    deadline = time.monotonic() + timeout_s
    while text not in node.log():
        if node.proc.poll() is not None or time.monotonic() > deadline:
            pytest.fail(f"the node did not log {text!r}:\n{node.log()}")
        time.sleep(0.1)
    return node.log()


@in_loopback_netns
def test_the_shipped_params_file_applies_to_a_node_in_a_namespace_or_renamed(tmp_path):
    # Keyed `cortexloc_node:`, the file applied to the root namespace's cortexloc_node only: a node started
    # in a namespace (the launch file's namespace:=robot1) or renamed ran on the defaults with no word.
    shipped = (Path(__file__).resolve().parents[3] / "clients/ros2/config/params.yaml").read_text()
    assert "    map: default\n" in shipped
    mine = tmp_path / "my_params.yaml"
    mine.write_text(shipped.replace("    map: default\n", "    map: from-file\n"))
    for ns, name in (("/robot1", None), ("/robot2", "cam2")):
        remaps = ["-r", f"__ns:={ns}"] + (["-r", f"__node:={name}"] if name else [])
        node = NodeProcess(tmp_path, {}, f"params{ns.strip('/')}", ros_args=("--params-file", str(mine),
                                                                              *remaps))
        try:
            log = _wait_for_log(node, " run id ")
        finally:
            assert node.stop() == 0
        assert f"map 'from-file' stream '{ns.strip('/')}/camera/image_raw'" in log, log
        assert f"[{ns.strip('/')}.{name or 'cortexloc_node'}]" in log, log


@in_loopback_netns
def test_each_kind_of_skipped_frame_is_told_and_malformed_frames_are_counted_apart(tmp_path):
    # Before, one line per encoding: after the first malformed rgb8 frame, frames with other faults were
    # skipped silently, counted as `unsupported`. No service needed: frames are skipped before the queue.
    from sensor_msgs.msg import Image

    from tests.clients.ros2.probe import start_probe, stop_probe

    probe = start_probe()
    node = NodeProcess(tmp_path, node_params("http://127.0.0.1:9", "m"))
    try:
        probe.wait_connected()
        good = bytes(64 * 32 * 3)
        bad = [dict(width=64, height=32, step=128, data=good),  # step shorter than a row
               dict(width=64, height=32, step=192, data=good[:100]),  # data shorter than the header says
               dict(width=0, height=0, step=0, data=b""),  # 0x0
               dict(width=0, height=32, step=192, data=good),  # 0 width
               dict(width=64, height=32, step=100, data=good),  # a short step again: not said again
               dict(width=64, height=32, step=192, data=good, encoding="yuv422")]
        for i, fields in enumerate(bad):
            msg = Image(encoding=fields.pop("encoding", "rgb8"), **fields)
            msg.header.stamp.sec = 1_700_000_000 + i
            probe.images.publish(msg)
            probe.spin(0.01)
        probe.wait(lambda: probe.last_diagnostics().get("received") == str(len(bad)), 30,
                   "every frame received")
        d = probe.last_diagnostics()
        assert (d["malformed"], d["unsupported"]) == ("5", "1"), d
        assert probe.diagnostics[-1][2] != 0  # not OK
    finally:
        assert node.stop() == 0
        stop_probe(probe)
    lines = [line for line in node.log().splitlines() if "frame skipped" in line]
    assert len(lines) == 4, node.log()  # one per kind of fault: short step, short data, no pixels, encoding
    assert "step 128 is shorter than a row of 192 bytes" in lines[0]
    assert "the message holds 100 bytes" in lines[1] and "0x0 has no pixels" in lines[2]
    assert "'yuv422' is not one the service takes" in lines[3]


@in_loopback_netns
def test_a_node_stopped_with_frames_queued_says_how_many_it_drops(tmp_path):
    # Before, SIGTERM with frames queued (the service unreachable) dropped them without a line. The line is
    # logged after the context is shut down: not through the node's rosout publisher, whose context is gone.
    import signal

    from tests.clients.ros2.probe import start_probe, stop_probe

    probe = start_probe()
    rng = np.random.default_rng(1)
    for sig, n in ((signal.SIGTERM, 4), (signal.SIGINT, 1)):
        node = NodeProcess(tmp_path, node_params("http://127.0.0.1:9", "m"), f"stop{sig.name}")
        try:
            probe.wait_connected()
            for i in range(n):
                frame = rng.integers(0, 256, (32, 64, 3), dtype=np.uint8)
                probe.publish(frame, T0_NS + i * PERIOD_NS, i, 0.0)
            queued = {"received": str(n), "queue_depth": str(n)}
            probe.wait(lambda q=queued: {k: probe.last_diagnostics().get(k) for k in q} == q, 30,
                       "the frames queued")
            os.kill(node.proc.pid, sig)
            assert node.proc.wait(timeout=30) == 0
        finally:
            node.stop()
            probe.diagnostics.clear()
        log = node.log()
        assert f"stopping: {n} frame{'s' * (n != 1)} queued not posted" in log, log
        assert "Failed to publish log message to rosout" not in log, log
    stop_probe(probe)
