"""`cortexloc ingest`: frames/s and latency in process vs over HTTP, for the same folder of frames.

Run: `cortexloc bench ingest [--frames 50] [--repeats 3] [--quick]` (`make bench`).
Writes benchmarks/results/ingest.json.

Setup: a folder of `--frames` 640x480 synthetic JPEGs (`models.evaluation.bench.synthetic_jpegs`),
learned into a fresh map of the default preset (created before the clock starts) on random seeded AlexNet
weights, one stream, posts one at a time in source order as `cortexloc ingest` does
(`service.ingest.poster.ingest`):

- in process: the app in this process behind httpx's ASGI transport (`in_process_client`);
- over HTTP: `cortexloc serve` in a subprocess on loopback (`remote_client`), default settings.

Reported per mode: the median over `--repeats` runs of frames/s (frames / wall time of the ingest) and of
the runs' client-side median and p95 latency.
"""

from __future__ import annotations

import os
import statistics
import tempfile
from pathlib import Path
from typing import Any

import anyio
import httpx

from benchmarks._common import quick_mode, write_json
from benchmarks.bench_http import Server
from models.evaluation.bench import synthetic_jpegs
from service.ingest import poster
from service.ingest.sources import open_source


async def _runs(client: httpx.AsyncClient, folder: Path, repeats: int, mode: str) -> list[dict[str, Any]]:
    out = []
    for r in range(repeats):
        map_id = f"bench-{mode}-{r}"
        created = await client.post("/v1/maps", json={"map_id": map_id})
        assert created.status_code == 201, created.text
        summary = await poster.ingest(client, open_source(folder), poster.Options(map_id, stream="s"))
        assert summary.errors == 0 and summary.frames == summary.total, summary
        out.append(summary.as_dict())
        print(f"{mode} run {r}: {summary.text()}", flush=True)
        assert (await client.delete(f"/v1/maps/{map_id}")).status_code == 204  # free its memory
    return out


def _medians(runs: list[dict[str, Any]]) -> dict[str, float]:
    return {k: round(statistics.median(r[k] for r in runs), 2)
            for k in ("frames_per_s", "latency_ms_median", "latency_ms_p95")}


def main(*, frames: int, repeats: int, quick: bool) -> None:
    frames, repeats = (10, 1) if quick_mode(quick) else (frames, repeats)
    from service.settings import Settings

    with tempfile.TemporaryDirectory(prefix="cortexloc-bench-ingest-") as tmp_s:
        tmp = Path(tmp_s)
        os.environ["CORTEXLOC_WEIGHTS_DIR"] = str(tmp / "no-weights")  # random weights, as the server's
        folder = tmp / "frames"
        folder.mkdir()
        for i, jpg in enumerate(synthetic_jpegs(frames)):
            (folder / f"{i:05d}.jpg").write_bytes(jpg)

        async def in_process() -> list[dict[str, Any]]:
            settings = Settings(data_dir=tmp / "in-process", log_level="WARNING")
            async with poster.in_process_client(settings) as client:
                return await _runs(client, folder, repeats, "in-process")

        inproc = anyio.run(in_process)
        (tmp / "http").mkdir()
        server = Server(tmp / "http")
        try:
            server.wait_ready()

            async def over_http() -> list[dict[str, Any]]:
                async with poster.remote_client(server.base) as client:
                    return await _runs(client, folder, repeats, "http")

            http = anyio.run(over_http)
        finally:
            server.stop()
    result = {"frames": frames, "repeats": repeats, "in_process": _medians(inproc), "http": _medians(http),
              "runs": {"in_process": inproc, "http": http}}
    path = write_json("ingest.json", result)
    print(f"ingest of {frames} frames, medians of {repeats}: in process {result['in_process']}, "
          f"over HTTP {result['http']} -> {path}")

