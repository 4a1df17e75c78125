"""The node's parts that need no ROS: frames from `sensor_msgs/Image` fields, stamps, planar poses, the
odometry buffer that matches a frame's stamp, the rate filter, the bounded queue and the idempotency key.

Kept apart from `cortexloc_ros.node` so that they are tested without rclpy, and so that the node reads as
what it does with messages. Frames are posted through the typed client (`cortexloc_client`), whose raw
frames are the service's (docs/design/service.md §1.2: rows unpadded, mono16 little-endian).
"""

from __future__ import annotations

import bisect
import math
import re
import threading
import time
import zlib
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Generic, Literal, NamedTuple, TypeVar

import numpy as np

from cortexloc_client import POSE_MAX_ABS, YAW_MAX_ABS

__all__ = ["ENCODINGS", "JUMP_CONFIRM", "LOG_PERIOD_S", "STAMP_JUMP_NS", "DropPolicy", "FrameKey",
           "FrameKeys", "FrameQueue", "ImageError", "LogLimiter", "OdometryBuffer", "Pose2D", "RateFilter",
           "RecentSet", "Stamp", "StampJumps", "idempotency_key", "image_array", "quaternion_from_matrix",
           "relative_pose", "yaw_from_quaternion"]

#: `sensor_msgs/Image` encodings the service takes as raw frames -> (sample dtype, channels). rgba8 and
#: bgra8 are sent without their alpha channel (the client drops it); mono16 is sent little-endian.
ENCODINGS: dict[str, tuple[str, int]] = {
    "rgb8": ("u1", 3), "bgr8": ("u1", 3), "rgba8": ("u1", 4), "bgra8": ("u1", 4),
    "mono8": ("u1", 1), "mono16": ("u2", 1),
}


class ImageError(ValueError):
    """A `sensor_msgs/Image` the node cannot post; `reason` names the fault's kind (the node logs each kind
    of each encoding once a while, and counts them): `encoding` (one the service does not take), else the
    message is malformed: `size` (no pixels: a zero width or height), `step` (shorter than a row), `data`
    (fewer bytes than `step` x `height`)."""

    def __init__(self, reason: str, text: str) -> None:
        super().__init__(text)
        self.reason = reason


def image_array(data: Any, *, height: int, width: int, step: int, encoding: str,
                is_bigendian: bool) -> np.ndarray:
    """A `sensor_msgs/Image` payload as the array `Client.observe` posts as a raw frame.

    Args:
        data: the message's `data` (bytes, `array.array('B')` or a uint8 array): `height` rows of `step`
            bytes, each row possibly padded past `width` pixels.
        encoding: one of `ENCODINGS`.
        is_bigendian: the byte order of 16-bit samples.

    Returns:
        (height, width, channels) uint8 for colour, (height, width) uint8 or uint16 (native order) for mono;
        a view of `data` where no copy is needed (the client copies it contiguously when it sends).

    Raises:
        ImageError: an encoding the service does not take, or a header its data does not fill (`reason`).
    """
    if encoding not in ENCODINGS:
        raise ImageError("encoding", f"image encoding {encoding!r} is not one the service takes "
                                     f"({', '.join(ENCODINGS)})")
    sample, channels = ENCODINGS[encoding]
    itemsize = np.dtype(sample).itemsize
    row = width * channels * itemsize
    buf = np.frombuffer(data, np.uint8)
    if height < 1 or width < 1:
        raise ImageError("size", f"{encoding} image {width}x{height} has no pixels")
    if step < row:
        raise ImageError("step", f"{encoding} image {width}x{height}: step {step} is shorter than a row of "
                                 f"{row} bytes")
    if buf.size < step * height:
        raise ImageError("data", f"{encoding} image {width}x{height} needs {height} rows of at least {row} "
                                 f"bytes (step {step}); the message holds {buf.size} bytes")
    rows = buf[: step * height].reshape(height, step)[:, :row]  # drops each row's padding
    if itemsize == 2:
        pixels = np.ascontiguousarray(rows).view(">u2" if is_bigendian else "<u2").astype(np.uint16)
        return pixels.reshape(height, width)
    return rows.reshape(height, width, channels) if channels > 1 else rows.reshape(height, width)


# ------------------------------------------------------------------------------------------ stamps


