"""What the ROS 2 node's tests run on: a network namespace with only loopback, a real `cortexloc serve`, a
relay in front of it (holds or loses replies, logs every post's Idempotency-Key), the node as a
subprocess, and a probe node in the test's process that publishes camera frames and records the node's
topics.

**All traffic stays on this host.** A test marked `@in_loopback_netns` re-runs itself in a pytest
subprocess under `unshare -rn` (a user and network namespace holding only `lo`, brought up), with its own
random `ROS_DOMAIN_ID`, Fast DDS on the package's UDP-only profile bound to 127.0.0.1 (no shared-memory
transport, so a killed process leaves no /dev/shm files; `ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT`,
since Kilted's LOCALHOST brings shared memory back), and ROS logs under the test's temporary folder. It
skips with the reason where rclpy, the node or namespaces are unavailable.
"""

from __future__ import annotations

import functools
import http.server
import importlib.util
import json
import os
import random
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest

REPO = Path(__file__).resolve().parents[3]
FASTDDS_PROFILE = REPO / "clients" / "ros2" / "config" / "fastdds_udp_localhost.xml"
IN_NETNS_ENV = "CORTEXLOC_ROS_TEST_NETNS"
#: The ONNX export of the backbone is made by the first service and reused (tests/e2e/conftest.py does
#: the same): set by the outer run, read inside the namespace.
WEIGHTS_ENV = "CORTEXLOC_ROS_TEST_WEIGHTS"
#: A small map (tests/conftest.py's tiny preset as overrides): the real code paths without 266 MB maps.
TINY_MAP = {"seed": 3, "slsbh": {"k": 64},
            "tm": {"columnDimensions": 128, "maxSegmentsPerCell": 8, "maxSynapsesPerSegment": 16,
                   "maxNewSynapseCount": 8, "activationThreshold": 4, "minThreshold": 2}}


# ------------------------------------------------------------------------------------------ namespace


