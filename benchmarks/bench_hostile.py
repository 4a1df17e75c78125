"""Hostile inputs against the real service (issue 11): how fast bombs are refused, what a normal frame
waits meanwhile, and what stalled snapshot downloads hold.

Run: `cortexloc bench hostile [--quick] [--server-cmd CMD]`. Writes
benchmarks/results/hostile.json. `--server-cmd` runs another build of the CLI (e.g. the code before the
fix) with the same measurements.

Setup as benchmarks/bench_http.py: `cortexloc serve` in a subprocess, default settings (one encoder
worker), temporary data directory, random weights. Measured, medians over repeats:

- `bombs`: status, problem type and latency of each hostile image: the issue's PNG (100x100, ~9.6 GB of
  deflated zeros in 9.8 MB), the same data split over 10,000 IDAT chunks, an interlaced one, one whose
  compressed size fits its 2000x2000 raster (only the bounded inflate can tell), a 5000x5000
  progressive JPEG with 4,000 empty scans (300 kB), and a flat 5000x5000 16-bit RGBA PNG (a well-formed
  file at the pixel cap whose raster is 200 MB: the decode costs by the bytes);
- `normal_frame_ms`: a 640x480 JPEG posted alone, and while two clients post the issue's bomb back to
  back (p50, p95, max);
- `downloads`: time to the first byte of a snapshot download, and the bytes the server holds in
  deleted-but-open files (per-request copies) while 4 clients stall after the first chunk, then after
  they go away;
- `listings`: a localising frame on a map of `rows` learned rows (1,500; 200 with --quick), posted alone
  and while 6 clients ask its repair listing nonstop (`GET /v1/maps/{id}/repair`, which replays the
  whole log: docs/design/service.md §1.2 "Repair"), with the listings answered meanwhile.
"""

from __future__ import annotations

import asyncio
import os
import re
import shlex
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np

from benchmarks._common import RESULTS, quick_mode, write_json
from benchmarks.bench_http import Server
from models.evaluation.bench import deflated_zeros, make_png, png_bomb, synthetic_jpegs

ISSUE_BOMB_BYTES = 9_600_000_000  # zeros inflated from the issue's 9.8 MB PNG


