"""The tests' side of the topics: a node in the test's process that publishes a camera (images,
camera_info, odometry) and records what `cortexloc_node` publishes. Imported inside the loopback namespace
only (it needs rclpy)."""

from __future__ import annotations

import json
import time
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import String
from visualization_msgs.msg import MarkerArray

from tests.clients.ros2.harness import wait_until

#: The test camera's intrinsics (the Nordland frames' are unknown; these are a 64 x 32 pinhole's).
K = [60.0, 0.0, 32.0, 0.0, 60.0, 16.0, 0.0, 0.0, 1.0]
D = [0.01, -0.02, 0.0, 0.0, 0.0]


class Probe(Node):
    def __init__(self) -> None:
        super().__init__("cortexloc_test_probe")
        self.images = self.create_publisher(Image, "/cam/image_raw", 100)
        self.compressed = self.create_publisher(CompressedImage, "/cam/image_raw/compressed", 100)
        self.infos = self.create_publisher(CameraInfo, "/cam/camera_info", 100)
        self.odom = self.create_publisher(Odometry, "/odom", 100)
        self.places: list[dict[str, Any]] = []
        self.closures: list[dict[str, Any]] = []
        self.poses: list[PoseWithCovarianceStamped] = []
        self.markers: list[MarkerArray] = []
        self.diagnostics: list[tuple[float, dict[str, str], int]] = []  # (receipt time, values, level)
        self.create_subscription(String, "/cortexloc/place",
                                 lambda m: self.places.append(json.loads(m.data)), 100)
        self.create_subscription(String, "/cortexloc/loop_closures",
                                 lambda m: self.closures.append(json.loads(m.data)), 100)
        self.create_subscription(PoseWithCovarianceStamped, "/cortexloc/place_pose", self.poses.append, 100)
        self.create_subscription(MarkerArray, "/cortexloc/loop_closure_markers", self.markers.append, 10)
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 100)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for s in msg.status:
            if s.name.endswith(": cortexloc"):
                level = s.level if isinstance(s.level, int) else int.from_bytes(s.level, "little")
                self.diagnostics.append((time.monotonic(), {kv.key: kv.value for kv in s.values}, level))

    def spin(self, seconds: float = 0.05) -> None:
        rclpy.spin_once(self, timeout_sec=seconds)

    def wait(self, cond: Any, timeout_s: float, what: str) -> None:
        wait_until(cond, timeout_s, what, self.spin)

    def last_diagnostics(self) -> dict[str, str]:
        return self.diagnostics[-1][1] if self.diagnostics else {}

    def wait_connected(self, timeout_s: float = 60, compressed: bool = False) -> None:
        """Until the node subscribes to the camera and its diagnostics arrive (DDS discovery done)."""
        images = self.compressed if compressed else self.images
        self.wait(lambda: images.get_subscription_count() > 0 and self.odom.get_subscription_count() > 0
                  and self.infos.get_subscription_count() > 0 and bool(self.diagnostics), timeout_s,
                  "the node to subscribe and publish diagnostics")

    def publish(self, frame: np.ndarray, stamp_ns: int, x: float, y: float, yaw: float = 0.0,
                encoding: str = "rgb8", pad: int = 0, png: bool = False) -> None:
        """Odometry, camera_info and the frame, all stamped `stamp_ns`: a raw `Image` with rows padded by
        `pad` bytes, or (`png`) a `CompressedImage` of an RGB frame."""
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        odom = Odometry()
        odom.header.stamp.sec, odom.header.stamp.nanosec = sec, nanosec
        odom.header.frame_id, odom.child_frame_id = "odom", "base_link"
        odom.pose.pose.position.x, odom.pose.pose.position.y = x, y
        odom.pose.pose.orientation.z, odom.pose.pose.orientation.w = np.sin(yaw / 2), np.cos(yaw / 2)
        self.odom.publish(odom)
        info = CameraInfo(height=frame.shape[0], width=frame.shape[1], distortion_model="plumb_bob", d=D, k=K)
        info.header.stamp.sec, info.header.stamp.nanosec = sec, nanosec
        info.header.frame_id = "cam_optical"
        self.infos.publish(info)
        if png:
            import cv2

            _, buf = cv2.imencode(".png", cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
            msg = CompressedImage(format="png", data=buf.tobytes())
            msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
            msg.header.frame_id = "cam_optical"
            self.compressed.publish(msg)
            return
        rows = frame.reshape(frame.shape[0], -1).view(np.uint8)
        if pad:
            rows = np.concatenate([rows, np.full((rows.shape[0], pad), 0xAB, np.uint8)], axis=1)
        img = Image(height=frame.shape[0], width=frame.shape[1], encoding=encoding,
                    is_bigendian=int(frame.dtype.byteorder == ">"), step=rows.shape[1], data=rows.tobytes())
        img.header.stamp.sec, img.header.stamp.nanosec = sec, nanosec
        img.header.frame_id = "cam_optical"
        self.images.publish(img)


def start_probe() -> Probe:
    rclpy.init()
    return Probe()


def stop_probe(probe: Probe) -> None:
    probe.destroy_node()
    rclpy.try_shutdown()