@dataclass(frozen=True, order=True)
class Stamp:
    """A ROS time (`builtin_interfaces/Time`) as integer nanoseconds: exact, ordered, hashable."""

    ns: int

    @classmethod
    def of(cls, sec: int, nanosec: int) -> Stamp:
        return cls(int(sec) * 1_000_000_000 + int(nanosec))

    @classmethod
    def parse(cls, value: Any) -> Stamp | None:
        """A stamp read back from metadata: integer nanoseconds as text (`stamp_ns`, exact) or seconds."""
        if isinstance(value, str) and value.isdigit():
            return cls(int(value))
        if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
            return cls(round(value * 1e9))
        return None

    @property
    def sec(self) -> int:
        return self.ns // 1_000_000_000

    @property
    def nanosec(self) -> int:
        return self.ns % 1_000_000_000

    @property
    def seconds(self) -> float:
        return self.ns / 1e9

    def as_json(self) -> dict[str, int]:
        return {"sec": self.sec, "nanosec": self.nanosec}


#: An Idempotency-Key is `[A-Za-z0-9._:-]{8,128}` (docs/design/service.md §1.2).
_KEY_UNSAFE = re.compile(r"[^A-Za-z0-9._-]")
_KEY_MAX = 128


def idempotency_key(run_id: str, topic: str, stamp: Stamp, content: str) -> str:
    """The post's key: (run, topic, stamp, a digest of the message's image data), so a retry (which
    reuses the frame's key) and a drive resumed under its run id (the same messages again) are
    deduplicated by the service, a bag replayed under another run id is a second drive, and two messages
    with one stamp (a driver that does not stamp, or stamps twice) are two frames, not one key reused
    (which the service refuses with 422). Not a count of the messages received: one the transport lost
    in one run and not in the other would shift every key after it.

    ROS names hold letters, digits, `_`, `/` and `~`; `/` becomes `.` (which no ROS name holds), anything
    else `-`. A key that would pass 128 characters keeps its stamp and digest and a hash of the rest.
    """
    key = f"{run_id}:{_KEY_UNSAFE.sub('-', topic.replace('/', '.'))}:{stamp.ns}:{content}"
    if len(key) <= _KEY_MAX:
        return key
    import hashlib

    return f"h:{hashlib.sha256(f'{run_id}:{topic}'.encode()).hexdigest()[:40]}:{stamp.ns}:{content}"


def content_digest(data: Any) -> str:
    """8 hex digits of CRC-32 over a message's image bytes (any buffer): tells apart two frames with one
    stamp (a collision needs two frames with the same stamp too); about 3 ms for a 1080p RGB frame."""
    return f"{zlib.crc32(data) & 0xFFFFFFFF:08x}"


