"""Run every benchmark in this folder (`make bench`; `make bench-quick` for a smoke run).

Each script runs in its own process (so RSS and start-up are its own) and writes JSON under
benchmarks/results/; this runner prints their summaries as they come and a final list of failures.
Quick mode (`--quick` or CORTEXLOC_BENCH_QUICK=1) shrinks every benchmark to a smoke run of a few
minutes in all; the full run takes about 1.5 hours here, most of it the 10^6-step long run.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

# In running order: the short ones first, the 10^6-step long run last.
ORDER = ["bench_runtimes.py", "bench_encoder.py", "bench_tm.py", "bench_tm_peer.py", "bench_tm_profile.py",
         "bench_index.py", "bench_localiser.py", "bench_place.py", "bench_http.py", "bench_scaleout.py",
         "bench_hostile.py", "bench_startup.py", "bench_growth.py", "bench_forgetting.py", "bench_longrun.py"]
# Scripts that predate quick mode take their own smaller sizes.
QUICK_ARGS = {"bench_encoder.py": ["--repeats", "3"], "bench_tm.py": ["--steps", "500"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="smoke run (also CORTEXLOC_BENCH_QUICK=1)")
    ap.add_argument("--only", nargs="+", default=None, help="script names to run (default: all)")
    args = ap.parse_args()
    quick = args.quick or os.environ.get("CORTEXLOC_BENCH_QUICK", "").strip().lower() in ("1", "true", "yes")
    found = {p.name for p in HERE.glob("bench_*.py")}
    scripts = [s for s in ORDER if s in found] + sorted(found - set(ORDER))
    if args.only:
        scripts = [s for s in scripts if s in args.only or s.removesuffix(".py") in args.only]
    env = {**os.environ, "CORTEXLOC_BENCH_QUICK": "1" if quick else ""}
    failed = []
    for script in scripts:
        extra = (QUICK_ARGS.get(script, ["--quick"])) if quick else []
        print(f"== {script} {' '.join(extra)}", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call([sys.executable, str(HERE / script), *extra], env=env, cwd=HERE.parent)
        print(f"== {script}: exit {rc} after {time.perf_counter() - t0:.0f} s", flush=True)
        if rc != 0:
            failed.append(script)
    if failed:
        print(f"failed: {', '.join(failed)}", flush=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
