"""The node's parts that need no ROS (cortexloc_ros.core, .params, .answers): raw frames from Image fields,
idempotency keys, odometry matching, the rate filter, the queue's drop policies, the parameters' checks
and the loop-closure document's relative pose (the service's g2o convention)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cortexloc_ros.core", reason="the ROS 2 node is not installed (make install-ros)")

from cortexloc_ros.answers import loop_closure_json, place_json
from cortexloc_ros.core import (
    JUMP_CONFIRM,
    FrameKeys,
    FrameQueue,
    LogLimiter,
    OdometryBuffer,
    Pose2D,
    RateFilter,
    Stamp,
    idempotency_key,
    image_array,
    quaternion_from_matrix,
    yaw_from_quaternion,
)
from cortexloc_ros.params import (
    PARAMETERS,
    ConfigError,
    config_warnings,
    empty_overrides,
    read_config,
    trail_of,
)

from cortexloc_client import POSE_MAX_ABS, YAW_MAX_ABS, Observation

DEFAULTS = {name: default for name, (default, _) in PARAMETERS.items()}


def _padded(pixels: np.ndarray, pad: int) -> tuple[bytes, int]:
    rows = pixels.reshape(pixels.shape[0], -1).view(np.uint8)
    rows = np.concatenate([rows, np.full((rows.shape[0], pad), 0xEE, np.uint8)], axis=1)
    return rows.tobytes(), rows.shape[1]


@pytest.mark.parametrize("encoding,dtype,channels", [("rgb8", "u1", 3), ("bgra8", "u1", 4),
                                                     ("mono8", "u1", 1), ("mono16", ">u2", 1),
                                                     ("mono16", "<u2", 1)])
def test_an_image_with_padded_rows_of_either_byte_order_gives_its_pixels(encoding, dtype, channels):
    rng = np.random.default_rng(0)
    shape = (5, 7, channels) if channels > 1 else (5, 7)
    pixels = rng.integers(0, 65535 if "2" in dtype else 255, shape).astype(dtype)
    data, step = _padded(pixels, 6)
    out = image_array(data, height=5, width=7, step=step, encoding=encoding, is_bigendian=dtype == ">u2")
    assert out.shape == shape and np.array_equal(out, pixels)  # values, whatever the byte order
    assert out.dtype == (np.uint16 if "2" in dtype else np.uint8)


def test_an_image_shorter_than_its_header_or_of_another_encoding_is_refused():
    with pytest.raises(ValueError, match="needs 4 rows of at least 12 bytes"):
        image_array(b"\0" * 40, height=4, width=4, step=12, encoding="rgb8", is_bigendian=False)
    with pytest.raises(ValueError, match="32FC1"):
        image_array(b"\0" * 64, height=4, width=4, step=16, encoding="32FC1", is_bigendian=False)


def test_the_key_is_run_topic_stamp_and_message_number_so_a_replayed_bag_is_a_second_drive():
    stamp = Stamp.of(1_700_000_000, 5)
    key = idempotency_key("run1", "/robot/cam/image_raw", stamp, "0badf00d")
    assert key == "run1:.robot.cam.image_raw:1700000000000000005:0badf00d"
    assert key == idempotency_key("run1", "/robot/cam/image_raw", stamp, "0badf00d")  # a retry: the same
    assert key != idempotency_key("run2", "/robot/cam/image_raw", stamp, "0badf00d")  # a replay: another
    assert key != idempotency_key("run1", "/robot/cam2/image_raw", stamp, "0badf00d")
    long = idempotency_key("r", "/" + "x" * 200, stamp, "0badf00d")
    assert len(long) <= 128 and long.endswith(":1700000000000000005:0badf00d")
    import re

    assert re.fullmatch(r"[A-Za-z0-9._:-]{8,128}", long) and re.fullmatch(r"[A-Za-z0-9._:-]{8,128}", key)


def test_frames_with_one_stamp_get_keys_of_their_own_and_the_repeat_is_told():
    # a driver that does not stamp (0 every time), then two frames stamped alike: each its own post
    frames = [bytes([i]) * 64 for i in range(6)]
    stamps = (0, 0, 0, 5, 5, 6)
    keys = FrameKeys("run1", "/cam/image_raw")
    got = [keys.next(Stamp(ns), f) for ns, f in zip(stamps, frames, strict=True)]
    assert len({g.key for g in got}) == 6  # no key reused: the service would refuse it 422
    # a zero stamp or the previous frame's identifies no frame: its odometry pose would be another's
    assert [g.unstamped for g in got] == [True, True, True, False, True, False]
    assert not any(g.duplicate for g in got)
    # the same messages in a second start under the same run id: the same keys (a resumed drive)...
    again = FrameKeys("run1", "/cam/image_raw")
    assert [again.next(Stamp(ns), f).key for ns, f in zip(stamps, frames, strict=True)] == \
        [g.key for g in got]
    # ...also where the transport lost a message in one run and not the other (a count would shift)
    lossy = FrameKeys("run1", "/cam/image_raw")
    assert [lossy.next(Stamp(ns), f).key for ns, f in list(zip(stamps, frames, strict=True))[1:]] == \
        [g.key for g in got[1:]]
    # and a camera that does not stamp, restarted under its run id with other frames: no key reused
    other = FrameKeys("run1", "/cam/image_raw")
    assert not {other.next(Stamp(0), bytes([100 + i]) * 64).key for i in range(3)} & {g.key for g in got}


def test_a_message_delivered_twice_is_a_duplicate_and_a_looped_bag_one_new_drive_on_its_third_message():
    t0, period = 1_700_000_000 * 10**9, 100_000_000
    frames = [bytes([i]) * 64 for i in range(20)]
    keys = FrameKeys("run1", "/cam/image_raw")
    first = [keys.next(Stamp(t0 + i * period), f) for i, f in enumerate(frames)]
    assert {(g.duplicate, g.back_ns, g.drive) for g in first} == {(False, 0, 0)}
    # the same message again (a camera bridged twice), at once or a few frames later: the same frame
    assert keys.next(Stamp(t0 + 19 * period), frames[19]).duplicate
    assert keys.next(Stamp(t0 + 17 * period), frames[17]).duplicate  # 0.2 s back: out of order, no new drive
    assert keys.drive == 0
    # the recording played again (`ros2 bag play --loop`): its stamps go back 1.9 s. Its first two messages
    # are taken as the last drive's (repeats of its messages: not posted); the third, the third in a row
    # to go back, starts a new drive whose keys are its own, so its frames are posted again, not answered
    # from the store as the first pass's
    loop = [keys.next(Stamp(t0 + i * period), f) for i, f in enumerate(frames)]
    assert [(g.duplicate, g.drive) for g in loop[:3]] == [(True, 0), (True, 0), (False, 1)]
    assert loop[2].back_ns == 19 * period and not loop[2].unstamped
    assert {(g.duplicate, g.back_ns, g.drive) for g in loop[3:]} == {(False, 0, 1)}
    assert not {g.key for g in loop[2:]} & {g.key for g in first}
    digest = loop[2].key.rsplit(":", 1)[1]
    assert loop[2].key == idempotency_key("run1.1", "/cam/image_raw", Stamp(t0 + 2 * period), digest)
    # a third pass: exactly one more drive
    third = [keys.next(Stamp(t0 + i * period), f) for i, f in enumerate(frames)]
    assert [g.drive for g in third] == [1, 1] + [2] * 18 and sum(g.back_ns > 0 for g in third) == 1
    # a zero stamp (a driver's glitch) is no jump back
    assert keys.next(Stamp(0), b"z" * 64).drive == 2 and keys.drive == 2


def test_a_single_late_or_early_message_starts_no_new_drive():
    # Before, one message stamped more than 1 s before the newest started a new drive (the stream reset on
    # the service, the recent keys forgotten): a topic bridged twice whose copy lags 1.5 s made every copy a
    # new drive and a frame posted again, and two publishers with skewed clocks reset the stream each frame.
    S, period = 10**9, 10**9 // 30
    keys = FrameKeys("run1", "/cam/image_raw")
    got = []
    for i in range(90):  # bridged twice, the copy 1.5 s (45 frames) late
        got.append(keys.next(Stamp(10 * S + i * period), b"f%d" % i))
        if i >= 45:
            got.append(keys.next(Stamp(10 * S + (i - 45) * period), b"f%d" % (i - 45)))
    assert keys.drive == 0 and not any(g.back_ns for g in got)
    assert sum(not g.duplicate for g in got) == 90 and sum(g.duplicate for g in got) == 45  # each posted once
    # two publishers on one topic, the second's clock 1.2 s behind, interleaved: both posted, no new drive
    two = FrameKeys("run1", "/cam/image_raw")
    got = [two.next(Stamp(t), b"%s%d" % (who, i)) for i in range(30)
           for who, t in ((b"A", 100 * S + i * S // 10), (b"B", 100 * S - 1_200_000_000 + i * S // 10))]
    assert two.drive == 0 and not any(g.duplicate or g.back_ns for g in got)
    # one frame stamped 49 s in the future: the frames after it are not a jump back
    glitch = FrameKeys("run1", "/cam/image_raw")
    stamps = [50_000, 50_100, 50_200, 99_000, 50_300, 50_400, 50_500, 50_600]  # ms
    got = [glitch.next(Stamp(ms * 10**6), b"%d" % ms) for ms in stamps]
    assert glitch.drive == 0 and not any(g.back_ns for g in got)
    # going back, but not in stamp order among themselves (a late copy between two going back): no drive
    mixed = FrameKeys("run1", "/cam/image_raw")
    for i in range(30):
        mixed.next(Stamp(20 * S + i * period), b"m%d" % i)
    got = [mixed.next(Stamp(10 * S + i * period), b"n%d" % i) for i in (2, 1, 3)]
    assert mixed.drive == 0 and not any(g.back_ns for g in got)


def test_a_still_camera_that_does_not_stamp_is_never_a_duplicate():
    # Before, a frame stamped 0 with the bytes of one before (a covered lens, a still simulated camera) was a
    # "duplicate", not posted: nothing was published while the robot stood. Its key decides on the service.
    keys = FrameKeys("run1", "/cam/image_raw")
    got = [keys.next(Stamp(0), b"black" * 16) for _ in range(4)]
    assert not any(g.duplicate for g in got) and all(g.unstamped for g in got)
    assert len({g.key for g in got}) == 1  # one key: the service answers the repeats from its store
    # a stamped message delivered twice is still a duplicate
    assert [keys.next(Stamp(5), b"x" * 64).duplicate for _ in range(2)] == [False, True]


def test_a_skipped_image_says_which_fault_it_has():
    from cortexloc_ros.core import ImageError

    faults = {"step": dict(data=b"\0" * 4096, height=32, width=64, step=128),  # a row is 192 bytes
              "data": dict(data=b"\0" * 100, height=32, width=64, step=192),
              "size": dict(data=b"", height=0, width=0, step=0)}
    said = {}
    for fields in faults.values():
        with pytest.raises(ImageError) as e:
            image_array(encoding="rgb8", is_bigendian=False, **fields)
        said[e.value.reason] = str(e.value)
    assert set(said) == set(faults)
    assert "step 128 is shorter than a row of 192 bytes" in said["step"]
    assert "needs 32 rows of at least 192 bytes (step 192); the message holds 100 bytes" in said["data"]
    assert said["size"] == "rgb8 image 0x0 has no pixels"
    with pytest.raises(ImageError) as e:
        image_array(b"\0" * 64, height=4, width=4, step=16, encoding="yuv422", is_bigendian=False)
    assert e.value.reason == "encoding"


def test_odometry_that_jumps_back_starts_a_segment_and_each_frame_matches_the_one_of_its_stamp():
    import time

    t0, S = 1_700_000_000 * 10**9, 10**9
    buf = OdometryBuffer(tolerance_ns=50_000_000)
    for i in range(200):  # the first pass, 20 s
        buf.add(Stamp(t0 + i * 100_000_000), Pose2D(float(i), 0.0, 0.0, "odom"))
    buf.add(Stamp(t0 + 19_950_000_000), Pose2D(-1.0, 0.0, 0.0, "odom"))  # out of order: kept with the rest
    buf.add(Stamp(t0 + 18_050_000_000), Pose2D(10.0, 0.0, 0.0, "odom"))  # one sample 1.9 s late: no segment
    buf.add(Stamp(t0 + 20 * S), Pose2D(200.0, 0.0, 0.0, "odom"))  # (the run of candidates ends)
    assert buf.match(Stamp(t0 + 2 * S)) == Pose2D(20.0, 0.0, 0.0, "odom")  # before: all dropped
    assert buf.segment == 0 and buf.match(Stamp(t0 + 18_050_000_000)) == Pose2D(10.0, 0.0, 0.0, "odom")
    # a frame past the newest sample waits for the sample of its instant
    started = time.monotonic()
    assert buf.wait_match(Stamp(t0 + 20_500_000_000), time.monotonic() + 0.05) is None
    assert time.monotonic() - started >= 0.04
    # the camera's stamps go back first: until the new pass's odometry is in, its frame at t0 + 0.5 s
    # takes the last pass's pose at that stamp (the same for a bag played again)
    assert buf.match(Stamp(t0 + S // 2)) == Pose2D(5.0, 0.0, 0.0, "odom")
    # the new pass's odometry: a segment once three samples in a row went back
    for i in range(3):
        buf.add(Stamp(t0 + 400_000_000 + i * 100_000_000), Pose2D(100.0 + i, 0.0, 0.0, "odom"))
    assert buf.segment == 1 and buf.match(Stamp(t0 + S // 2)) == Pose2D(101.0, 0.0, 0.0, "odom")
    assert buf.latest() == Pose2D(102.0, 0.0, 0.0, "odom")
    # the last pass's frames still queued keep their poses: its segment is kept, and theirs by the stamp
    assert buf.match(Stamp(t0 + 19_900_000_000)) == Pose2D(199.0, 0.0, 0.0, "odom")
    # a review: three late samples make a segment the camera never jumped with; the live frames after it
    # still take their poses (counted drives went out of step and lost every pose for good)
    for i in range(3):
        buf.add(Stamp(t0 + 500_000_000 + i * 10_000_000), Pose2D(300.0, 0.0, 0.0, "odom"))
    for i in range(10):
        buf.add(Stamp(t0 + 700_000_000 + i * 100_000_000), Pose2D(400.0 + i, 0.0, 0.0, "odom"))
    assert buf.match(Stamp(t0 + 1_100_000_000)) == Pose2D(404.0, 0.0, 0.0, "odom")
    # a candidate stamp repeated is held once: the held samples stay bounded
    for _ in range(1000):
        buf.add(Stamp(t0 - 5 * S), Pose2D(0.0, 0.0, 0.0, "odom"))
    assert len(buf._held) <= JUMP_CONFIRM
    # the capacity holds for all segments: the oldest samples of the oldest go first
    small = OdometryBuffer(tolerance_ns=50_000_000, capacity=4)
    for i in range(3):
        small.add(Stamp(50 * S + i * S // 10), Pose2D(float(i), 0.0, 0.0, "odom"))
    for i in range(3):
        small.add(Stamp(S + i * S // 10), Pose2D(1.0, 0.0, 0.0, "odom"))
    assert small.segment == 1 and small.match(Stamp(50 * S)) is None
    assert small.match(Stamp(50 * S + S // 5)) == Pose2D(2.0, 0.0, 0.0, "odom")


def test_a_frame_takes_the_odometry_pose_nearest_its_stamp_within_the_tolerance():
    odom = OdometryBuffer(tolerance_ns=50_000_000)
    for i in (0, 2, 1, 3):  # out of order too
        odom.add(Stamp(i * 100_000_000), Pose2D(float(i), 0.0, 0.0, "odom"))
    assert odom.match(Stamp(140_000_000)).x == 1.0
    assert odom.match(Stamp(160_000_000)).x == 2.0
    assert odom.match(Stamp(250_000_000)).x == 2.0  # a tie: the earlier
    assert odom.match(Stamp(360_000_000)) is None  # 60 ms past the last: beyond the tolerance
    assert odom.latest().x == 3.0


def test_a_match_waits_for_odometry_at_or_after_the_stamp_until_its_deadline():
    import threading
    import time

    odom = OdometryBuffer(tolerance_ns=50_000_000)
    odom.add(Stamp(60_000_000), Pose2D(0.0, 0.0, 0.0, "odom"))  # 40 ms before the frame
    threading.Timer(0.05, odom.add, (Stamp(110_000_000), Pose2D(1.0, 0.0, 0.0, "odom"))).start()
    assert odom.wait_match(Stamp(100_000_000), time.monotonic() + 30).x == 1.0  # 10 ms after: the nearest
    t0 = time.monotonic()
    assert odom.wait_match(Stamp(100_000_000), t0 + 30).x == 1.0  # already in: no wait
    assert odom.wait_match(Stamp(140_000_000), t0 - 1).x == 1.0  # past its deadline: what is in
    assert time.monotonic() - t0 < 5  # neither waited for its deadline


def test_the_camera_mount_moves_the_pose_with_the_robots_heading():
    pose = Pose2D(1.0, 2.0, math.pi / 2, "odom").compose((0.5, 0.0, math.pi / 2))
    assert (round(pose.x, 9), round(pose.y, 9), round(pose.yaw, 9)) == (1.0, 2.5, round(math.pi, 9))


def test_a_pose_the_service_would_refuse_says_so():
    # the node ignores such odometry (an EKF before it converged, or diverged): the service refuses NaN,
    # infinities and coordinates beyond its bounds, and the frame with them
    assert Pose2D(1.0, -2.0, 3.0, "odom").is_postable()
    assert Pose2D(-POSE_MAX_ABS, POSE_MAX_ABS, -YAW_MAX_ABS, "odom").is_postable()  # the bounds are in
    for x, y, yaw in ((math.nan, 0.0, 0.0), (0.0, math.inf, 0.0), (0.0, 0.0, -math.inf),
                      (POSE_MAX_ABS * 1.01, 0.0, 0.0), (0.0, -1e12, 0.0), (0.0, 0.0, YAW_MAX_ABS * 2)):
        assert not Pose2D(x, y, yaw, "odom").is_postable()
    assert not Pose2D(0.0, 0.0, yaw_from_quaternion(math.nan, 0.0, 0.0, 1.0), "odom").is_postable()


def test_a_kind_of_log_line_is_said_at_once_then_once_a_minute_with_a_count():
    now = [100.0]
    said = LogLimiter(clock=lambda: now[0])
    lines = []
    for t, kind in ((100.0, "a"), (101.0, "a"), (102.0, "b"), (130.0, "a"), (160.0, "a"), (161.0, "a"),
                    (300.0, "a")):
        now[0] = t
        lines.append(said.line(kind, f"{kind} at {t:g}"))
    more = " more like it since the last line)"
    assert lines == ["a at 100", None, "b at 102", None, f"a at 160 (2{more}", None, f"a at 300 (1{more}"]


def test_the_rate_filter_takes_every_nth_frame_and_only_after_the_minimum_distance():
    every = RateFilter(every_n=3)
    assert [every.take(None) for _ in range(7)] == [False, False, True, False, False, True, False]
    far = RateFilter(min_distance=1.0)
    poses = [Pose2D(x, 0.0, 0.0, "odom") for x in (0.0, 0.4, 0.9, 1.1, 1.5, 2.2)]
    assert [far.take(p) for p in poses] == [True, False, False, True, False, True]
    assert far.take(None) is False  # no pose: cannot tell how far


@pytest.mark.parametrize("policy,kept", [("drop_oldest", [3, 4]), ("drop_newest", [0, 1])])
def test_a_full_queue_drops_by_its_policy(policy, kept):
    q: FrameQueue[int] = FrameQueue(2, policy)
    dropped = [q.put(i) for i in range(5)]
    assert q.dropped == 3 and len(q) == 2
    assert dropped == ([None, None, 0, 1, 2] if policy == "drop_oldest" else [None, None, 2, 3, 4])
    assert [q.get(0), q.get(0), q.get(0)] == [*kept, None]


def test_the_parameters_yaml_declares_every_parameter_with_its_default():
    yaml = pytest.importorskip("yaml")
    path = Path(__file__).resolve().parents[3] / "clients" / "ros2" / "config" / "params.yaml"
    doc = yaml.safe_load(path.read_text())["/**"]["ros__parameters"]

    def flat(d: dict, prefix: str = "") -> dict:
        out = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
        return out

    assert flat(doc) == DEFAULTS
    assert all(description for _, description in PARAMETERS.values())


def test_bad_parameters_are_all_named_at_once(monkeypatch, tmp_path):
    bad = {**DEFAULTS, "service_url": "127.0.0.1:8000", "queue.size": 0, "queue.policy": "lifo",
           "odom_tolerance": 0.0, "camera_mount": [1.0, 2.0], "image_transport": "theora", "trail": "a b"}
    with pytest.raises(ConfigError) as e:
        read_config(bad)
    assert [p.split(":")[0] for p in e.value.problems] == [
        "service_url", "trail", "image_transport", "odom_tolerance", "camera_mount", "queue.size",
        "queue.policy"]
    with pytest.raises(ConfigError, match="api_key: the API key is never a parameter"):
        read_config(DEFAULTS, unknown=["api_key"])
    monkeypatch.setenv("ROBOT_KEY", "from-env")
    assert read_config({**DEFAULTS, "api_key_env": "ROBOT_KEY"}).api_key == "from-env"
    (tmp_path / "key").write_text("from-file\n")
    assert read_config({**DEFAULTS, "api_key_file": str(tmp_path / "key")}).api_key == "from-file"
    cfg = read_config({**DEFAULTS, "odom_tolerance": 1, "camera_mount": [0, 0, 1]})  # integers as numbers
    assert cfg.odom_tolerance_ns == 1_000_000_000 and cfg.camera_mount == (0.0, 0.0, 1.0)


def test_every_float_parameter_must_be_finite_and_in_range_and_the_url_port_too():
    # a NaN passes every comparison: a NaN mount had every frame refused 422, a NaN or inf covariance
    # was published; an inf timeout or tolerance cannot be used either
    nan, inf = math.nan, math.inf
    with pytest.raises(ConfigError) as e:
        read_config({**DEFAULTS, "service_url": "http://127.0.0.1:99999", "request_timeout": inf,
                     "odom_tolerance": nan, "rate.min_distance": -inf, "camera_mount": [nan, 0.0, 0.0],
                     "place_covariance": [1.0, inf, 0.1]})
    assert e.value.problems == [
        "service_url: 'http://127.0.0.1:99999' has no port 1-65535",
        "request_timeout: inf must be a finite number > 0 seconds",
        "odom_tolerance: nan must be a finite number > 0 seconds",
        "rate.min_distance: -inf must be a finite number >= 0 metres",
        "camera_mount: [nan, 0.0, 0.0] must be 3 finite numbers (x, y, yaw)",
        "place_covariance: [1.0, inf, 0.1] must be 3 finite numbers (variances of x, y, yaw)"]
    for value in ([nan, 1.0, 0.1], [-1.0, 1.0, 0.1]):
        with pytest.raises(ConfigError, match="place_covariance"):
            read_config({**DEFAULTS, "place_covariance": value})
    with pytest.raises(ConfigError, match="service_url: 'http://h:0' has no port"):
        read_config({**DEFAULTS, "service_url": "http://h:0"})
    assert read_config({**DEFAULTS, "service_url": "https://h:65535/"}).service_url == "https://h:65535"


def test_an_empty_override_is_named_before_rcl_fails_to_parse_it():
    # `-p map:=` made rclpy.init raise RCLError (a traceback, exit 1); the node says which, and exits 2
    assert empty_overrides(["prog", "--ros-args", "-p", "map:=", "--param", "service_url:=",
                            "-p", "learn:=false", "-p", "stream:=''"]) == [
        "map: -p map:= gives no value (an empty string is -p \"map:=''\")",
        "service_url: -p service_url:= gives no value (an empty string is -p \"service_url:=''\")"]
    assert empty_overrides(["prog", "-p", "map:="]) == []  # not a ROS argument: not ROS's to parse
    run = read_config(DEFAULTS)
    assert not run.resume and run.run_id  # a new drive per start; a given run_id resumes one
    assert read_config({**DEFAULTS, "run_id": "drive-a"}).resume


def test_a_name_with_a_last_newline_is_refused_at_start_not_on_every_frame():
    # `$` in a Python pattern also matches before a last newline; the service's patterns do not
    with pytest.raises(ConfigError) as e:
        read_config({**DEFAULTS, "map": "robot-map\n", "stream": "front\n", "run_id": "run1\n"})
    assert [p.split(":")[0] for p in e.value.problems] == ["map", "run_id", "stream"]
    assert trail_of("", "/robot1\n") is None


def test_a_stream_the_service_refuses_on_every_frame_is_refused_at_start_and_a_large_top_k_told():
    with pytest.raises(ConfigError) as e:
        read_config({**DEFAULTS, "top_k": -1, "stream": "front cam", "trail": "robot//1"})
    assert e.value.problems == [
        "top_k: -1 must be 0 or more",
        "stream: 'front cam' is not a stream name (up to 8 '/'-separated parts of 1 to 64 letters, digits, "
        "'.', '_' or '-')",
        "trail: 'robot//1' is not a stream name (up to 8 '/'-separated parts of 1 to 64 letters, digits, "
        "'.', '_' or '-')"]
    cfg = read_config({**DEFAULTS, "top_k": 100, "stream": "robot1/front.cam"})
    assert (cfg.top_k, cfg.stream) == (100, "robot1/front.cam") and config_warnings(cfg) == []
    # over the service's default limit: a service may raise it (CORTEXLOC_MAX_TOP_K), so said, not refused
    big = read_config({**DEFAULTS, "top_k": 101})
    assert big.top_k == 101 and config_warnings(big) == [
        "top_k: 101 is over 100, the service's default CORTEXLOC_MAX_TOP_K: a service that keeps that limit "
        "refuses every frame (400; diagnostics: refused)"]


def _answer(place: dict | None) -> Observation:
    return Observation.model_validate({
        "map_id": "m", "stream": "s", "learned": True, "seq": 9, "sequence": {
            "step": 1, "active_columns": 1, "predicted_columns": 0, "bursting_columns": 1, "winner_cells": 1},
        "matches": [], "timings_ms": {},
        "versions": {"api": "v1", "code": "x", "encoder": "e", "weights": "w", "projection": "p",
                     "map_seq": 9},
        "place": place})


def test_a_verified_loop_closure_carries_the_relative_pose_of_the_services_g2o_export():
    """The document's relative pose is in the keyframe camera's optical axes (its `frame` says so); the g2o
    export's edge is the same pose in body axes (x ahead, y left, z up: `BODY_FROM_OPTICAL`)."""
    from types import SimpleNamespace

    from service.maps.closures import BODY_FROM_OPTICAL, g2o_lines

    a = 0.3
    R = [[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]]
    t = [0.6, 0.0, 0.8]
    place = {"seq": 4, "confidence": 0.95, "revisit": True, "support": 12, "place_id": 4, "span": 2,
             "span_seqs": [4, 5],
             "metadata": {"stamp": 12.5, "stamp_ns": "12500000000", "pose": {"x": 1.0, "y": 2.0, "yaw": 0.1,
                                                                             "frame_id": "odom"}},
             "verification": {"verified": True, "keyframe_seq": 4, "inliers": 80, "model": "fundamental",
                              "rotation": R, "translation": t, "rotation_deg": math.degrees(a)}}
    doc = loop_closure_json(_answer(place), Stamp.of(20, 1), "cam", Pose2D(1.5, 2.0, 0.0, "odom"), "map")
    assert doc["stamp"] == {"sec": 20, "nanosec": 1}
    assert doc["place_stamp"] == {"sec": 12, "nanosec": 500000000}
    assert doc["place_pose"] == {"x": 1.0, "y": 2.0, "yaw": 0.1, "frame_id": "odom"}
    assert doc["pose"]["x"] == 1.5 and doc["confidence"] == 0.95 and doc["verified"] is True
    assert doc["span"] == 2 and doc["span_seqs"] == [4, 5]
    edge = g2o_lines(SimpleNamespace(verification=place["verification"], seq=9, place_seq=4, id=1,
                                     consolidated_into=None, metadata=None, place_metadata=None,
                                     span=doc["span"]))
    want = [float(v) for v in edge.splitlines()[-1].split()[3:10]]  # x y z qx qy qz qw
    rel = doc["relative_pose"]
    assert rel["frame"] == "keyframe_camera_optical"
    B = BODY_FROM_OPTICAL
    position = B @ [rel["position"][k] for k in "xyz"]
    qx, qy, qz, qw = (rel["orientation"][k] for k in "xyzw")
    orientation = np.array([[1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
                            [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
                            [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)]])
    got = [*position, *quaternion_from_matrix(B @ orientation @ B.T)]
    assert np.allclose(got, want, atol=1e-8)
    assert loop_closure_json(_answer({**place, "revisit": False}), Stamp(1), "cam", None, "map") is None
    assert place_json(_answer(None), Stamp(1), "cam", None, 3.0, "map")["place"] is None
    # the place document says why a confident answer is no revisit, as the service's reply does
    said = place_json(_answer({**place, "revisit": False, "lagging": True}), Stamp(1), "cam", None, 3.0,
                      "map")["place"]
    assert said["lagging"] is True and said["span"] == 2 and said["span_seqs"] == [4, 5]


def test_a_closures_marker_is_red_at_the_maps_revisit_threshold_and_green_at_1():
    # The markers' docstring said red at the threshold, green at 1, but the colour was (1 - c, c): every
    # closure (confidence >= 0.91 on the default threshold) drew about 91 % green, alike. The node scales by
    # the threshold the poster read from the map at first contact, clamped to [0, 1].
    from collections import deque
    from types import SimpleNamespace

    node = pytest.importorskip("cortexloc_ros.node", reason="rclpy is not installed (make install-ros)")
    from cortexloc_ros.answers import DEFAULT_REVISIT_THRESHOLD as NODES_DEFAULT

    from service.maps.config import DEFAULT_REVISIT_THRESHOLD

    assert NODES_DEFAULT == DEFAULT_REVISIT_THRESHOLD  # the scale where the map's own is unknown

    def colours(threshold: float | None, *confidences: float) -> list[tuple[float, float]]:
        edges = deque((i, Pose2D(i, 0, 0, "odom"), Pose2D(i, 5, 0, "odom"), c)
                      for i, c in enumerate(confidences))
        fake = SimpleNamespace(_edges=edges, poster=SimpleNamespace(revisit_threshold=threshold))
        (line,) = node.CortexlocNode._markers(fake).markers
        assert line.colors[0::2] == line.colors[1::2]  # both ends of an edge alike
        return [(round(c.r, 6), round(c.g, 6)) for c in line.colors[0::2]]

    # the map's threshold 0.91: a closure at it is red, one at 1 green, halfway between half and half
    assert colours(0.91, 0.91, 0.955, 1.0) == [(1.0, 0.0), (0.5, 0.5), (0.0, 1.0)]
    # another map's threshold scales alike; a closure below it (the threshold lowered since) is red
    assert colours(0.5, 0.5, 0.75, 0.4) == [(1.0, 0.0), (0.5, 0.5), (1.0, 0.0)]
    # an older server's map names none: the service's default; at 1 nothing but a confidence of 1 is green
    assert colours(None, 0.91, 1.0) == [(1.0, 0.0), (0.0, 1.0)]
    assert colours(1.0, 1.0) == [(0.0, 1.0)] and colours(0.0, 0.25) == [(0.75, 0.25)]
    assert colours(0.91, math.nan) == [(1.0, 0.0)]  # never outside [0, 1]


def test_a_robots_nodes_name_one_trail_its_namespace_unless_the_parameter_names_another():
    # two cameras under /robot1 share the robot's short-term memory (service metadata.trail)
    assert trail_of("", "/robot1") == trail_of("", "/robot1/") == "robot1"
    assert trail_of("", "/fleet/robot1") == "fleet/robot1"
    assert trail_of("rover", "/robot1") == "rover"  # the parameter wins
    assert trail_of("", "/") is None and trail_of("", "") is None  # the root: each stream its own trail