class RecentSet:
    """The last `capacity` items added, in a set: bounded memory of what was seen (keys, closure ids)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._items: dict[Any, None] = {}  # insertion-ordered: the oldest first

    def add(self, item: Any) -> bool:
        """Remember `item`; False when it was remembered already."""
        if item in self._items:
            return False
        self._items[item] = None
        if len(self._items) > self.capacity:
            del self._items[next(iter(self._items))]
        return True

    def __contains__(self, item: Any) -> bool:
        return item in self._items

    def __len__(self) -> int:
        return len(self._items)

    def clear(self) -> None:
        self._items.clear()


#: A stamp this far before the newest one seen on a topic may start a new drive (a bag played again,
#: `ros2 bag play --loop`, or a simulation reset); a smaller step back is a message delivered out of order.
STAMP_JUMP_NS = 1_000_000_000
#: Messages in a row that must go back past `STAMP_JUMP_NS` to start a new drive (`StampJumps`): a single
#: late message (a copy from a topic bridged twice, a second publisher whose clock is behind) never does.
JUMP_CONFIRM = 3
#: Messages of a drive remembered per topic to tell a message delivered twice (a camera bridged twice, a
#: re-send): one of the last `RECENT_KEYS` stamped messages of the drive.
RECENT_KEYS = 1000


class StampJumps:
    """The newest stamp of a topic's drive, and when its stamps jumped back to start a new one.

    A message stamped more than `STAMP_JUMP_NS` before the newest stamp is a candidate; a new drive starts
    only at the `JUMP_CONFIRM`-th candidate in a row, the candidates in stamp order among themselves
    (`see` returns how far they went back). A message that does not go back ends the run; so does a
    candidate older than the one before it (it starts a run of its own). A jump forward past
    `STAMP_JUMP_NS` (a frame stamped in the future) moves the newest stamp only when confirmed the same
    way, so a single such frame does not make the frames after it look like a jump back. Zero stamps are
    not given to it."""

    def __init__(self) -> None:
        self.newest = 0  # ns; 0: none yet
        self._run: list[tuple[int, Any]] = []  # the candidates of a jump back: (stamp, identity)
        self._ahead: list[int] = []  # the candidates of a jump forward

    def is_back(self, ns: int) -> bool:
        return bool(self.newest) and self.newest - ns > STAMP_JUMP_NS

    def pending(self) -> list[Any]:
        """The identities of the candidates of a jump back so far (not yet a new drive)."""
        return [ident for _, ident in self._run]

    def see(self, ns: int, ident: Any = None) -> int:
        """A message stamped `ns` (non-zero): > 0, how far the stamps went back, when it confirms a new
        drive (the newest stamp is then its); else 0. A candidate whose `ident` is one of the run's (the
        same message again) changes nothing."""
        if self.is_back(ns):
            self._ahead.clear()
            if ident is not None and any(ident == i for _, i in self._run):
                return 0
            if self._run and ns < self._run[-1][0]:
                self._run.clear()
            self._run.append((ns, ident))
            if len(self._run) < JUMP_CONFIRM:
                return 0
            back = self.newest - self._run[0][0]
            self.newest = ns
            self._run.clear()
            return back
        self._run.clear()
        if self.newest and ns - self.newest > STAMP_JUMP_NS:
            if self._ahead and ns < self._ahead[-1]:
                self._ahead.clear()
            self._ahead.append(ns)
            if len(self._ahead) >= JUMP_CONFIRM:
                self.newest = ns
                self._ahead.clear()
            return 0
        self._ahead.clear()
        self.newest = max(self.newest, ns)
        return 0


class FrameKey(NamedTuple):
    """What `FrameKeys.next` says of a message.

    Attributes:
        key: the post's Idempotency-Key.
        unstamped: its stamp does not identify the frame (zero, or the previous message's): an odometry
            pose matched by it would be another frame's, so the frame is posted without one.
        duplicate: the same stamp (not zero) and bytes as one of the last `RECENT_KEYS` messages of this
            drive: the same frame delivered again, not posted again.
        back_ns: > 0 for the first message of a new drive (the `JUMP_CONFIRM`-th in a row that went back):
            how far the stamps went back.
        drive: the drives the stamps' jumps back started since the node started (0: the first).
    """

    key: str
    unstamped: bool
    duplicate: bool
    back_ns: int
    drive: int


@dataclass
class FrameKeys:
    """The keys of one topic's messages in one run. Stamps that go back more than `STAMP_JUMP_NS`, confirmed
    by `JUMP_CONFIRM` messages in a row (`StampJumps`), start a new drive (`FrameKey.drive`), whose keys
    hold its number (`run_id.N`), so a recording played again is posted again, not answered from the
    service's store as the first pass. Until confirmed, a message is the current drive's, the duplicate
    check first: a late copy of a message seen is a duplicate, not a new drive. A frame stamped 0 is never
    a duplicate (a still camera that does not stamp sends the same bytes): its key decides, on the
    service. Used by the executor's callback only."""

    run_id: str
    topic: str
    drive: int = 0
    _last: Stamp | None = None
    _jumps: StampJumps = field(default_factory=StampJumps)
    _recent: RecentSet = field(default_factory=lambda: RecentSet(RECENT_KEYS))  # (stamp ns, digest)

    def _key(self, stamp: Stamp, digest: str) -> str:
        run = self.run_id if self.drive == 0 else f"{self.run_id}.{self.drive}"  # run ids hold no '.'
        return idempotency_key(run, self.topic, stamp, digest)

    def next(self, stamp: Stamp, data: Any) -> FrameKey:
        """What the message just received is (`FrameKey`); `data` its image bytes (any buffer)."""
        digest = content_digest(data)
        unstamped = stamp.ns == 0 or stamp == self._last
        self._last = stamp
        if stamp.ns == 0:
            return FrameKey(self._key(stamp, digest), True, False, 0, self.drive)
        item = (stamp.ns, digest)
        seen = item in self._recent
        # a message seen before that does not go back is a copy: it neither confirms nor ends a jump back
        back = 0 if seen and not self._jumps.is_back(stamp.ns) else self._jumps.see(stamp.ns, item)
        if back:
            self.drive += 1
            self._recent.clear()
            seen = False
        if not seen:
            self._recent.add(item)
        return FrameKey(self._key(stamp, digest), unstamped, seen, back, self.drive)


# ------------------------------------------------------------------------------------------- poses


@dataclass(frozen=True)
class Pose2D:
    """A planar pose (metres, radians) in a named frame: what the service stores (`metadata.pose`)."""

    x: float
    y: float
    yaw: float
    frame_id: str

    def compose(self, mount: tuple[float, float, float]) -> Pose2D:
        """This base pose followed by the camera's planar mounting (x, y, yaw on the base)."""
        mx, my, myaw = mount
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return Pose2D(self.x + c * mx - s * my, self.y + s * mx + c * my,
                      math.atan2(math.sin(self.yaw + myaw), math.cos(self.yaw + myaw)), self.frame_id)

    def distance(self, other: Pose2D) -> float:
        return math.hypot(self.x - other.x, self.y - other.y)

    def is_postable(self) -> bool:
        """x, y and yaw are finite and within the service's bounds (`POSE_MAX_ABS`, `YAW_MAX_ABS`): it refuses
        any other pose, NaN and infinities included (422 `invalid-metadata`), and the frame with it."""
        return (abs(self.x) <= POSE_MAX_ABS and abs(self.y) <= POSE_MAX_ABS  # False for NaN
                and abs(self.yaw) <= YAW_MAX_ABS)

    def as_metadata(self) -> dict[str, Any]:
        return {"x": self.x, "y": self.y, "yaw": self.yaw, "frame_id": self.frame_id}

    @classmethod
    def from_metadata(cls, pose: Any, default_frame: str) -> Pose2D | None:
        """A stored pose (the client's `Pose` or a dict) back; None where there is none."""
        if pose is None:
            return None
        get = pose.get if isinstance(pose, dict) else lambda k: getattr(pose, k, None)
        x, y = get("x"), get("y")
        if x is None or y is None:
            return None
        return cls(float(x), float(y), float(get("yaw") or 0.0), get("frame_id") or default_frame)


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """The heading (rotation about z) of a quaternion, in (-pi, pi]."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quaternion_from_matrix(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w), w >= 0, of a 3 x 3 rotation matrix (Shepperd's method: stable for every angle)."""
    R = np.asarray(R, np.float64)
    tr = float(np.trace(R))
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = ((R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s)
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 0.0))
        v = [0.0, 0.0, 0.0]
        v[i] = 0.25 * s
        v[j] = (R[j, i] + R[i, j]) / s
        v[k] = (R[k, i] + R[i, k]) / s
        q = (v[0], v[1], v[2], (R[k, j] - R[j, k]) / s)
    n = math.sqrt(sum(c * c for c in q))
    sign = -1.0 if q[3] < 0 else 1.0
    return tuple(sign * c / n for c in q)  # type: ignore[return-value]


