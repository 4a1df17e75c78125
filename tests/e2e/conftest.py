"""Helpers for end-to-end tests: `cortexloc serve` as a real subprocess on a free loopback port."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def frame(place: int) -> bytes:
    rng = np.random.default_rng(place)
    img = cv2.resize(rng.integers(0, 256, (12, 16, 3), dtype=np.uint8), (320, 240),
                     interpolation=cv2.INTER_CUBIC)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return buf.tobytes()


def call(url: str, data: bytes | None = None, ctype: str = "image/jpeg") -> tuple[int, dict]:
    req = urllib.request.Request(url, data=data, method="POST" if data is not None else "GET",
                                 headers={"Content-Type": ctype} if data is not None else {})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


class Server:
    """Start, kill and restart `cortexloc serve` on one data directory."""

    def __init__(self, tmp_path: Path, weights_dir: Path | None = None) -> None:
        self.extra_env: dict[str, str] = {}
        self.tmp = tmp_path
        # No AlexNet weights in it; the backbone's ONNX export, stored there by the first server, is
        # shared by the others instead of exported again at every start.
        self.weights_dir = weights_dir or tmp_path / "no-weights"
        self.data_dir = tmp_path / "var"
        self.proc: subprocess.Popen | None = None
        self.base = ""

    def start(self) -> str:
        port = free_port()
        env = {k: v for k, v in os.environ.items() if not k.startswith("CORTEXLOC_")}
        env.update({"CORTEXLOC_WEIGHTS_DIR": str(self.weights_dir), "CORTEXLOC_LOG_FORMAT": "text",
                    **self.extra_env})
        self.log = (self.tmp / "server.log").open("a")
        self.proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port),
                                      "--data-dir", str(self.data_dir)], env=env, stdout=self.log,
                                     stderr=self.log, cwd=Path(__file__).resolve().parents[2])
        self.base = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                pytest.fail(f"server exited: {(self.tmp / 'server.log').read_text()[-2000:]}")
            try:
                if call(f"{self.base}/readyz")[0] == 200:
                    return self.base
            except OSError:
                pass
            time.sleep(0.3)
        pytest.fail("server not ready within 120 s")

    def kill9(self) -> None:
        assert self.proc is not None
        self.proc.kill()  # SIGKILL: no shutdown hook, no flush
        self.proc.wait(timeout=30)
        self.log.close()

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=30)
            self.log.close()


@pytest.fixture(scope="session")
def shared_weights_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("no-weights")


@pytest.fixture
def server_proc(tmp_path, shared_weights_dir) -> Iterator[Server]:
    s = Server(tmp_path, shared_weights_dir)
    try:
        yield s
    finally:
        s.stop()


@pytest.fixture
def server(server_proc):
    yield server_proc.start()




@pytest.fixture
def http():
    """`call(url, data=None, ctype=...) -> (status, json)`."""
    return call


@pytest.fixture
def make_frame():
    """`frame(place) -> JPEG bytes` of a generated place."""
    return frame
