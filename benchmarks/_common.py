"""Helpers shared by the benchmarks: results folder, quick mode, machine description, JSON out.

Timings on the shared development machines are noisy, so every script reports medians and ratios of
quantities measured side by side in one run; none of this is ever asserted in a test.
"""

from __future__ import annotations

import json
import os
import platform
from pathlib import Path
from typing import Any

from models.evaluation.bench import rss_mb as rss_mib

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results"

__all__ = ["RESULTS", "machine", "quick_mode", "rss_mib", "write_json"]


def quick_mode(flag: bool = False) -> bool:
    """True for a smoke run: `--quick` on the command or CORTEXLOC_BENCH_QUICK=1 in the environment."""
    return flag or os.environ.get("CORTEXLOC_BENCH_QUICK", "").strip().lower() in ("1", "true", "yes")


def machine() -> dict[str, Any]:
    """What the numbers were measured on: cores, memory, load when the run started."""
    mem_gib = 0.0
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                mem_gib = int(line.split()[1]) / 2**20
                break
    except OSError:
        pass
    try:
        load = list(os.getloadavg())
    except OSError:
        load = []
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return {"cpus": os.cpu_count(), "affinity": affinity, "mem_gib": round(mem_gib, 1),
            "loadavg_at_start": load, "python": platform.python_version(), "platform": platform.platform()}


def write_json(name: str, payload: dict[str, Any], out: Path | None = None) -> Path:
    """Write `payload` (plus the machine description) to benchmarks/results/<name> or `out`."""
    path = out or RESULTS / name
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps({"machine": machine(), **payload}, indent=2))
    tmp.replace(path)  # a reader (or a crash) never sees half a file
    return path
