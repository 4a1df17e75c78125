"""The process-wide memory budget against the real service (issue 19 item 1): server RSS while maps are
created, and at the next start.

Run: `cortexloc bench memory [--quick] [--budget BYTES] [--server-cmd CMD] [--out NAME]`.
Writes benchmarks/results/<NAME>.json (default `memory`). `--server-cmd` runs another build of the CLI
(e.g. the code before the budget) with the same requests.

Setup as benchmarks/bench_http.py: `cortexloc serve` in a subprocess, random weights, the default
backbone, a temporary data directory. Two scenarios, each on a fresh server:

- `big`: `--big` maps created with the issue's TM (`cellsPerColumn` 16, `maxSegmentsPerCell` 64,
  `maxSynapsesPerSegment` 64: 2.03 GB each), RSS after each request;
- `many`: up to `--many` maps created with the defaults, one learned frame each, RSS after each; then
  the server is restarted on the same data directory (with `--restart-budget`, e.g. a smaller
  container) and the RSS and the maps left closed are read.

Each request's status (and problem type) is recorded; a scenario stops at its first refusal.

`index`, in process: the budget's per-row index estimate
(`service.maps.runtime.budget.index_row_bytes`) beside what `InvertedIndex.nbytes()` measures with N
random rows of the default map's 308 winner cells.
"""

from __future__ import annotations

import shlex
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from benchmarks._common import quick_mode, write_json
from benchmarks.bench_http import Server
from models.evaluation.bench import synthetic_jpegs
from models.localisation import InvertedIndex
from service.maps.config import MapOptions, resolve
from service.maps.runtime.budget import index_row_bytes
from service.maps.states import serving

BIG_TM = {"cellsPerColumn": 16, "maxSegmentsPerCell": 64, "maxSynapsesPerSegment": 64}


def status(r: httpx.Response) -> str:
    kind = r.json().get("type", "") if r.headers.get("content-type", "").endswith("json") else ""
    return f"{r.status_code} {kind.removeprefix('urn:cortexloc:problem:')}".strip()


def scenario(tmp: Path, env: dict[str, str], command: list[str] | None, n: int, body: dict[str, Any],
             frame: bytes | None) -> dict[str, Any]:
    """Create up to `n` maps with `body` (posting `frame` to each when given); RSS after each."""
    server = Server(tmp, env, command)
    out: dict[str, Any] = {"steps": []}
    try:
        server.wait_ready()
        out["rss_start_mib"] = server.rss_mib()
        with httpx.Client(timeout=600) as http:
            for i in range(n):
                r = http.post(f"{server.base}/v1/maps", json={"map_id": f"m{i}", **body})
                step = {"map": f"m{i}", "create": status(r)}
                if r.status_code == 201 and frame is not None:
                    step["post"] = status(http.post(f"{server.base}/v1/maps/m{i}/observations",
                                                    content=frame, headers={"Content-Type": "image/jpeg"}))
                step["rss_mib"] = server.rss_mib()
                out["steps"].append(step)
                print(step, flush=True)
                if r.status_code != 201:
                    break
            memory = http.get(f"{server.base}/v1/memory")
            if memory.status_code == 200:
                out["budget"] = {k: memory.json()[k] for k in ("total_bytes", "source", "used_bytes")}
    finally:
        server.stop()
    out["maps_created"] = sum(s["create"].startswith("201") for s in out["steps"])
    out["rss_end_mib"] = out["steps"][-1]["rss_mib"] if out["steps"] else out.get("rss_start_mib")
    return out


def restart(tmp: Path, env: dict[str, str], command: list[str] | None) -> dict[str, Any]:
    """Start again on `tmp`'s data directory: RSS when ready, and the maps left closed."""
    server = Server(tmp, env, command)
    try:
        t0 = time.perf_counter()
        server.wait_ready(timeout=1800)
        out: dict[str, Any] = {"ready_s": round(time.perf_counter() - t0, 1), "rss_mib": server.rss_mib()}
        maps = httpx.get(f"{server.base}/v1/maps", timeout=600).json()["maps"]
        out["ready_maps"] = sum(serving(m["state"]).learns for m in maps)
        out["closed"] = {m["map_id"]: m["state_reason"] for m in maps if not serving(m["state"]).learns}
    finally:
        server.stop()
    return out


def index_estimate(sizes: list[int]) -> list[dict[str, float]]:
    """Measured index bytes per row against the budget's estimate, for the default map's rows."""
    config = resolve(MapOptions(preset="cortexloc-default", backbone="efficientnet-lite0-s5"),
                     default_preset="cortexloc-default", default_backbone="efficientnet-lite0-s5")
    params = config.stored()
    cells = int(params["tm"]["columnDimensions"]) * int(params["tm"]["cellsPerColumn"])
    rng = np.random.default_rng(0)
    out = []
    for n in sizes:
        index = InvertedIndex(cells, 10**6)
        for i in range(n):
            index.add(i + 1, np.sort(rng.choice(cells, 308, replace=False)), "robot1")
        index.rank(np.sort(rng.choice(cells, 308, replace=False)), 10)  # its scratch, sized to the rows
        out.append({"rows": n, "measured_bytes_per_row": round(index.nbytes() / n, 1),
                    "estimate_bytes_per_row": index_row_bytes(config)})
        print(out[-1], flush=True)
    return out


def main(*, quick: bool, budget: int | None, big: int, many: int, restart_budget: int | None,
         server_cmd: str | None, out: str) -> None:
    quick = quick_mode(quick)
    command = shlex.split(server_cmd) if server_cmd else None
    env = {} if budget is None else {"CORTEXLOC_MEMORY_BUDGET_BYTES": str(budget)}
    frame = synthetic_jpegs(1, 640, 480)[0]
    result: dict[str, Any] = {"budget_setting": budget, "server_cmd": server_cmd}
    result["index"] = index_estimate([1000] if quick else [1000, 10_000, 50_000])
    with tempfile.TemporaryDirectory() as d:
        result["big"] = scenario(Path(d), env, command, 1 if quick else big, {"tm": BIG_TM}, None)
    with tempfile.TemporaryDirectory() as d:
        result["many"] = scenario(Path(d), env, command, 3 if quick else many, {}, frame)
        again = env if restart_budget is None else {
            "CORTEXLOC_MEMORY_BUDGET_BYTES": str(restart_budget)}
        result["many_restart"] = restart(Path(d), again, command)
    write_json(f"{out}.json", result)
    print({k: result[k] for k in ("big", "many_restart")})

