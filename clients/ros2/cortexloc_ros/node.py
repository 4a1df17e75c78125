"""`cortexloc_node`: camera frames (and odometry, camera_info) in, places and loop closures out.

The executor only converts and queues: each image callback turns the message into a raw frame (step
padding dropped, 16-bit samples in the host's order), applies the rate filter (with the odometry in so
far) and puts it on the bounded queue. The poster thread (`cortexloc_ros.poster`) matches each frame's
odometry (waiting, bounded, for the sample of its instant), posts the queue through the typed client
and publishes each answer. A 1 Hz timer on the executor
publishes diagnostics, so they keep coming while the service is down.

Topics and parameters: `cortexloc_ros.params.PARAMETERS`; the JSON documents: `cortexloc_ros.answers`.
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from collections import deque
from dataclasses import replace
from typing import Any

import rclpy
import rclpy.logging
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.event_handler import QoSMessageLostInfo, SubscriptionEventCallbacks, UnsupportedEventTypeError
from rclpy.exceptions import InvalidTopicNameException
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import ColorRGBA, String
from visualization_msgs.msg import Marker, MarkerArray

from cortexloc_client import Client, Observation, RetryPolicy
from cortexloc_client.models import LoopClosure
from cortexloc_ros.answers import (
    closure_colour,
    epoch_json,
    loop_closure_json,
    place_json,
    place_pose,
    retraction_json,
)
from cortexloc_ros.core import (
    JUMP_CONFIRM,
    FrameKeys,
    FrameQueue,
    ImageError,
    LogLimiter,
    OdometryBuffer,
    Pose2D,
    RateFilter,
    Stamp,
    image_array,
    yaw_from_quaternion,
)
from cortexloc_ros.params import (
    PARAMETERS,
    Config,
    ConfigError,
    config_warnings,
    empty_overrides,
    read_config,
    stream_problem,
    trail_of,
    usage,
)
from cortexloc_ros.poster import Frame, Poster, Stats

__all__ = ["CortexlocNode", "main"]

NODE_NAME = "cortexloc_node"
#: Loop-closure edges kept for the markers (the oldest go first).
MAX_EDGES = 1000
#: The frame of poses that were posted without one.
DEFAULT_FRAME = "map"
#: Distortion models the service's pinhole camera takes (OpenCV's coefficients, in ROS's order).
PINHOLE_MODELS = ("plumb_bob", "rational_polynomial", "")
DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)

# Sensor data as camera drivers publish it: best effort (a reliable subscriber would not hear a
# best-effort camera; a best-effort one hears both). `qos_overrides.<topic>.subscription.reliability`
# changes it (ROS 2's QoS override parameters).
_SENSOR_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
_QOS_OVERRIDES = QoSOverridingOptions.with_default_policies()


class NodeLog:
    """The node's logger while its context is valid. Once SIGINT or SIGTERM shut the context down, lines go
    through a logger of another name (`<node>.shutdown`), which has no rosout publisher: the node's would
    print each line with rcl's "Failed to publish log message to rosout: publisher's context is invalid"."""

    def __init__(self, node: Node) -> None:
        self._node = node
        self._name = node.get_logger().name

    def _logger(self) -> Any:
        if self._node.context.ok():
            return self._node.get_logger()
        return rclpy.logging.get_logger(f"{self._name}.shutdown")

    def info(self, text: str) -> None:
        self._logger().info(text)

    def warning(self, text: str) -> None:
        self._logger().warning(text)

    def error(self, text: str) -> None:
        self._logger().error(text)


