"""The real thing: `cortexloc serve` in a subprocess on a free loopback port, a robot driving a loop."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
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


@pytest.fixture
def server(tmp_path):
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("CORTEXLOC_")}
    env.update({"CORTEXLOC_WEIGHTS_DIR": str(tmp_path / "no-weights"), "CORTEXLOC_LOG_FORMAT": "text"})
    log = (tmp_path / "server.log").open("w")
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port),
                             "--data-dir", str(tmp_path / "var")], env=env, stdout=log, stderr=log,
                            cwd=Path(__file__).resolve().parents[2])
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                pytest.fail(f"server exited: {(tmp_path / 'server.log').read_text()[-2000:]}")
            try:
                if call(f"{base}/readyz")[0] == 200:
                    break
            except OSError:
                pass
            time.sleep(0.3)
        else:
            pytest.fail("server not ready within 120 s")
        yield base
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        log.close()


def test_a_looping_route_finds_its_revisit_first(server):
    obs = f"{server}/v1/maps/default/observations?learn=true&top_k=3"
    seqs = {}
    for place in range(6):
        status, body = call(obs, frame(place))
        assert status == 200, body
        seqs[place] = body["seq"]
        assert body["versions"]["weights"] == "random"
    for place in range(3):  # the robot drives the loop again
        status, body = call(obs, frame(place))
        assert status == 200, body
    assert body["matches"][0]["seq"] == seqs[2]
    assert body["matches"][0]["score"] > 0.9
    status, problem = call(obs, b"not an image")
    assert status == 415 and problem["type"] == "urn:cortexloc:problem:unsupported-media-type"
