"""Where the service's CPU goes per image: 16 loopback clients learning into one map (issue 24).

Run: `cortexloc bench profile-service [--clients 16] [--seconds 30]` (needs `py-spy` on PATH or in
the venv, to name the server's threads; not part of `make bench`). Writes benchmarks/results/profile.json.

The real `cortexloc serve` as in bench_http.py (default settings, the default map, 640x480 JPEGs). Over
one run of the clients it reads every server thread's CPU time from /proc (user + system) and the
client process's own, and divides by the replies: CPU milliseconds per image, per thread group
(event loop, encoder worker = the backbone, decode threads, map writer, group-commit sync, AnyIO
workers = header probes and digests, ONNX Runtime's own). A 25 s py-spy sample names the threads (by
their Python names) and gives the share of the writer's samples per function. On 2 cores the sum of
these is what bounds images/s: 2000 ms / (server + client CPU ms per image), less what other work on
the machine takes.
"""

from __future__ import annotations

import asyncio
import collections
import os
import re
import resource
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from benchmarks._common import RESULTS, write_json
from benchmarks.bench_http import Server, drive
from models.evaluation.bench import synthetic_jpegs

_TICK = os.sysconf("SC_CLK_TCK")


def thread_cpu_s(pid: int) -> dict[int, float]:
    """CPU seconds (user + system) of every thread of `pid`, by thread id."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[int(task.name)] = (int(fields[11]) + int(fields[12])) / _TICK
    return out


def group_of(name: str) -> str:
    """A thread's group from its Python name (numbers dropped)."""
    name = re.sub(r"[_-]?\d+$", "", name)
    return {"encoder": "encoder worker (backbone)", "decode": "decode threads", "MainThread": "event loop",
            "AnyIO worker thread": "AnyIO workers (probe, digest)"}.get(
        name, "map writer" if name.startswith("map-") else "group-commit sync"
        if name.startswith("sync-") else name)


def main(*, clients: int, seconds: float, server_cmd: str | None, out: Path | None) -> None:
    if out is None:
        out = RESULTS / "profile.json"
    spy_bin = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))
    frames = synthetic_jpegs(64, seed=1)
    tmp = Path(tempfile.mkdtemp(prefix="cortexloc-profile-"))
    os.environ["CORTEXLOC_WEIGHTS_DIR"] = str(tmp / "no-weights")
    server = Server(tmp, command=shlex.split(server_cmd) if server_cmd else None)
    raw = tmp / "spy.txt"
    try:
        server.wait_ready()
        asyncio.run(drive(server.base, frames, 4, 32, 60))  # warm-up
        pid = server.proc.pid
        spy = subprocess.Popen([spy_bin, "record", "-p", str(pid), "-d", str(int(seconds * 0.8)),
                                "-r", "50", "--threads", "-f", "raw", "-o", str(raw), "--nonblocking"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        before, c0 = thread_cpu_s(pid), resource.getrusage(resource.RUSAGE_SELF)
        r = asyncio.run(drive(server.base, frames, clients, 100000, seconds))
        after, c1 = thread_cpu_s(pid), resource.getrusage(resource.RUSAGE_SELF)
        spy.wait(timeout=120)
    finally:
        server.stop()
    names: dict[int, str] = {}
    writer: collections.Counter[str] = collections.Counter()
    for line in raw.read_text().splitlines() if raw.exists() else []:
        stack, _, n = line.rpartition(" ")
        head, *frames_ = stack.split(";")
        m = re.match(r"thread \((\d+|0x[0-9a-fA-F]+)\): (.*)", head) or re.match(
            r"thread \((\d+|0x[0-9a-fA-F]+)\)", head)
        if not m:
            continue
        tid = int(m.group(1), 0)
        name = m.group(2) if m.lastindex and m.lastindex > 1 else (frames_[0] if frames_ else "?")
        names.setdefault(tid, name)
        if name.startswith("map-"):
            ours = [f for f in frames_ if re.search(r"\((service|models|storage)/", f)]
            writer[re.sub(r" \(.*", "", ours[-1]) if ours else "other"] += int(n)
    n_img = max(r["replies"], 1)
    by_group: collections.Counter[str] = collections.Counter()
    for tid, cpu in after.items():
        by_group[group_of(names.get(tid, "ONNX Runtime / native")) if tid in names
                 else "ONNX Runtime / native / unnamed"] += (cpu - before.get(tid, 0.0)) * 1e3 / n_img
    client_ms = ((c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)) * 1e3 / n_img
    server_ms = sum(by_group.values())
    total_w = sum(writer.values()) or 1
    print(f"{clients} clients: {r['images_per_s']:.1f} img/s over {r['wall_s']:.0f} s; CPU ms per "
          f"image: server {server_ms:.1f}, client {client_ms:.1f}", flush=True)
    for g, v in by_group.most_common():
        print(f"  {g:34s} {v:6.2f} ms/image", flush=True)
    print("map writer's py-spy samples by function (running or waiting on I/O): " + ", ".join(
        f"{k} {v / total_w:.0%}" for k, v in writer.most_common(8)), flush=True)
    payload: dict[str, Any] = {
        "server_cmd": server_cmd or "cortexloc", "clients": clients,
        "images_per_s": r["images_per_s"], "replies": r["replies"],
        "server_cpu_ms_per_image": server_ms, "client_cpu_ms_per_image": client_ms,
        "server_cpu_ms_per_image_by_thread": dict(by_group.most_common()),
        "writer_samples_by_function": {k: v / total_w for k, v in writer.most_common(12)},
        "server_stage_ms_median": r["server_stage_ms_median"]}
    write_json(out.name, payload, out)
    shutil.rmtree(tmp, ignore_errors=True)

