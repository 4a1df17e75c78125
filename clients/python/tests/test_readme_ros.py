"""The README's "With ROS 2" example node, run as written (its service URL aside) with `rclpy` and
`sensor_msgs` stubbed, so without ROS or a server: a frame posted while the service is unreachable is
logged and the node goes on, promptly. An outside probe: the example caught only `CortexlocError`, and
its first frame with the service down ended the node with httpx's `ConnectError` in a traceback."""

from __future__ import annotations

import re
import socket
import sys
import time
import types
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
URL = '"http://cortexloc:8000"'


def example() -> str:
    """The first ```python block under '## With ROS 2' in the client's README, as written."""
    text = README.read_text()
    section = text[text.index("## With ROS 2\n"):]
    found = re.search(r"```python\n(.*?)```", section, re.DOTALL)
    assert found, "no python block under '## With ROS 2'"
    return found.group(1)


#: The keywords rclpy's logger takes besides the text (its filters: `rclpy.impl.rcutils_logger`).
LOG_FILTERS = frozenset({"once", "throttle_duration_sec", "throttle_time_source_type", "skip_first"})


class Logger:
    """Records each line, filters left out (a throttled warning is recorded every time)."""

    def __init__(self, lines: list[tuple[str, str]]) -> None:
        self.lines = lines

    def info(self, text: str, **filters: Any) -> None:
        assert set(filters) <= LOG_FILTERS, filters
        self.lines.append(("info", text))

    def warning(self, text: str, **filters: Any) -> None:
        assert set(filters) <= LOG_FILTERS, filters
        self.lines.append(("warning", text))


class Node:
    """As much of `rclpy.node.Node` as the example uses."""

    def __init__(self, name: str) -> None:
        self.lines: list[tuple[str, str]] = []
        self.subscriptions: list[tuple[Any, str, Any]] = []

    def create_subscription(self, kind: Any, topic: str, callback: Any, depth: int) -> None:
        self.subscriptions.append((kind, topic, callback))

    def get_namespace(self) -> str:
        return "/"

    def get_logger(self) -> Logger:
        return Logger(self.lines)


def _stubbed_ros(monkeypatch: pytest.MonkeyPatch) -> None:
    names = ("rclpy", "rclpy.node", "sensor_msgs", "sensor_msgs.msg")
    modules = {name: types.ModuleType(name) for name in names}
    modules["rclpy.node"].Node = Node  # type: ignore[attr-defined]
    modules["sensor_msgs.msg"].Image = type("Image", (), {})  # type: ignore[attr-defined]
    for name, module in modules.items():
        monkeypatch.setitem(sys.modules, name, module)


def _closed_port() -> int:
    """A loopback port nothing listens on (bound, then let go): a connection to it is refused."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _image(i: int) -> SimpleNamespace:
    """A `sensor_msgs/Image` (mono8, 64 x 32) as far as the example reads it."""
    pixels = np.random.default_rng(i).integers(0, 256, (32, 64), dtype=np.uint8)
    return SimpleNamespace(encoding="mono8", height=32, width=64, step=64, is_bigendian=0,
                           data=pixels.tobytes(), header=SimpleNamespace(
                               stamp=SimpleNamespace(sec=1_700_000_000 + i, nanosec=0), frame_id="camera"))


def test_the_example_node_logs_a_frame_the_unreachable_service_did_not_answer_and_goes_on(monkeypatch):
    code = example()
    assert code.count(URL) == 1, "the example's service URL is not where the test patches it"
    _stubbed_ros(monkeypatch)
    namespace: dict[str, Any] = {"__name__": "readme_ros_example"}
    exec(compile(code.replace(URL, f'"http://127.0.0.1:{_closed_port()}"'), str(README), "exec"), namespace)
    node = namespace["Localiser"]()
    (_, topic, on_image), = node.subscriptions
    assert topic == "/camera/image_raw"
    for i in range(3):  # each frame tried, logged, and the callback returns: the executor goes on
        started = time.monotonic()
        on_image(_image(i))  # before, httpx.ConnectError out of the callback: rclpy.spin ended in a traceback
        # one try a frame: the client's default retries of a refused connection wait 0.5 + 1 + 2 s
        assert time.monotonic() - started < 3.0
    assert len(node.lines) == 3, node.lines
    assert all(level == "warning" and "ConnectError" in text for level, text in node.lines), node.lines
    node.client.close()