def relative_pose(rotation: list[list[float]], translation: list[float] | None
                  ) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """The query camera's pose in the keyframe camera's frame (optical axes: x right, y down, z ahead),
    from the service's verification X_query = R X_keyframe + t: position -R^T t (a unit direction, or zero
    where unobservable: two views give no scale) and orientation R^T as (x, y, z, w). The convention of
    the service's CSV and JSON lines exports; its g2o export writes the same pose in body axes (x ahead,
    y left, z up: B p and B R^T B^T with B = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]), the axes of the
    posted poses (docs/design/service.md §1.2)."""
    R = np.asarray(rotation, np.float64)
    t = np.asarray(translation if translation is not None else (0.0, 0.0, 0.0), np.float64)
    p = -R.T @ t
    return (float(p[0]), float(p[1]), float(p[2])), quaternion_from_matrix(R.T)


#: How far past an odometry segment's newest sample a frame's stamp may be for the frame to be matched in
#: it (`OdometryBuffer`), waiting for the sample of its instant: more than odometry's period and a
#: frame's wait.
SEGMENT_REACH_NS = 5_000_000_000


class OdometryBuffer:
    """Recent odometry poses by stamp; a frame takes the pose nearest its stamp within `tolerance_ns`
    (message_filters' ApproximateTime for two topics, which pip-installed ROS 2 lacks). Thread-safe: the
    executor adds, the poster matches (`wait_match`: once a pose at or after the frame's stamp is in,
    since the nearest may be the one after it).

    Odometry arriving out of order is inserted in order. Stamps that go back more than `STAMP_JUMP_NS`,
    confirmed as the camera's are (`StampJumps`: `JUMP_CONFIRM` samples in a row), start a new segment
    (a bag played again, a simulation reset; the candidates are held until then, and go to the new
    segment, or, when the run ends unconfirmed, to the current one). A frame matches the samples of one
    segment only, chosen by its stamp (`_segment_of`): the newest segment whose samples span it (from its
    first sample, less the tolerance, to `SEGMENT_REACH_NS` past its newest). So once a new pass's
    odometry is in, its frames take their poses from it while the last pass's frames still queued keep
    theirs, and a camera and an odometry that disagree on whether a jump happened (a clock that jumped
    forward, a few late messages) never lose the live segment (a review: drives and segments counted
    apart went out of step, and every later frame lost its pose). A frame of a new pass that comes before
    its pass's odometry has gone back takes the last pass's pose at its stamp: the same for a bag played
    again, another for a simulation reset (the README says so). The oldest samples (of the oldest segment
    first) go past `capacity` in all.
    """

    def __init__(self, tolerance_ns: int, capacity: int = 4096) -> None:
        self.tolerance_ns = tolerance_ns
        self.segment = 0  # the current segment: the one new samples go to
        self._segments: dict[int, tuple[list[int], list[Pose2D]]] = {0: ([], [])}
        self._held: list[tuple[int, Pose2D]] = []  # candidates of a jump back
        self._jumps = StampJumps()
        self._size = 0
        self._capacity = capacity
        self._lock = threading.Lock()
        self._added = threading.Condition(self._lock)

    def _insert(self, segment: int, ns: int, pose: Pose2D) -> None:
        stamps, poses = self._segments.setdefault(segment, ([], []))
        i = bisect.bisect_right(stamps, ns)
        stamps.insert(i, ns)
        poses.insert(i, pose)
        self._size += 1

    def add(self, stamp: Stamp, pose: Pose2D) -> None:
        with self._lock:
            back = self._jumps.see(stamp.ns, stamp.ns) if stamp.ns else 0
            if back:
                self.segment += 1
                for ns, p in (*self._held, (stamp.ns, pose)):
                    self._insert(self.segment, ns, p)
                self._held.clear()
            else:
                pending = self._jumps.pending()
                for ns, p in [h for h in self._held if h[0] not in pending]:  # a run ended: out of order
                    self._insert(self.segment, ns, p)
                self._held = [h for h in self._held if h[0] in pending and h[0] != stamp.ns]
                if stamp.ns and stamp.ns in pending:  # a candidate: the segment it goes to is not known yet
                    self._held.append((stamp.ns, pose))  # (one a stamp: at most JUMP_CONFIRM held)
                else:
                    self._insert(self.segment, stamp.ns, pose)
            while self._size > self._capacity:
                oldest = min(self._segments)
                stamps, poses = self._segments[oldest]
                del stamps[0], poses[0]
                self._size -= 1
                if not stamps and oldest != self.segment:
                    del self._segments[oldest]
            self._added.notify_all()

    def _segment_of(self, ns: int) -> int | None:
        """Under the lock: the newest segment whose samples span stamp `ns` (class docstring); None: none
        does (the frame's odometry is not in)."""
        for segment in sorted(self._segments, reverse=True):
            stamps = self._segments[segment][0]
            if stamps and stamps[0] - self.tolerance_ns <= ns <= stamps[-1] + SEGMENT_REACH_NS:
                return segment
        return None

    def wait_match(self, stamp: Stamp, deadline: float) -> Pose2D | None:
        """`match(stamp)` once a pose at or after `stamp` is in its segment, or at `deadline`
        (`time.monotonic()`) with what is in by then: a frame arriving before the odometry of its instant
        would otherwise take an older pose, or none. Waits on the poster's thread; the executor's `add`
        wakes it."""
        with self._lock:
            while True:
                segment = self._segment_of(stamp.ns)
                if segment is not None and self._segments[segment][0][-1] >= stamp.ns:
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._added.wait(left)
        return self.match(stamp)

    def match(self, stamp: Stamp) -> Pose2D | None:
        """The pose of the frame's segment (`_segment_of`) whose stamp is nearest `stamp`, if within the
        tolerance."""
        with self._lock:
            segment = self._segment_of(stamp.ns)
            if segment is None:
                return None
            stamps, poses = self._segments[segment]
            i = bisect.bisect_left(stamps, stamp.ns)
            best: tuple[int, Pose2D] | None = None
            for j in (i - 1, i):
                if 0 <= j < len(stamps):
                    gap = abs(stamps[j] - stamp.ns)
                    if gap <= self.tolerance_ns and (best is None or gap < best[0]):
                        best = (gap, poses[j])
            return None if best is None else best[1]

    def latest(self) -> Pose2D | None:
        """The newest pose of the current segment (the rate filter's, for a frame that matched none)."""
        with self._lock:
            poses = self._segments.get(self.segment, ([], []))[1]
            return poses[-1] if poses else None


