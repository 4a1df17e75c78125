"""One map's flood against another map's robot, through the real service (docs/design/service.md §6).

Run: `cortexloc bench fairness [--quick] [--server-cmd CMD] [--env NAME=VALUE ...]`. Writes
benchmarks/results/fairness.json (or `--out`). `--server-cmd` runs another build of the CLI (e.g. the code
before the encoder's shares) with the same measurements.

Setup as benchmarks/bench_http.py: `cortexloc serve` in a subprocess, default settings unless `--env`
says otherwise, a temporary data directory, random weights. Two maps: `flood` and `robot`.
- **Alone**: the robot posts `--frames` 640x480 JPEGs to its map one at a time, `--gap` seconds apart,
  with nothing else running: its latency with the service to itself.
- **Flooded**: `--clients` connections post `--side` x `--side` 8-bit RGB PNGs to `flood` as fast as they
  are answered (a burst of frames at the pixel cap: each decodes all its 25 million pixels, the file
  itself 117 kB for 5,000 px), and the robot posts as before once the flood has filled the
  encoder. `--noise --side 1800`: the flood's bodies are 9.7 MB of noise instead, near the upload limit,
  so that it fills the in-flight upload budget too. `--keyframes orb` (or `sift`): both maps take local
  features from every frame (the map option `keyframes`), so the flood fills the keyframe extractions
  (`CORTEXLOC_MAX_EXTRACTIONS`) as well as the encoder.

Measured: the robot's replies by status and its latency (median, p95, max) in both phases, and the
flood's replies by status. The question is whether one map's client can keep another map's robot
waiting or refused.
"""

from __future__ import annotations

import asyncio
import json
import shlex
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np

from benchmarks._common import RESULTS, quick_mode, write_json
from benchmarks.bench_http import Server
from models.evaluation.bench import synthetic_jpegs


def heavy_png(side: int, noise: bool = False) -> bytes:
    """A `side` x `side` 8-bit RGB PNG that compresses well (gradients and a coarse pattern) but decodes
    every pixel: small on the wire, costly in the decoder; with `noise`, of seeded noise instead, which
    does not compress (side² x 3 bytes on the wire: 1,800 px is 9.7 MB, near the 10 MiB upload limit)."""
    if noise:
        img = np.random.default_rng(0).integers(0, 256, (side, side, 3), dtype=np.uint8)
    else:
        y, x = np.mgrid[0:side, 0:side]
        img = np.stack([x * 255 // side, y * 255 // side, (x // 7 + y // 5) % 256], axis=-1).astype(np.uint8)
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    assert ok
    return buf.tobytes()


def stats(ms: list[float]) -> dict[str, float]:
    if not ms:
        return {}
    a = np.asarray(ms)
    return {"p50": round(float(np.percentile(a, 50)), 1), "p95": round(float(np.percentile(a, 95)), 1),
            "max": round(float(a.max()), 1)}


async def robot(http: httpx.AsyncClient, base: str, frames: list[bytes], gap: float) -> dict[str, Any]:
    """The robot's frames one at a time to its map: statuses and the latency of its 200s."""
    statuses: dict[str, int] = {}
    ms: list[float] = []
    for i, body in enumerate(frames):
        t0 = time.perf_counter()
        try:
            r = await http.post(f"{base}/v1/maps/robot/observations", params={"stream": "robot"},
                                content=body, headers={"Content-Type": "image/jpeg"})
            status = str(r.status_code)
        except httpx.TransportError:  # refused before its body and closed while it was sent
            status = "closed"
        dt = (time.perf_counter() - t0) * 1e3
        statuses[status] = statuses.get(status, 0) + 1
        if status == "200":
            ms.append(dt)
        if i + 1 < len(frames):
            await asyncio.sleep(gap)
    return {"statuses": statuses, "latency_ms": stats(ms)}


async def flooded(base: str, frames: list[bytes], gap: float, clients: int, png: bytes) -> dict[str, Any]:
    stop = asyncio.Event()
    flood: dict[str, int] = {}

    async def flooder(http: httpx.AsyncClient, i: int) -> None:
        while not stop.is_set():
            try:
                r = await http.post(f"{base}/v1/maps/flood/observations", params={"stream": f"f{i}"},
                                    content=png, headers={"Content-Type": "image/png"})
                status = str(r.status_code)
            except httpx.TransportError:  # a 503 before the body, its connection closed while sending
                status = "closed"
            flood[status] = flood.get(status, 0) + 1

    limits = httpx.Limits(max_connections=clients + 4, max_keepalive_connections=clients + 4)
    async with httpx.AsyncClient(limits=limits, timeout=300) as http:
        tasks = [asyncio.create_task(flooder(http, i)) for i in range(clients)]
        await asyncio.sleep(3.0)  # the flood fills the encoder
        t0 = time.perf_counter()
        mine = await robot(http, base, frames, gap)
        wall = time.perf_counter() - t0
        stop.set()
        await asyncio.gather(*tasks)
    return {"robot": mine, "flood_statuses": flood, "robot_wall_s": round(wall, 1)}


def main(*, quick: bool, server_cmd: str | None, env: list[str], frames: int, gap: float, clients: int,
         side: int, noise: bool, out: Path | None, keyframes: str | None = None) -> None:
    quick = quick_mode(quick)
    frames, clients, side = (4, 4, 1500) if quick else (frames, clients, side)
    server_env = dict(e.split("=", 1) for e in env)
    command = shlex.split(server_cmd) if server_cmd else None
    jpegs = synthetic_jpegs(frames, 640, 480, seed=3)
    png = heavy_png(side, noise)
    with tempfile.TemporaryDirectory() as tmp:
        server = Server(Path(tmp), server_env, command)
        try:
            server.wait_ready()
            with httpx.Client(timeout=60) as http:
                extra = {} if keyframes is None else {"keyframes": {"features": keyframes}}
                for m in ("flood", "robot"):
                    made = http.post(f"{server.base}/v1/maps", json={"map_id": m, **extra})
                    assert made.status_code == 201, made.text
                # warm: the encoder, both maps' writers, a PNG at the size
                for m, body, ctype in (("robot", jpegs[0], "image/jpeg"), ("flood", png, "image/png")):
                    r = http.post(f"{server.base}/v1/maps/{m}/observations", params={"stream": "warm"},
                                  content=body, headers={"Content-Type": ctype})
                    assert r.status_code == 200, r.text

            async def alone() -> dict[str, Any]:
                async with httpx.AsyncClient(timeout=300) as http:
                    return await robot(http, server.base, jpegs, gap)

            result: dict[str, Any] = {"alone": asyncio.run(alone())}
            result["flooded"] = asyncio.run(flooded(server.base, jpegs, gap, clients, png))
        finally:
            server.stop()
    result = {"frames": frames, "gap_s": gap, "clients": clients, "side": side, "noise": noise,
              "keyframes": keyframes, "png_bytes": len(png),
              "env": server_env, "server_cmd": server_cmd, **result}
    print(json.dumps(result, indent=2))
    write_json("fairness.json", result, out or RESULTS / "fairness.json")
