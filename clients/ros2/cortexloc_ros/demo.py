"""`cortexloc-ros-demo`: the node on the shipped demo frames, from camera to loop closures on a topic.

It starts `cortexloc_node` (a subprocess, `python -m cortexloc_ros`, ended by its PID), waits until the
node's diagnostics say the service is up, then publishes the 60 frames of `data/nordland_demo.npz` (30
places of the Nordland line in summer, the same 30 in winter) as `sensor_msgs/Image` with odometry, and
prints every loop closure that arrives on `/cortexloc/loop_closures`: the winter pass closes loops with
the summer one. Odometry is made up: the line is straight, one place every 10 m, and the winter pass has
drifted 5 m to the side, so the closures' edges show in RViz (`/cortexloc/loop_closure_markers`).

Exit status 0 when every frame was answered and a loop closure arrived; 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from importlib.resources import files
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import String

__all__ = ["main", "run"]

IMAGE_TOPIC, ODOM_TOPIC = "/demo/camera/image_raw", "/demo/odom"
PLACE_SPACING_M, WINTER_DRIFT_M = 10.0, 5.0
FRAME_PERIOD_S = 0.1


def demo_frames() -> tuple[np.ndarray, list[str]]:
    """The shipped frames, (60, 32, 64) uint8 grey, and their source names."""
    with files("cortexloc_ros").joinpath("data/nordland_demo.npz").open("rb") as f, np.load(f) as z:
        return z["frames"], [str(n) for n in z["names"]]


def node_command(url: str, map_id: str) -> list[str]:
    """The node's command line for the demo: its topics, a queue that holds the whole route."""
    return [sys.executable, "-m", "cortexloc_ros", "--ros-args",
            "-p", f"service_url:={url}", "-p", f"map:={map_id}", "-p", "stream:=demo/camera",
            "-p", f"topics.image:={IMAGE_TOPIC}", "-p", f"topics.odometry:={ODOM_TOPIC}",
            "-p", "topics.camera_info:=''", "-p", "queue.size:=100",
            "-p", f"qos_overrides.{IMAGE_TOPIC}.subscription.reliability:=reliable",
            "-p", f"qos_overrides.{ODOM_TOPIC}.subscription.reliability:=reliable"]


class Demo(Node):
    def __init__(self) -> None:
        super().__init__("cortexloc_demo")
        self.images = self.create_publisher(Image, IMAGE_TOPIC, 100)
        self.odom = self.create_publisher(Odometry, ODOM_TOPIC, 100)
        self.answers: list[dict[str, Any]] = []
        self.closures: list[dict[str, Any]] = []
        self.service = ""
        self.create_subscription(String, "/cortexloc/place",
                                 lambda m: self.answers.append(json.loads(m.data)), 100)
        self.create_subscription(String, "/cortexloc/loop_closures", self._on_closure, 100)
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)

    def _on_closure(self, msg: String) -> None:
        c = json.loads(msg.data)
        self.closures.append(c)
        t, pt = c["stamp"], c["place_stamp"] or {"sec": 0, "nanosec": 0}
        pose, place = c["pose"] or {}, c["place_pose"] or {}
        print(f"loop closure: {t['sec']}.{t['nanosec']:09d} at "
              f"({pose.get('x', 0):.0f}, {pose.get('y', 0):.0f}) "
              f"-> {pt['sec']}.{pt['nanosec']:09d} at ({place.get('x', 0):.0f}, {place.get('y', 0):.0f}), "
              f"confidence {c['confidence']:.2f}  [place seq {c['place_seq']}]", flush=True)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name.endswith("cortexloc"):
                self.service = {kv.key: kv.value for kv in status.values}.get("service", "")

    def publish(self, i: int, frame: np.ndarray, stamp_ns: int, x: float, y: float) -> None:
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        odom = Odometry()
        odom.header.stamp.sec, odom.header.stamp.nanosec = sec, nanosec
        odom.header.frame_id, odom.child_frame_id = "odom", "base_link"
        odom.pose.pose.position.x, odom.pose.pose.position.y = x, y
        odom.pose.pose.orientation.w = 1.0
        self.odom.publish(odom)
        img = Image(height=frame.shape[0], width=frame.shape[1], encoding="mono8", is_bigendian=0,
                    step=frame.shape[1], data=frame.tobytes())
        img.header.stamp.sec, img.header.stamp.nanosec = sec, nanosec
        img.header.frame_id = "camera_optical"
        self.images.publish(img)


class NodeExitedError(RuntimeError):
    pass


def _spin_until(node: Node, done: Any, timeout_s: float, proc: subprocess.Popen[bytes] | None = None) -> bool:
    deadline = time.monotonic() + timeout_s
    while not done():
        if proc is not None and proc.poll() is not None:
            raise NodeExitedError(f"cortexloc_node exited with status {proc.returncode}")
        if time.monotonic() > deadline:
            return False
        rclpy.spin_once(node, timeout_sec=0.1)
    return True


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="cortexloc-ros-demo", description=__doc__.split("\n\n")[0])
    ap.add_argument("--url", default="http://127.0.0.1:8000", help="the cortexloc service")
    ap.add_argument("--map", default="cortexloc-demo", help="the map learned (created when missing)")
    ap.add_argument("--timeout", type=float, default=600.0,
                    help="seconds to wait for the service and answers")
    args = ap.parse_args(argv)
    frames, names = demo_frames()
    rclpy.init()
    node = subprocess.Popen(node_command(args.url, args.map))
    demo = Demo()
    try:
        print(f"waiting for cortexloc_node and the service at {args.url} ...", flush=True)
        if not _spin_until(demo, lambda: demo.service == "up", args.timeout, node):
            print(f"the service at {args.url} did not come up (start it: cortexloc serve)", file=sys.stderr)
            return 1
        _spin_until(demo, lambda: demo.images.get_subscription_count() > 0
                    and demo.odom.get_subscription_count() > 0, 30, node)
        print(f"publishing {len(frames)} frames on {IMAGE_TOPIC} ({names[0]} .. {names[-1]}) with "
              f"odometry on {ODOM_TOPIC}; loop closures from /cortexloc/loop_closures:", flush=True)
        t0 = time.time_ns()
        half = len(frames) // 2
        for i, frame in enumerate(frames):
            lap, place = divmod(i, half)
            demo.publish(i, frame, t0 + round(i * FRAME_PERIOD_S * 1e9), place * PLACE_SPACING_M,
                         lap * WINTER_DRIFT_M)
            _spin_until(demo, lambda: False, FRAME_PERIOD_S)
        answered = _spin_until(demo, lambda: len(demo.answers) >= len(frames), args.timeout, node)
        revisits = sum(bool(a["place"] and a["place"]["revisit"]) for a in demo.answers)
        # the last answer's closure is published just after its place: let it arrive
        _spin_until(demo, lambda: len(demo.closures) >= revisits, 10, node)
        print(f"{len(demo.answers)}/{len(frames)} frames answered, {revisits} revisits, "
              f"{len(demo.closures)} loop closures on /cortexloc/loop_closures", flush=True)
        return 0 if answered and demo.closures else 1
    except NodeExitedError as e:
        print(e, file=sys.stderr)
        return 1
    finally:
        node.terminate()  # SIGTERM: the node shuts down cleanly
        try:
            node.wait(timeout=10)
        except subprocess.TimeoutExpired:
            node.kill()
            node.wait()
        demo.destroy_node()
        rclpy.try_shutdown()


def run() -> None:
    """The console entry point."""
    sys.exit(main())
