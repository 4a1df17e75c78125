"""The Ray Serve scale-out's per-request cost against the single process, side by side in one run.

Run: `cortexloc bench scaleout [--requests 60] [--clients 8] [--quick]` (`make bench`; skipped,
with its reason in the JSON, when the `ray` extra is not installed). Writes benchmarks/results/scaleout.json.

Setup: both services up at once on loopback, on the same settings (the service defaults: the default
backbone, EfficientNet-Lite0 stage 5, on ONNX Runtime; no AlexNet weights; one ONNX export shared by
every process): `cortexloc serve` (one uvicorn worker) and `cortexloc serve --ray` on a local Ray cluster
(`ray start --head`, 4 logical CPUs, 80 MB object store, no dashboard; 1 encoder replica, 2 shards,
the ingress). Each gets a map `bench` with the default preset (on one shard of the Ray path). Frames
are 640x480 synthetic JPEGs (`models.evaluation.bench.synthetic_jpegs`).

Measured, in alternating rounds (single, Ray, single, Ray, ...) so that a change of the machine's load
falls on both:

- one client, one request at a time: `learn=true` posts (decode, encode, TM, ranking, durable commit)
  and `GET /v1/maps/bench` (no encoder, no writer: the forwarding alone): median and p95 latency, and
  the Ray path's extra milliseconds per request (median of the Ray path minus median of the single
  process);
- `--clients` robots at once (each its own stream), posting `learn=true`: images/s of each path;
- after the runs, the resident memory of the single process and of the whole Ray cluster, and a
  failover: the replica of the shard owning `bench` killed with SIGKILL, the seconds until the map is
  served again (Ray's replacement replica recovered it) and the 503s answered meanwhile; then
  `cortexloc shards move bench --to <the other shard>`: the seconds the move took (the map unavailable)
  and the command's wall time (its Ray client start included).

On the 2 shared cores of the development machine the encoder is CPU-bound: a second encoder replica
would share the same cores with the first, the shards and the ingress, so replica scaling is not
measured here (docs/scaling.md says what a larger machine needs).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from benchmarks._common import ROOT, quick_mode, write_json
from models.evaluation.bench import synthetic_jpegs


def _stats(ms: list[float]) -> dict[str, float]:
    a = np.asarray(ms)
    return {"n": int(a.size), "p50_ms": round(float(np.median(a)), 2),
            "p95_ms": round(float(np.percentile(a, 95)), 2), "mean_ms": round(float(a.mean()), 2)}


def tree_rss_mib(root: int) -> dict[str, float]:
    """Resident MiB of `root` and every process below it, by command (one /proc walk; {} without /proc)."""
    parent: dict[int, int] = {}
    for d in Path("/proc").glob("[0-9]*"):
        try:
            parent[int(d.name)] = int(d.joinpath("stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
    tree, grew = {root}, True
    while grew:
        more = {p for p, pp in parent.items() if pp in tree} - tree
        tree |= more
        grew = bool(more)
    out: dict[str, float] = {}
    for p in tree:
        try:
            name = Path(f"/proc/{p}/cmdline").read_bytes().split(b"\0")[0].decode(errors="replace")
            rss = next(int(line.split()[1]) for line in Path(f"/proc/{p}/status").read_text().splitlines()
                       if line.startswith("VmRSS:"))
        except (OSError, StopIteration, ValueError):
            continue
        key = name if name.startswith("ray::") else Path(name).name
        out[key] = round(out.get(key, 0.0) + rss / 1024, 1)
    return out


def _sequential(base: str, frames: list[bytes], n: int, stream: str) -> dict[str, list[float]]:
    """`n` learn posts, then `n` map reads, one at a time; wall-clock ms of each."""
    out: dict[str, list[float]] = {"post": [], "get": []}
    with httpx.Client(base_url=base, timeout=120) as c:
        for i in range(n):
            t0 = time.perf_counter()
            r = c.post("/v1/maps/bench/observations", content=frames[i % len(frames)],
                       params={"learn": "true", "stream": stream, "top_k": 5},
                       headers={"Content-Type": "image/jpeg"})
            out["post"].append((time.perf_counter() - t0) * 1e3)
            r.raise_for_status()
        for _ in range(n):
            t0 = time.perf_counter()
            c.get("/v1/maps/bench").raise_for_status()
            out["get"].append((time.perf_counter() - t0) * 1e3)
    return out


def _concurrent(base: str, frames: list[bytes], clients: int, per_client: int, tag: str) -> float:
    """Images/s of `clients` robots posting `per_client` frames each."""
    done: list[int] = []

    def robot(k: int) -> None:
        with httpx.Client(base_url=base, timeout=300) as c:
            for i in range(per_client):
                r = c.post("/v1/maps/bench/observations", content=frames[(i + k) % len(frames)],
                           params={"learn": "true", "stream": f"{tag}-{k}", "top_k": 5},
                           headers={"Content-Type": "image/jpeg"})
                done.append(r.status_code == 200)

    threads = [threading.Thread(target=robot, args=(k,)) for k in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return sum(done) / (time.perf_counter() - t0)


def _failover(cluster: Any, base: str) -> dict[str, Any]:
    """SIGKILL the replica of the shard that owns `bench`, then read the map once every 0.2 s: the
    seconds until it is served again (by Ray's replacement replica, which recovered it) and what the
    reads got meanwhile (503s while the ingress knows the shard down; a read that Ray queued for the
    replacement waits instead)."""
    shard = cluster.routes()["bench"][0]
    pid = cluster.pids(shard)[shard]
    t0 = time.perf_counter()
    os.kill(pid, signal.SIGKILL)
    statuses: list[int] = []
    while time.perf_counter() - t0 < 600:
        t1 = time.perf_counter()
        r = httpx.get(f"{base}/v1/maps/bench", timeout=300)
        statuses.append(r.status_code)
        if r.status_code == 200:
            return {"shard": shard, "served_again_s": round(time.perf_counter() - t0, 2),
                    "longest_read_s": round(time.perf_counter() - t1, 2), "reads": len(statuses),
                    "reads_503": statuses.count(503), "observations": r.json()["observations"],
                    "new_pid": cluster.pids(shard)[shard] != pid}
        time.sleep(0.2)
    raise RuntimeError("the killed shard was not served again within 600 s")


def _move(cluster: Any) -> dict[str, Any]:
    """`cortexloc shards move bench --to <the other shard>`: its own timing (drain, snapshot, download,
    import, recovery, switch) and the command's wall time."""
    shard = cluster.routes()["bench"][0]
    target = "shard-1" if shard == "shard-0" else "shard-0"
    t0 = time.perf_counter()
    done = cluster.cli("shards", "move", "bench", "--to", target, "--address", cluster.address)
    if done.returncode != 0:
        raise RuntimeError(done.stderr[-2000:])
    import json

    return {**json.loads(done.stdout.strip().splitlines()[-1]),
            "command_s": round(time.perf_counter() - t0, 2)}


def _single(tmp: Path, env: dict[str, str]) -> tuple[subprocess.Popen, str]:
    from tests.e2e.scaleout_cluster import free_port

    port = free_port()
    log = (tmp / "single.log").open("ab")
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--data-dir",
                             str(tmp / "single")], env=env, cwd=ROOT, stdout=log, stderr=log)
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError((tmp / "single.log").read_text()[-2000:])
        try:
            if httpx.get(f"{base}/readyz", timeout=5).status_code == 200:
                return proc, base
        except httpx.HTTPError:
            pass
        time.sleep(0.5)
    raise RuntimeError("the single process was not ready in 300 s")