def _netns_unavailable() -> str | None:
    try:
        p = subprocess.run(["unshare", "-rn", "sh", "-c", "ip link set lo up"], capture_output=True,
                           text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"no network namespace for the ROS tests (unshare -rn, ip): {e}"
    if p.returncode != 0:
        return f"no network namespace for the ROS tests (unshare -rn; ip link set lo up): {p.stderr.strip()}"
    return None


@functools.cache
def ros_unavailable() -> str | None:
    """Why the ROS tests cannot run here, or None."""
    for module, how in (("rclpy", "make install-ros: the `ros` extra, ROS 2 Kilted's wheels"),
                        ("cortexloc_ros", "make install-ros: the node, clients/ros2")):
        if importlib.util.find_spec(module) is None:
            return f"{module} is not installed ({how})"
    return _netns_unavailable()


def in_loopback_netns(test: Callable[..., None]) -> Callable[..., None]:
    """Run `test` inside a fresh loopback-only network namespace (module docstring): outside one, the test
    re-runs itself there in a pytest subprocess and passes, fails or skips with it."""

    @functools.wraps(test)
    def wrapper(*args: Any, **kwargs: Any) -> None:
        if os.environ.get(IN_NETNS_ENV) == "1":
            test(*args, **kwargs)
            return
        reason = ros_unavailable()
        if reason is not None:
            pytest.skip(reason)
        nodeid = os.environ["PYTEST_CURRENT_TEST"].rsplit(" ", 1)[0]
        tmp = kwargs.get("tmp_path") or Path(os.environ.get("TMPDIR", "/tmp"))
        env = {**os.environ, IN_NETNS_ENV: "1", "ROS_DOMAIN_ID": str(random.randint(1, 101)),
               "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
               "FASTDDS_DEFAULT_PROFILES_FILE": str(FASTDDS_PROFILE),
               "ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT", "ROS_LOG_DIR": str(tmp / "ros-log"),
               WEIGHTS_ENV: os.environ.get(WEIGHTS_ENV) or str(_weights_dir())}
        env.pop("ROS_LOCALHOST_ONLY", None)
        env.pop("ROS_STATIC_PEERS", None)
        cmd = ["unshare", "-rn", "sh", "-c", 'ip link set lo up && exec "$@"', "sh",
               sys.executable, "-m", "pytest", "-q", "-rsP", "-p", "no:cacheprovider", nodeid]
        p = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
        out = p.stdout + p.stderr
        skipped = re.search(r"SKIPPED \[\d+\] [^:]+:\d+: (.*)", out)
        if p.returncode == 0 and skipped and " passed" not in out:
            pytest.skip(skipped.group(1))
        if p.returncode != 0 or " passed" not in out:
            pytest.fail(f"in the loopback namespace (exit {p.returncode}):\n{out[-12000:]}", pytrace=False)
        print(out[-3000:])  # the inner run's printed figures (-rP; pytest -s shows them here)

    return wrapper


@functools.cache
def _weights_dir() -> Path:
    """One folder per pytest session for the service's backbone export, removed when the session ends."""
    import atexit
    import shutil
    import tempfile

    path = Path(tempfile.mkdtemp(prefix="cortexloc-ros-weights-"))
    atexit.register(shutil.rmtree, path, True)
    return path


# -------------------------------------------------------------------------------------------- service


def wait_until(cond: Callable[[], bool], timeout_s: float, what: str, step: Callable[[], None] | None = None
               ) -> None:
    """Poll `cond` (calling `step` between polls, e.g. spinning the probe) until true; fail after
    `timeout_s` naming `what` (a bound on a wait, not a timed assertion)."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s:.0f} s waiting for {what}")
        if step is not None:
            step()
        else:
            time.sleep(0.05)


class Service:
    """`cortexloc serve` on a fixed loopback port and one data directory: started, stopped, started again."""

    def __init__(self, tmp: Path, port: int) -> None:
        self.tmp, self.port = tmp, port
        self.url = f"http://127.0.0.1:{port}"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> Service:
        env = {k: v for k, v in os.environ.items() if not k.startswith("CORTEXLOC_")}
        env.update({"CORTEXLOC_WEIGHTS_DIR": os.environ[WEIGHTS_ENV], "CORTEXLOC_LOG_FORMAT": "text"})
        with (self.tmp / "server.log").open("ab") as log:
            self.proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port",
                                          str(self.port), "--data-dir", str(self.tmp / "var")],
                                         env=env, stdout=log, stderr=log, cwd=REPO)

        def ready() -> bool:
            assert self.proc is not None
            if self.proc.poll() is not None:
                pytest.fail(f"server exited: {(self.tmp / 'server.log').read_text()[-2000:]}")
            try:
                return httpx.get(f"{self.url}/readyz", timeout=5).status_code == 200
            except httpx.TransportError:
                return False

        wait_until(ready, 180, "the service to be ready", lambda: time.sleep(0.2))
        return self

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(timeout=60)


class Relay:
    """An HTTP relay on loopback in front of the service, as the node's `service_url`.

    Logs every observation post as (Idempotency-Key, outcome): the service's status, `lost` (the service
    answered, the relay dropped the reply: `lose_next_reply()`), `spoilt` (the service answered, the relay
    sent a proxy's HTML page with status 200 instead: `spoil_next_reply()`), or `down` (the service could
    not be reached; the relay drops the connection, as a dead service would). `hold()` keeps observation posts
    waiting until `release()`: a slow service, deterministically.
    """

    def __init__(self, upstream: str) -> None:
        self.upstream = upstream
        self.posts: list[tuple[str, str]] = []
        self.held = 0
        self._gate = threading.Event()
        self._gate.set()
        self._lose = threading.Event()
        self._spoil = threading.Event()
        self._lock = threading.Lock()
        relay = self

        class Handler(http.server.BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args: Any) -> None:
                pass

            def _relay(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length") or 0))
                post = self.command == "POST" and self.path.split("?")[0].endswith("/observations")
                key = self.headers.get("Idempotency-Key", "")
                if post and not relay._gate.is_set():
                    with relay._lock:
                        relay.held += 1
                    relay._gate.wait()
                headers = {k: v for k, v in self.headers.items()
                           if k.lower() not in ("host", "content-length", "connection")}
                try:
                    r = httpx.request(self.command, relay.upstream + self.path, content=body, headers=headers,
                                      timeout=60)
                except httpx.TransportError:
                    if post:
                        relay._log(key, "down")
                    self.close_connection = True
                    self.connection.shutdown(socket.SHUT_RDWR)
                    return
                if post and relay._lose.is_set():
                    relay._lose.clear()
                    relay._log(key, "lost")
                    self.close_connection = True
                    self.connection.shutdown(socket.SHUT_RDWR)
                    return
                if post and relay._spoil.is_set():
                    relay._spoil.clear()
                    relay._log(key, "spoilt")
                    page = b"<html><body>502 upstream hiccup</body></html>"
                    self.send_response(200)
                    self.send_header("Content-Type", "text/html")
                    self.send_header("Content-Length", str(len(page)))
                    self.end_headers()
                    self.wfile.write(page)
                    return
                if post:
                    relay._log(key, str(r.status_code))
                self.send_response(r.status_code)
                for k, v in r.headers.items():
                    if k.lower() not in ("content-length", "connection", "transfer-encoding",
                                         "content-encoding", "date", "server"):
                        self.send_header(k, v)
                self.send_header("Content-Length", str(len(r.content)))
                self.end_headers()
                self.wfile.write(r.content)

            do_GET = do_POST = do_PATCH = do_DELETE = _relay

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def _log(self, key: str, outcome: str) -> None:
        with self._lock:
            self.posts.append((key, outcome))

    def hold(self) -> None:
        self._gate.clear()

    def release(self) -> None:
        self._gate.set()

    def lose_next_reply(self) -> None:
        self._lose.set()

    def spoil_next_reply(self) -> None:
        self._spoil.set()

    def close(self) -> None:
        self._gate.set()
        self.server.shutdown()
        self.server.server_close()


# ----------------------------------------------------------------------------------------------- node


class NodeProcess:
    """`cortexloc_node` as a subprocess (`python -m cortexloc_ros`), ended by its PID."""

    def __init__(self, tmp: Path, params: dict[str, Any], name: str = "node", ros_args: tuple[str, ...] = ()
                 ) -> None:
        """`ros_args`: more after `--ros-args` (`--params-file`, `-r __ns:=...`), before the `-p`s."""
        self.log_path = tmp / f"{name}.log"
        args = [sys.executable, "-m", "cortexloc_ros", "--ros-args", *ros_args]
        for k, v in params.items():
            value = "''" if v == "" else json.dumps(v) if not isinstance(v, str) else v
            args += ["-p", f"{k}:={value}"]
        self.args = args
        with self.log_path.open("ab") as log:
            self.proc = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, cwd=REPO)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self) -> int:
        """SIGTERM to its PID (SIGKILL if it has not ended in 20 s); its exit status."""
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.kill(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        return self.proc.returncode


def node_params(url: str, map_id: str, **overrides: Any) -> dict[str, Any]:
    """The tests' node: the probe's topics, reliable subscriptions (the probe publishes reliably, so no
    frame is lost to best effort under load), then `overrides` (dots in names as `__`)."""
    params = {"service_url": url, "map": map_id, "stream": "test/cam", "topics.image": "/cam/image_raw",
              "topics.camera_info": "/cam/camera_info", "topics.odometry": "/odom", "request_timeout": 60.0,
              "queue.size": 100}
    for topic in ("/cam/image_raw", "/cam/image_raw/compressed", "/cam/camera_info", "/odom"):
        params[f"qos_overrides.{topic}.subscription.reliability"] = "reliable"
    params.update({k.replace("__", "."): v for k, v in overrides.items()})
    return params