def jpeg_scan_flood(side: int = 5000, extra_scans: int = 4000) -> bytes:
    """A flat progressive JPEG whose last (empty) scan is repeated: each costs a pass over every block."""
    flat = np.full((side, side, 3), 128, np.uint8)
    ok, buf = cv2.imencode(".jpg", flat, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
    assert ok
    data = buf.tobytes()
    last = data[[m.start() for m in re.finditer(rb"\xff\xda", data)][-1]:-2]
    return data[:-2] + last * extra_scans + b"\xff\xd9"


def hostile_images(quick: bool) -> dict[str, bytes]:
    import zlib

    zeros = 600_000_000 if quick else ISSUE_BOMB_BYTES
    interlaced = make_png(100, 100, zlib.compress(bytes(4_000_000), 9), interlace=1)
    return {"png_100x100_issue_bomb": png_bomb(100, 100, zeros),
            "png_100x100_10000_idat_chunks": png_bomb(100, 100, zeros, idat_chunks=10_000),
            "png_100x100_interlaced_4MB": interlaced,
            "png_2000x2000_fits_raster": png_bomb(2000, 2000, zeros),
            "jpeg_5000x5000_4000_scans": jpeg_scan_flood(5000, 300 if quick else 4000),
            # 16-bit RGBA at the pixel cap, all zeros: 200 MB of raster in ~200 kB, a legitimate PNG
            "png_5000x5000_rgba16_flat": make_png(5000, 5000, deflated_zeros(5000 * (1 + 5000 * 8)),
                                                  colour=6, depth=16)}


def post(http: httpx.Client, base: str, body: bytes, ctype: str) -> tuple[int, str, float]:
    t0 = time.perf_counter()
    r = http.post(f"{base}/v1/maps/default/observations", content=body, headers={"Content-Type": ctype},
                  params={"learn": "false", "top_k": 1})
    ms = (time.perf_counter() - t0) * 1e3
    kind = r.json().get("type", "") if r.headers.get("content-type", "").endswith("json") else ""
    return r.status_code, kind.removeprefix("urn:cortexloc:problem:"), ms


def stats(ms: list[float]) -> dict[str, float]:
    a = np.asarray(ms)
    return {"n": len(ms), "p50": float(np.median(a)), "p95": float(np.percentile(a, 95)),
            "max": float(a.max())}


async def frames_during_bombs(base: str, frame: bytes, bomb: bytes, n: int) -> list[float]:
    """Latencies of `n` normal frames posted one after another while two clients post `bomb` nonstop."""
    done = False
    async with httpx.AsyncClient(timeout=600) as http:
        async def bomber() -> None:
            while not done:
                await http.post(f"{base}/v1/maps/default/observations", content=bomb,
                                headers={"Content-Type": "image/png"})

        tasks = [asyncio.create_task(bomber()) for _ in range(2)]
        await asyncio.sleep(1.0)  # the bombs are in flight
        out = []
        for _ in range(n):
            t0 = time.perf_counter()
            r = await http.post(f"{base}/v1/maps/default/observations", content=frame,
                                headers={"Content-Type": "image/jpeg"}, params={"learn": "false", "top_k": 1})
            out.append((time.perf_counter() - t0) * 1e3)
            assert r.status_code == 200, r.text
        done = True
        await asyncio.gather(*tasks, return_exceptions=True)
    return out


async def frames_during_listings(base: str, frame: bytes, rows: int, n: int, clients: int = 6
                                 ) -> dict[str, Any]:
    """Latencies of `n` localising frames on a map of `rows` learned rows, alone and while `clients` ask
    its repair listing nonstop."""
    done = False
    listed = 0
    async with httpx.AsyncClient(base_url=base, timeout=600) as http:
        assert (await http.post("/v1/maps", json={"map_id": "listed"})).status_code == 201
        for _ in range(rows):
            r = await http.post("/v1/maps/listed/observations", content=frame, params={"stream": "s"},
                                headers={"Content-Type": "image/jpeg"})
            assert r.status_code == 200, r.text

        async def timed() -> list[float]:
            out = []
            for _ in range(n):
                t0 = time.perf_counter()
                r = await http.post("/v1/maps/listed/observations", content=frame, headers={
                    "Content-Type": "image/jpeg"}, params={"learn": "false", "stream": "q", "top_k": 1})
                out.append((time.perf_counter() - t0) * 1e3)
                assert r.status_code == 200, r.text
            return out

        async def lister() -> None:
            nonlocal listed
            while not done:
                assert (await http.get("/v1/maps/listed/repair")).status_code == 200
                listed += 1

        alone = await timed()
        tasks = [asyncio.create_task(lister()) for _ in range(clients)]
        await asyncio.sleep(1.0)  # the listings are in flight
        during = await timed()
        done = True
        await asyncio.gather(*tasks)
    return {"rows": rows, "clients": clients, "alone_ms": stats(alone), "while_listed_ms": stats(during),
            "listings_answered": listed}


def deleted_open_bytes(pid: int) -> tuple[int, int]:
    """(count, bytes) of deleted files the process still holds open."""
    n = size = 0
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
            if target.endswith("(deleted)"):
                n += 1
                size += os.stat(f"/proc/{pid}/fd/{fd}").st_size
        except OSError:
            continue
    return n, size


def downloads(server: Server, stalled: int) -> dict[str, Any]:
    base = server.base
    sid = httpx.post(f"{base}/v1/maps/default/snapshots", timeout=120).json()["snapshot_id"]
    url = f"{base}/v1/maps/default/snapshots/{sid}/download"
    t0 = time.perf_counter()
    with httpx.stream("GET", url, timeout=600) as r:
        chunks = r.iter_raw(1 << 16)
        first = next(chunks)
        ttfb_ms = (time.perf_counter() - t0) * 1e3
        total = len(first) + sum(len(c) for c in chunks)
    full_ms = (time.perf_counter() - t0) * 1e3
    clients = [httpx.Client(timeout=600) for _ in range(stalled)]
    streams = []
    for c in clients:
        s = c.stream("GET", url)
        r = s.__enter__()
        next(r.iter_raw(65536))  # read the first chunk, then stop reading
        streams.append(s)
    time.sleep(2.0)
    held_n, held_bytes = deleted_open_bytes(server.proc.pid)
    for s, c in zip(streams, clients, strict=True):
        s.__exit__(None, None, None)
        c.close()
    time.sleep(2.0)
    after_n, after_bytes = deleted_open_bytes(server.proc.pid)
    return {"tar_bytes": total, "ttfb_ms": ttfb_ms, "full_download_ms": full_ms, "stalled_clients": stalled,
            "deleted_open_files_while_stalled": held_n, "deleted_open_bytes_while_stalled": held_bytes,
            "deleted_open_files_after_abort": after_n, "deleted_open_bytes_after_abort": after_bytes}


def main(*, quick: bool, repeats: int | None, server_cmd: str | None, skip: list[str],
         frames_during: int | None, out: Path | None) -> None:
    if out is None:
        out = RESULTS / "hostile.json"
    quick = quick_mode(quick)
    repeats = repeats or (1 if quick else 3)
    frame = synthetic_jpegs(1, seed=3)[0]
    images = {k: v for k, v in hostile_images(quick).items() if k not in skip}
    tmp = Path(tempfile.mkdtemp(prefix="cortexloc-bench-hostile-"))
    server = Server(tmp, command=shlex.split(server_cmd) if server_cmd else None)
    result: dict[str, Any] = {"config": {"server_cmd": server_cmd or "cortexloc", "quick": quick,
                                      "repeats": repeats}}
    try:
        server.wait_ready()
        with httpx.Client(timeout=600) as http:
            for _ in range(10):  # warm-up, and rows for the snapshot below
                http.post(f"{server.base}/v1/maps/default/observations", content=frame,
                          headers={"Content-Type": "image/jpeg"})
            alone = [post(http, server.base, frame, "image/jpeg")[2] for _ in range(5 if quick else 20)]
            bombs = {}
            for name, body in images.items():
                ctype = "image/jpeg" if name.startswith("jpeg") else "image/png"
                runs = [post(http, server.base, body, ctype) for _ in range(repeats)]
                bombs[name] = {"bytes": len(body), "status": runs[0][0], "type": runs[0][1],
                               "ms": stats([ms for _, _, ms in runs])}
                print(f"{name}: {len(body)} bytes -> {runs[0][0]} {runs[0][1]}, "
                      f"median {bombs[name]['ms']['p50']:.1f} ms", flush=True)
        during = asyncio.run(frames_during_bombs(server.base, frame, images["png_100x100_issue_bomb"],
                                                 frames_during or (3 if quick else 10)))
        result["bombs"] = bombs
        result["normal_frame_ms"] = {"alone": stats(alone), "while_bombs_posted": stats(during)}
        print(f"normal frame: alone p50 {np.median(alone):.1f} ms; while 2 clients post the issue's bomb "
              f"p50 {np.median(during):.1f} ms, max {max(during):.1f} ms", flush=True)
        result["downloads"] = downloads(server, 4)
        d = result["downloads"]
        print(f"download: {d['tar_bytes']} bytes, first byte {d['ttfb_ms']:.0f} ms, whole "
              f"{d['full_download_ms']:.0f} ms; 4 stalled clients: "
              f"{d['deleted_open_files_while_stalled']} deleted files open, "
              f"{d['deleted_open_bytes_while_stalled']} bytes; after they left: "
              f"{d['deleted_open_bytes_after_abort']} bytes", flush=True)
        result["listings"] = asyncio.run(frames_during_listings(server.base, frame, 200 if quick else 1500,
                                                                frames_during or (10 if quick else 40)))
        li = result["listings"]
        print(f"localising frame on a {li['rows']}-row map: alone p50 {li['alone_ms']['p50']:.1f} ms; "
              f"while {li['clients']} clients list its repair p50 {li['while_listed_ms']['p50']:.1f} ms "
              f"({li['listings_answered']} listings answered)", flush=True)
    finally:
        server.stop()
        shutil.rmtree(tmp, ignore_errors=True)
    write_json(out.name, result, out)