def run(requests: int, clients: int, rounds: int) -> dict[str, Any]:
    from tests.e2e.scaleout_cluster import RayCluster

    tmp = Path(tempfile.mkdtemp(prefix="bench-scaleout-"))
    env = {"CORTEXLOC_WEIGHTS_DIR": str(tmp / "no-weights"), "CORTEXLOC_LOG_FORMAT": "text",
           "CORTEXLOC_LOG_LEVEL": "WARNING"}
    cluster = RayCluster(tmp, env)
    single = None
    try:
        single, single_base = _single(tmp, {**cluster.env})  # builds the ONNX export the replicas reuse
        cluster.start()
        t0 = time.perf_counter()
        ray_base = cluster.serve(shards=2, encoder_replicas=1, timeout=600)
        ray_start_s = time.perf_counter() - t0
        bases = {"single": single_base, "ray": ray_base}
        for base in bases.values():
            httpx.post(f"{base}/v1/maps", json={"map_id": "bench"}, timeout=120).raise_for_status()
        frames = synthetic_jpegs(16)
        for path, base in bases.items():  # warm-up: first requests compile and allocate
            _sequential(base, frames, 5, f"warm-{path}")
        seq: dict[str, dict[str, list[float]]] = {p: {"post": [], "get": []} for p in bases}
        rates: dict[str, list[float]] = {p: [] for p in bases}
        for r in range(rounds):
            for path, base in bases.items():
                got = _sequential(base, frames, requests // rounds, f"seq-{r}")
                for k, v in got.items():
                    seq[path][k] += v
                rates[path].append(_concurrent(base, frames, clients, max(2, requests // (rounds * clients)),
                                               f"c{r}"))
        out: dict[str, Any] = {"ray_start_s": round(ray_start_s, 1), "requests": requests, "clients": clients,
                               "rounds": rounds, "frame": "640x480 JPEG", "paths": {}}
        for path in bases:
            out["paths"][path] = {"post": _stats(seq[path]["post"]), "get": _stats(seq[path]["get"]),
                                  "images_per_s": [round(x, 2) for x in rates[path]],
                                  "images_per_s_median": round(float(np.median(rates[path])), 2)}
        out["failover"] = _failover(cluster, ray_base)
        out["move"] = _move(cluster)
        # Memory after the runs: the single process, and the whole Ray cluster (head, workers, replicas).
        assert cluster.head is not None
        ray_rss = tree_rss_mib(cluster.head.pid)
        out["rss_mib"] = {"single": sum(tree_rss_mib(single.pid).values()),
                          "ray_total": round(sum(ray_rss.values()), 1), "ray_by_process": ray_rss}
        s, ray = out["paths"]["single"], out["paths"]["ray"]
        out["ray_extra_ms"] = {"post_p50": round(ray["post"]["p50_ms"] - s["post"]["p50_ms"], 2),
                               "get_p50": round(ray["get"]["p50_ms"] - s["get"]["p50_ms"], 2)}
        out["ray_over_single"] = {
            "post_p50": round(ray["post"]["p50_ms"] / s["post"]["p50_ms"], 3),
            "images_per_s": round(ray["images_per_s_median"] / s["images_per_s_median"], 3)}
        return out
    finally:
        cluster.stop()
        if single is not None:
            single.terminate()
            single.wait(timeout=60)
        shutil.rmtree(tmp, ignore_errors=True)


def main(*, requests: int, clients: int, rounds: int, quick: bool) -> None:
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # `finally` tears the cluster down
    quick = quick_mode(quick)
    if quick:
        requests, clients, rounds = 12, 4, 2
    try:
        import ray  # noqa: F401
    except ImportError:
        path = write_json("scaleout.json", {"skipped": "the `ray` extra is not installed"})
        print(f"skipped: ray is not installed ({path})")
        return
    out = run(requests, clients, rounds)
    path = write_json("scaleout.json", {"quick": quick, **out})
    for name, p in out["paths"].items():
        print(f"{name:>6}: post p50 {p['post']['p50_ms']} ms (p95 {p['post']['p95_ms']}), get p50 "
              f"{p['get']['p50_ms']} ms, {clients} clients {p['images_per_s_median']} img/s")
    extra = out["ray_extra_ms"]
    print(f"ray extra per request: post {extra['post_p50']} ms, get {extra['get_p50']} ms; ray/single "
          f"img/s {out['ray_over_single']['images_per_s']}; ray start {out['ray_start_s']} s")
    f = out["failover"]
    print(f"failover: served again after {f['served_again_s']} s ({f['reads_503']} of {f['reads']} reads "
          f"503, {f['observations']} observations)")
    print(f"move: {out['move']['observations']} observations in {out['move']['seconds']} s "
          f"(command {out['move']['command_s']} s)")
    print(f"RSS: single {out['rss_mib']['single']} MiB, Ray cluster {out['rss_mib']['ray_total']} MiB")
    print(f"wrote {path}")