@dataclass
class RateFilter:
    """Which frames are posted: every `every_n`-th frame, and, with `min_distance` > 0, only once the
    camera moved that far from the last frame taken (frames without a pose then wait for one)."""

    every_n: int = 1
    min_distance: float = 0.0
    _count: int = 0
    _last: Pose2D | None = None

    def take(self, pose: Pose2D | None) -> bool:
        self._count += 1
        if self._count < self.every_n:
            return False
        if self.min_distance > 0:
            if pose is None:
                return False
            if self._last is not None and pose.distance(self._last) < self.min_distance:
                return False
            self._last = pose
        self._count = 0
        return True


# --------------------------------------------------------------------------------------------- log

#: Seconds between two log lines of one kind (`LogLimiter`): skipped and refused frames, ignored odometry,
#: the poster's faults.
LOG_PERIOD_S = 60.0


class LogLimiter:
    """Log lines of many of a kind, at camera or odometry rate, kept to one a minute: each kind is said the
    first time, then at most every `period_s` with how many more came since (the rest counted, not said).
    Thread-safe."""

    def __init__(self, period_s: float = LOG_PERIOD_S, clock: Any = time.monotonic) -> None:
        self.period_s, self._clock = period_s, clock
        self._kinds: dict[str, tuple[float, int]] = {}  # kind: (last said, not said since)
        self._lock = threading.Lock()

    def line(self, kind: str, text: str) -> str | None:
        """The line to log now for one more of `kind` (`text`, and how many more since the last line), or
        None: said within `period_s`, counted."""
        with self._lock:
            now = self._clock()
            said, since = self._kinds.get(kind, (-math.inf, 0))
            if now - said < self.period_s:
                self._kinds[kind] = (said, since + 1)
                return None
            self._kinds[kind] = (now, 0)
        return f"{text} ({since} more like it since the last line)" if since else text


