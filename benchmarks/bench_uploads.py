"""Half-sent uploads against the real service (issue 19 item 2): what they hold, and for how long.

Run: `cortexloc bench uploads [--quick] [--server-cmd CMD] [--env NAME=VALUE ...]`. Writes
benchmarks/results/uploads.json (or `--out`). `--server-cmd` runs another build of the CLI (e.g. the code
before the fix) with the same measurements.

Setup as benchmarks/bench_http.py: `cortexloc serve` in a subprocess, default settings unless `--env`
says otherwise, temporary data directory, random weights. `--uploads` connections (50) each send the
head of an observation post declaring `--declared` bytes (10 MB) and `--sent` of them (9 MB), then
nothing. Measured: the server's RSS before, once every connection sent its part (and each one's answer
so far: none, 503 or 408), then at `--watch` seconds (default: the body deadline plus 10 s) with which
connections the server closed by then, and a small post's latency while they stall.
"""

from __future__ import annotations

import contextlib
import json
import shlex
import socket
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

from benchmarks._common import RESULTS, quick_mode, write_json
from benchmarks.bench_http import Server
from models.evaluation.bench import synthetic_jpegs


def stall(port: int, declared: int, sent: int) -> socket.socket:
    """A connection that sent the head of a post declaring `declared` bytes and `sent` of them."""
    sock = socket.create_connection(("127.0.0.1", port))
    sock.sendall(b"POST /v1/maps/default/observations HTTP/1.1\r\nHost: bench\r\nContent-Type: image/jpeg\r\n"
                 b"Content-Length: %d\r\n\r\n" % declared)
    sock.settimeout(0.5)
    chunk = b"\xff\xd8\xff\xe0" + bytes(2**20 - 4)
    left = sent
    while left > 0:
        try:
            left -= sock.send(chunk[: min(left, len(chunk))])
        except (TimeoutError, BlockingIOError):
            break  # the server stopped reading (it answered already): the rest stays unsent
        except (BrokenPipeError, ConnectionResetError):
            break
    return sock


def answered(sock: socket.socket) -> tuple[int | None, bool]:
    """(status of what the server sent so far or None, whether it closed the connection)."""
    sock.setblocking(False)
    got = b""
    closed = False
    with contextlib.suppress(BlockingIOError, TimeoutError):
        while True:
            try:
                chunk = sock.recv(65536)
            except ConnectionResetError:
                closed = True
                break
            if not chunk:
                closed = True
                break
            got += chunk
    status = int(got.split(b" ", 2)[1]) if got.startswith(b"HTTP/1.1 ") else None
    return status, closed


def tally(socks: list[socket.socket]) -> dict[str, Any]:
    seen = [answered(s) for s in socks]
    statuses: dict[str, int] = {}
    for status, _ in seen:
        statuses[str(status)] = statuses.get(str(status), 0) + 1
    return {"answers": statuses, "closed_by_server": sum(closed for _, closed in seen)}


def main(*, quick: bool, server_cmd: str | None, env: list[str], uploads: int, declared: int, sent: int,
         watch: float | None, out: Path | None) -> None:
    quick = quick_mode(quick)
    uploads = 5 if quick else uploads
    server_env = dict(e.split("=", 1) for e in env)
    deadline_s = float(server_env.get("CORTEXLOC_BODY_TIMEOUT_S", 60.0))
    watch = watch if watch is not None else deadline_s + 10
    command = shlex.split(server_cmd) if server_cmd else None
    small = synthetic_jpegs(1, 640, 480)[0]
    with tempfile.TemporaryDirectory() as tmp:
        server = Server(Path(tmp), server_env, command)
        try:
            server.wait_ready()
            http = httpx.Client(timeout=60)
            assert http.post(f"{server.base}/v1/maps/default/observations", content=small,
                             headers={"Content-Type": "image/jpeg"}).status_code == 200  # warm
            before = server.rss_mib()
            t0 = time.monotonic()
            socks = [stall(server.port, declared, sent) for _ in range(uploads)]
            time.sleep(1.0)
            held = {"rss_mib": server.rss_mib(), "after_s": round(time.monotonic() - t0, 1), **tally(socks)}
            t1 = time.perf_counter()
            r = http.post(f"{server.base}/v1/maps/default/observations", content=small,
                          headers={"Content-Type": "image/jpeg"})
            small_post = {"status": r.status_code, "ms": round((time.perf_counter() - t1) * 1e3, 1)}
            time.sleep(max(watch - (time.monotonic() - t0), 0))
            later = {"rss_mib": server.rss_mib(), "after_s": round(time.monotonic() - t0, 1), **tally(socks)}
            metrics = http.get(f"{server.base}/metrics").text
            for s in socks:
                s.close()
        finally:
            server.stop()
    lines = [ln for ln in metrics.splitlines() if ln.startswith("cortexloc_upload_")]
    result = {"uploads": uploads, "declared_bytes": declared, "sent_bytes": sent, "env": server_env,
              "server_cmd": server_cmd, "rss_mib_before": before, "held": held, "small_post": small_post,
              "later": later, "upload_metrics": lines}
    print(json.dumps(result, indent=2))
    write_json("uploads.json", result, out or RESULTS / "uploads.json")