class CortexlocNode(Node):
    """The node; `ConfigError` from the constructor when its parameters cannot be used."""

    def __init__(self) -> None:
        super().__init__(NODE_NAME)
        self.cfg = self._read_parameters()
        cfg = self.cfg
        for line in config_warnings(cfg):
            self.get_logger().warning(line)
        self.stats = Stats()
        self.queue: FrameQueue[Frame] = FrameQueue(cfg.queue_size, cfg.queue_policy)  # type: ignore[arg-type]
        self.rate = RateFilter(cfg.every_n, cfg.min_distance)
        self.odometry = OdometryBuffer(cfg.odom_tolerance_ns) if cfg.topics["odometry"] else None
        self._camera: dict[str, Any] | None = None
        # (closure id, the frame's pose, the place's stored pose, confidence)
        self._edges: deque[tuple[int | None, Pose2D, Pose2D, float]] = deque(maxlen=MAX_EDGES)
        self._warned: set[str] = set()
        self._said = LogLimiter()  # kinds of skipped frames and ignored odometry: one line a minute each
        self._lock = threading.Lock()
        self.log = NodeLog(self)

        image_topic = cfg.topics["image"] + ("/compressed" if cfg.compressed else "")
        self._check_names(cfg)
        self.image_topic = self.resolve_topic_name(image_topic)
        self.keys = FrameKeys(cfg.run_id, self.image_topic)
        stream = cfg.stream or self.image_topic.lstrip("/")
        self.cfg = cfg = replace(cfg, stream=stream, trail=trail_of(cfg.trail, self.get_namespace()) or "")
        # A best-effort subscription loses what the transport loses (a raw camera image is hundreds of UDP
        # fragments): the middleware's count of lost samples goes to diagnostics, which would else only
        # show the frames that arrived.
        kind = CompressedImage if cfg.compressed else Image
        try:
            self.create_subscription(kind, image_topic, self._on_image, _SENSOR_QOS,
                                     qos_overriding_options=_QOS_OVERRIDES,
                                     event_callbacks=SubscriptionEventCallbacks(message_lost=self._on_lost))
        except UnsupportedEventTypeError:  # a middleware without the event: no count, the node still runs
            self.create_subscription(kind, image_topic, self._on_image, _SENSOR_QOS,
                                     qos_overriding_options=_QOS_OVERRIDES)
        if cfg.topics["camera_info"]:
            self.create_subscription(CameraInfo, cfg.topics["camera_info"], self._on_camera_info, _SENSOR_QOS,
                                     qos_overriding_options=_QOS_OVERRIDES)
        if self.odometry is not None:
            self.create_subscription(Odometry, cfg.topics["odometry"], self._on_odometry,
                                     QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT),
                                     qos_overriding_options=_QOS_OVERRIDES)
        self.pub_place = self.create_publisher(String, cfg.topics["place"], 10)
        self.pub_pose = self.create_publisher(PoseWithCovarianceStamped, cfg.topics["place_pose"], 10)
        self.pub_closures = self.create_publisher(String, cfg.topics["loop_closures"], 100)
        self.pub_markers = self.create_publisher(MarkerArray, cfg.topics["markers"], 1)
        self.pub_diagnostics = self.create_publisher(DiagnosticArray, cfg.topics["diagnostics"], 10)

        # The poster is the only retry loop: the client tries once, so each failure reaches diagnostics.
        self.client = Client(cfg.service_url, api_key=cfg.api_key, timeout=cfg.request_timeout,
                             retry=RetryPolicy(attempts=1))
        self.poster = Poster(cfg, self.client, self.queue, self.stats, self.odometry, self._camera_now,
                             self._publish_answer, self.log, self._publish_retraction, self._publish_epoch)
        self.create_timer(1.0, self._publish_diagnostics)
        self.poster.start()
        self.get_logger().info(
            f"{image_topic} -> {cfg.service_url} map {cfg.map_id!r} stream {cfg.stream!r} "
            f"trail {cfg.trail or '(its own)'} ({'learn' if cfg.learn else 'localise'}), run id {cfg.run_id}")

    # ---------------------------------------------------------------------------------- parameters

    def _read_parameters(self) -> Config:
        values: dict[str, Any] = {}
        for name, (default, description) in PARAMETERS.items():
            # dynamic typing: `read_config` checks the types itself and says which parameter is wrong
            # (rclpy would refuse `-p odom_tolerance:=1` for a double with a terse type error)
            descriptor = ParameterDescriptor(description=description, read_only=True, dynamic_typing=True)
            values[name] = self.declare_parameter(name, default, descriptor).value
        overrides = getattr(self, "_parameter_overrides", {})  # what --ros-args and params files gave
        unknown = [n for n in overrides if not self.has_parameter(n) and not n.startswith("qos_overrides.")]
        return read_config(values, unknown=unknown)

    def _check_names(self, cfg: Config) -> None:
        """Topic names ROS refuses, and a stream derived from the image topic that the service refuses,
        as `ConfigError` lines: found here, before anything is made, they would otherwise end the node
        in a traceback from `create_publisher`, or have every frame refused."""
        problems = []
        for name, topic in cfg.topics.items():
            if not topic:  # an optional input left out (read_config requires the others)
                continue
            try:
                self.resolve_topic_name(topic)
            except (_rclpy.RCLError, InvalidTopicNameException) as e:
                reason = str(e).split(", at ")[0].removeprefix("failed to resolve name: ")
                problems.append(f"topics.{name}: {topic!r} is not a ROS topic name ({reason})")
        if not problems and not cfg.stream:
            image_topic = cfg.topics["image"] + ("/compressed" if cfg.compressed else "")
            problem = stream_problem("stream", self.resolve_topic_name(image_topic).lstrip("/"))
            if problem:
                problems.append(f"{problem}: it is the image topic's name; set stream")
        if problems:
            raise ConfigError(problems)

    # ----------------------------------------------------------------------------------- callbacks

    def _warn_once(self, what: str, text: str) -> None:
        if what not in self._warned:
            self._warned.add(what)
            self.get_logger().warning(text)

    def _warn_limited(self, what: str, text: str) -> None:
        """One of a kind that may come at camera or odometry rate (`what`: e.g. a skipped frame's encoding
        and fault): said the first time, then at most once a minute with how many more came since."""
        line = self._said.line(what, text)
        if line is not None:
            self.get_logger().warning(line)

    def _on_lost(self, info: QoSMessageLostInfo) -> None:
        """The middleware lost camera frames before they reached the node (a best-effort subscription)."""
        with self.stats.lock:
            self.stats.lost += int(info.total_count_change)
        self._warn_once("lost", f"camera frames lost in transport before they reached the node "
                                f"({info.total_count} so far, counted in diagnostics as `lost`): the image "
                                f"subscription is best effort; with a camera that publishes reliably set "
                                f"qos_overrides.{self.image_topic}.subscription.reliability:=reliable, or "
                                f"subscribe to its compressed images")

    def _on_odometry(self, msg: Odometry) -> None:
        assert self.odometry is not None
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        base = Pose2D(p.x, p.y, yaw_from_quaternion(q.x, q.y, q.z, q.w), msg.header.frame_id or "odom")
        pose = base.compose(self.cfg.camera_mount)
        if not pose.is_postable():
            # an EKF before it has converged, or after it diverged (NaN, Inf, or 10^12 m): the service refuses
            # such a pose (422), and every frame matched to it was lost; left out, a frame takes a postable
            # sample within odom_tolerance, or goes without a pose (`no_pose`) and the service judges the
            # move by appearance
            self._warn_limited("odometry:unpostable", f"odometry ignored: its pose is not finite or beyond "
                                                      f"the service's bounds (x {p.x}, y {p.y}, yaw "
                                                      f"{base.yaw}); frames go without it")
            return
        self.odometry.add(Stamp.of(msg.header.stamp.sec, msg.header.stamp.nanosec), pose)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        k, d = list(msg.k), list(msg.d)
        if not all(math.isfinite(v) for v in (*k, *d)):  # the service refuses the frames' metadata (422)
            self._warn_once("not-finite", "camera_info holds a K or D that is not finite: frames go without "
                                          "a camera")
            camera = None
        elif k[0] <= 0 or k[4] <= 0:  # an uncalibrated camera publishes zeros
            self._warn_once("uncalibrated", "camera_info holds no intrinsics (K is zero): frames go without")
            camera = None
        elif msg.distortion_model not in PINHOLE_MODELS or len(d) not in DISTORTION_LENGTHS:
            self._warn_once("model", f"camera_info's distortion model {msg.distortion_model!r} ({len(d)} "
                                     f"coefficients) is not OpenCV's pinhole model: frames go without "
                                     f"a camera")
            camera = None
        else:
            camera = {"fx": k[0], "fy": k[4], "cx": k[2], "cy": k[5], "distortion": d}
        with self._lock:
            self._camera = camera

    def _camera_now(self) -> dict[str, Any] | None:
        with self._lock:
            return self._camera

    def _on_image(self, msg: Image | CompressedImage) -> None:
        with self.stats.lock:
            self.stats.received += 1
        stamp = Stamp.of(msg.header.stamp.sec, msg.header.stamp.nanosec)
        got = self.keys.next(stamp, msg.data)  # before anything can skip it: one key a message
        if got.duplicate:
            with self.stats.lock:
                self.stats.duplicates += 1
            self._warn_once("duplicate", f"a camera message came twice (stamp {stamp.ns} ns and the same "
                                         f"bytes as one received before: a camera bridged or published "
                                         f"twice?): each is posted once (counted in diagnostics as "
                                         f"`duplicates`)")
            return
        if got.back_ns:
            text = (f"the camera's stamps went back {got.back_ns / 1e9:.3f} s ({JUMP_CONFIRM} frames in a "
                    f"row, the last stamped {stamp.ns} ns: a bag played again, as `ros2 bag play --loop` "
                    f"does, or a simulation reset): a new drive from this frame on (drive {got.drive} of "
                    f"this run): the stream is reset on the service and the frames are posted with keys of "
                    f"their own, as after a restart; to map a recording once, play it without --loop")
            if "back" in self._warned:  # each pass of a looped bag: said, but as a warning only once
                self.get_logger().info(text)
            else:
                self._warn_once("back", text)
        if got.unstamped:
            pose = ("without an odometry pose (one matched by such a stamp may be another frame's: counted "
                    "as `no_pose`), so the service judges the move by appearance" if self.odometry is not None
                    else "but its stored stamp cannot tell it from the one before")
            self._warn_once("stamps", f"the camera's stamps do not tell its frames apart ({stamp.ns} ns: "
                                      f"zero, or the previous frame's; a driver that does not stamp sends "
                                      f"0): each frame is still posted, {pose}")
        try:
            if isinstance(msg, CompressedImage):
                image: Any = bytes(msg.data)
                colour = "rgb8"
            else:
                image = image_array(msg.data, height=msg.height, width=msg.width, step=msg.step,
                                    encoding=msg.encoding, is_bigendian=bool(msg.is_bigendian))
                colour = msg.encoding if msg.encoding in ("rgb8", "bgr8", "rgba8", "bgra8") else "rgb8"
        except ValueError as e:  # an ImageError, which names its fault's kind
            reason = e.reason if isinstance(e, ImageError) else "malformed"
            with self.stats.lock:
                if reason == "encoding":
                    self.stats.unsupported += 1
                else:
                    self.stats.malformed += 1
                self.stats.last_error = str(e)
            self._warn_limited(f"{getattr(msg, 'encoding', '')}:{reason}", f"frame skipped: {e}")
            return
        # The rate filter's distance needs a pose now: the nearest in so far, else the latest. The pose
        # posted is matched by the poster, once the odometry of the frame's instant is in.
        pose = self.odometry.match(stamp) if self.odometry is not None and not got.unstamped else None
        if not self.rate.take(pose or (self.odometry.latest() if self.odometry is not None else None)):
            with self.stats.lock:
                self.stats.skipped_rate += 1
            return
        frame = Frame(stamp, msg.header.frame_id, image, colour, got.key, time.monotonic(),
                      stamped=not got.unstamped, drive=got.drive)
        if self.queue.put(frame) is not None:
            self._warn_once("drop", f"queue full ({self.cfg.queue_size}): frames dropped by "
                                    f"{self.cfg.queue_policy} (counted in diagnostics)")

    # ---------------------------------------------------------------------------------- publishing

    def _publish_answer(self, frame: Frame, pose: Pose2D | None, answer: Observation,
                        latency_ms: float) -> None:
        """On the poster's thread: the place JSON, the place's stored pose, a loop closure and its edge."""
        doc = place_json(answer, frame.stamp, frame.frame_id, pose, latency_ms, DEFAULT_FRAME)
        self.pub_place.publish(String(data=json.dumps(doc, separators=(",", ":"))))
        stored = place_pose(answer.place, DEFAULT_FRAME)
        if stored is not None:
            self.pub_pose.publish(self._pose_message(frame.stamp, stored))
        doc = loop_closure_json(answer, frame.stamp, frame.frame_id, pose, DEFAULT_FRAME)
        if doc is None:
            return
        self.pub_closures.publish(String(data=json.dumps(doc, separators=(",", ":"))))
        if pose is not None and stored is not None and pose.frame_id == stored.frame_id:
            self._edges.append((answer.loop_closure_id, pose, stored, float(doc["confidence"])))
            self.pub_markers.publish(self._markers())

    def _publish_retraction(self, entry: LoopClosure) -> None:
        """On the poster's thread: a retraction of one of the stream's closures, and its edge taken off
        the markers."""
        self.pub_closures.publish(String(data=json.dumps(retraction_json(entry, self.cfg.map_id),
                                                         separators=(",", ":"))))
        kept = [e for e in self._edges if e[0] != entry.retracts]
        if len(kept) != len(self._edges):
            self._edges = deque(kept, maxlen=MAX_EDGES)
            self.pub_markers.publish(self._markers())

    def _publish_epoch(self, previous: str, epoch: str) -> None:
        """On the poster's thread: the map's log changed its epoch (a restore, or a repair that withdrew
        closures the log no longer kept): the closures published so far may be gone or withdrawn without a
        retraction, so the back end rebuilds from the export; the markers are cleared."""
        self.pub_closures.publish(String(data=json.dumps(epoch_json(self.cfg.map_id, previous, epoch),
                                                         separators=(",", ":"))))
        self._edges.clear()
        self.pub_markers.publish(self._markers())

    def _pose_message(self, stamp: Stamp, pose: Pose2D) -> PoseWithCovarianceStamped:
        msg = PoseWithCovarianceStamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = stamp.sec, stamp.nanosec
        msg.header.frame_id = pose.frame_id
        msg.pose.pose.position.x, msg.pose.pose.position.y = pose.x, pose.y
        q = msg.pose.pose.orientation
        q.z, q.w = math.sin(pose.yaw / 2), math.cos(pose.yaw / 2)
        vx, vy, vyaw = self.cfg.place_covariance
        cov = [0.0] * 36
        for i, var in enumerate((vx, vy, 1e6, 1e6, 1e6, vyaw)):  # x y z roll pitch yaw
            cov[i * 7] = var
        msg.pose.covariance = cov
        return msg

    def _markers(self) -> MarkerArray:
        """Every kept loop-closure edge (frame's pose -> the place's stored pose) as one LINE_LIST in the
        first edge's frame, coloured from red (confidence at the map's `revisit_threshold`, as the poster
        read it at first contact) to green (1) (`answers.closure_colour`); with none left (all retracted),
        the list deleted."""
        edges = list(self._edges)
        m = Marker()
        m.ns, m.id, m.type = "cortexloc_loop_closures", 0, Marker.LINE_LIST
        if not edges:
            m.header.frame_id, m.action = DEFAULT_FRAME, Marker.DELETE
            return MarkerArray(markers=[m])
        frame_id = edges[0][1].frame_id
        m.header.frame_id = frame_id  # stamp zero: drawn with the latest transform
        m.action = Marker.ADD
        m.pose.orientation.w = 1.0
        m.scale.x = 0.2
        threshold = self.poster.revisit_threshold
        for _, a, b, confidence in edges:
            if a.frame_id != frame_id:
                continue
            red, green = closure_colour(confidence, threshold)
            colour = ColorRGBA(r=red, g=green, b=0.2, a=1.0)
            m.points.extend([Point(x=a.x, y=a.y), Point(x=b.x, y=b.y)])
            m.colors.extend([colour, colour])
        return MarkerArray(markers=[m])

    def _publish_diagnostics(self) -> None:
        s = self.stats
        median = s.median_latency_ms()
        with s.lock:
            service, error = s.service, s.last_error
            values = {"service": service, "service_url": self.cfg.service_url, "map": self.cfg.map_id,
                      "stream": self.cfg.stream, "mode": "learn" if self.cfg.learn else "localise",
                      "received": s.received, "lost": s.lost, "skipped_rate": s.skipped_rate,
                      "duplicates": s.duplicates, "unsupported": s.unsupported, "malformed": s.malformed,
                      "queue_depth": len(self.queue), "queue_size": self.cfg.queue_size,
                      "queue_policy": self.cfg.queue_policy, "dropped": self.queue.dropped,
                      "answered": s.answered, "refused": s.refused, "failed": s.failed, "retries": s.retries,
                      "revisits": s.revisits, "retractions": s.retractions, "no_pose": s.no_pose,
                      "latency_ms": "" if s.last_latency_ms is None else f"{s.last_latency_ms:.1f}",
                      "latency_ms_median": "" if median is None else f"{median:.1f}", "last_error": error}
            health, message = s.health(self.queue.dropped)
        level = getattr(DiagnosticStatus, health)  # the health's name is the constant's: OK, WARN, ERROR
        status = DiagnosticStatus(level=level, name=f"{self.get_fully_qualified_name()}: cortexloc",
                                  message=message, hardware_id=self.cfg.service_url,
                                  values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diagnostics.publish(msg)

    def close(self) -> None:
        """Stops the poster; says how many frames it leaves unposted (one line, not through the node's
        rosout once the context is shut down)."""
        line = self.poster.stop()
        if line:
            self.log.warning(f"{line}; a restart posts only what the camera sends from then on")
        self.client.close()


def main(args: list[str] | None = None) -> int:
    """`cortexloc-ros [--ros-args -p name:=value ... --params-file params.yaml]`: run the node until
    SIGINT or SIGTERM. Exit status 0; 2 with one line per problem when the parameters cannot be used.
    `--help` (or `-h`) before `--ros-args` prints the usage and exits 0 without starting ROS."""
    argv = sys.argv[1:] if args is None else args[1:]  # rclpy's args, like sys.argv, start with the program
    ours = argv[: argv.index("--ros-args")] if "--ros-args" in argv else argv
    if "--help" in ours or "-h" in ours:
        print(usage())
        return 0
    try:
        empty = empty_overrides(argv)
        if empty:
            raise ConfigError(empty)
        rclpy.init(args=args)
    except (ConfigError, _rclpy.RCLError) as e:  # rcl's parse errors: one line, not a traceback
        print(f"cortexloc-ros: {e}".split(", at /")[0], file=sys.stderr)
        return 2
    except _rclpy.UnknownROSArgsError as e:  # a stray word after --ros-args
        print(f"cortexloc-ros: unknown ROS arguments {e}: each parameter needs its -p, and a value with "
              "a space its quotes (-p stream:=\"'front cam'\")", file=sys.stderr)
        return 2
    try:
        node = CortexlocNode()
    except ConfigError as e:
        print(f"cortexloc-ros: {e}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except _rclpy.RCLError:
        # SIGTERM's handler shuts the context down; when that lands while spin builds its wait set,
        # rclpy raises RCLError ("the given context is not valid") instead of ExternalShutdownException:
        # the same shutdown, which must end with status 0 and no traceback
        if rclpy.ok():
            raise
    finally:
        node.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def run() -> None:
    """The console entry point."""
    sys.exit(main())