# ------------------------------------------------------------------------------------------- queue

DropPolicy = Literal["drop_oldest", "drop_newest"]
DROP_POLICIES: tuple[str, ...] = ("drop_oldest", "drop_newest")
T = TypeVar("T")


@dataclass
class FrameQueue(Generic[T]):
    """The frames waiting for the poster, at most `size`. Full, `drop_oldest` drops the oldest waiting
    frame for the new one (freshest answers: localising), `drop_newest` refuses the new one (the
    sequence keeps its first frames whole: mapping a short burst). Thread-safe."""

    size: int
    policy: DropPolicy = "drop_oldest"
    dropped: int = 0
    _items: deque[T] = field(default_factory=deque)
    _cond: threading.Condition = field(default_factory=threading.Condition)

    def put(self, item: T) -> T | None:
        """Queue `item`; returns the frame dropped for it (the oldest, or `item` itself), if any."""
        with self._cond:
            out = None
            if len(self._items) >= self.size:
                self.dropped += 1
                if self.policy == "drop_newest":
                    return item
                out = self._items.popleft()
            self._items.append(item)
            self._cond.notify()
            return out

    def get(self, timeout: float) -> T | None:
        """The oldest waiting frame, or None after `timeout` seconds without one."""
        with self._cond:
            if not self._items:
                self._cond.wait(timeout)
            return self._items.popleft() if self._items else None

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)
