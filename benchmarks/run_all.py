"""Run every benchmark (`cortexloc bench all`; `make bench`, `make bench-quick` for a smoke run).

Each benchmark runs as its `cortexloc` command in its own process (so RSS and start-up are its own) and
writes JSON under benchmarks/results/; this runner prints their summaries as they come and a final list
of failures. Quick mode (`--quick` or CORTEXLOC_BENCH_QUICK=1) shrinks every benchmark to a smoke run of a
few minutes in all; the full run takes about 1.5 hours here, most of it the 10^6-step long run.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

from benchmarks._common import ROOT, quick_mode

# Each `bench_<name>.py` of this folder as its command, in running order: the short ones first, the
# 10^6-step long run last (tests/test_benchmarks_smoke.py checks that none is left out).
COMMANDS: dict[str, list[str]] = {
    "bench_runtimes": ["bench", "runtimes"], "bench_encoder": ["bench", "encoder-suite"],
    "bench_tm": ["bench", "tm-suite"], "bench_tm_peer": ["bench", "tm-peer"],
    "bench_tm_profile": ["bench", "tm-profile"], "bench_index": ["bench", "index"],
    "bench_localiser": ["bench", "localiser"], "bench_place": ["bench", "place"],
    "bench_http": ["bench", "http"], "bench_scaleout": ["bench", "scaleout"],
    "bench_hostile": ["bench", "hostile"], "bench_fairness": ["bench", "fairness"],
    "bench_startup": ["bench", "startup"],
    "bench_growth": ["bench", "growth"], "bench_forgetting": ["bench", "forgetting"],
    "bench_gpu": ["bench", "gpu"], "bench_ingest": ["bench", "ingest"],
    "bench_keyframes": ["bench", "keyframes"], "bench_loops_http": ["eval", "loops-http"],
    "bench_memory": ["bench", "memory"], "bench_snapshot": ["bench", "snapshot"],
    "bench_uploads": ["bench", "uploads"], "bench_longrun": ["bench", "longrun"],
}
# Benchmarks that predate quick mode take their own smaller sizes.
QUICK_ARGS = {"bench_encoder": ["--repeats", "3"], "bench_tm": ["--steps", "500"], "bench_keyframes": []}


def main(*, quick: bool, only: list[str]) -> None:
    """Run the benchmarks named in `only` (module or command names; all when empty), in order."""
    quick = quick_mode(quick)
    names = [m for m, argv in COMMANDS.items()
             if not only or m in only or m.removeprefix("bench_") in only or argv[1] in only]
    env = {**os.environ, "CORTEXLOC_BENCH_QUICK": "1" if quick else ""}
    failed = []
    for module in names:
        argv = [*COMMANDS[module], *(QUICK_ARGS.get(module, ["--quick"]) if quick else [])]
        print(f"== cortexloc {' '.join(argv)}", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call([sys.executable, "-m", "service.cli", *argv], env=env, cwd=ROOT)
        print(f"== cortexloc {' '.join(argv)}: exit {rc} after {time.perf_counter() - t0:.0f} s", flush=True)
        if rc != 0:
            failed.append(" ".join(argv))
    if failed:
        print(f"failed: {', '.join(failed)}", flush=True)
        raise SystemExit(1)
