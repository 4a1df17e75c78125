"""The Temporal Memory against BrainBlocks 0.7.1, like for like, in one run (issue 25; `make bench`).

Run: `cortexloc bench tm-peer [--steps 5000] [--rounds 3] [--before REF ...]
[--peer-python .venv-peer/bin/python] [--quick]`.

Setup (the issue's): 2048 columns x 4 cells, 40 active columns, NuPIC's thresholds (activation 13,
20 new synapses; preset `numenta-defaults`) with 32 segments x 32 synapses per cell, `--steps` learning
steps on a never-repeating random SDR sequence; and the service preset (`cortexloc-default`, 308 active
columns). The peer is BrainBlocks' SequenceLearner with the same sizes (num_c 2048, num_spc 4, num_dps 32,
num_rpd 32, d_thresh 13, permanences in BrainBlocks' 0..99 scale: connected 50, +10, -10), fed the same
sequence through a BlankBlock, timed per step (BlankBlock + SequenceLearner feedforward). BrainBlocks is a
peer, not a dependency: it runs in its own environment (`--peer-python`; `make .venv-peer/.installed`
builds it from the sdist with cmake, g++, pybind11 and setuptools < 72, and `make bench` does first)
through a subprocess. Without it the peer row says why.

Both sides run in child processes, `--rounds` rounds of: this tree's memory, the memory of each commit
`--before REF` (`git archive`, for a before/after in the same run), then BrainBlocks, in reverse order
every other round, so that what else the shared cores run weighs on all alike. Reported: each side's
median ms/step per round and the median over the rounds, and the ratio cortexloc / BrainBlocks as the
median of the per-round ratios (each round's two medians measured minutes apart at most); and where the
service preset's step goes (`service_breakdown`; docs/benchmarks.md §12).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks._common import ROOT, quick_mode, write_json
from models.evaluation.bench import bench_tm, random_sequence

LIKE_FOR_LIKE = {"columns": 2048, "cells": 4, "active": 40, "preset": "numenta-defaults",
                 "overrides": {"maxSegmentsPerCell": 32, "maxSynapsesPerSegment": 32}}
SERVICE = {"columns": 2048, "cells": 4, "active": 308, "preset": "cortexloc-default"}

# Runs inside the peer's interpreter: reads {"steps", "seqs"} as JSON on stdin, prints the step times.
PEER = """
import json, sys, time
import numpy as np
from brainblocks.blocks import BlankBlock, SequenceLearner
job = json.load(sys.stdin)
blank = BlankBlock(num_s=2048)
sl = SequenceLearner(num_c=2048, num_spc=4, num_dps=32, num_rpd=32, d_thresh=13, perm_thr=50,
                     perm_inc=10, perm_dec=10, seed=0)
sl.input.add_child(blank.output, 0)
sl.init()
times = []
for x in job["seqs"]:
    t0 = time.perf_counter()
    blank.output.bits = np.zeros(2048, dtype=np.uint8)
    blank.output.acts = x
    blank.feedforward()
    sl.feedforward(learn=True)
    times.append(time.perf_counter() - t0)
print(json.dumps({"times": times}))
"""


# Runs in a child with the memory under test first on sys.path: prints bench_tm's result as JSON.
OURS = """
import json, sys
from models.evaluation.bench import bench_tm
print(json.dumps(bench_tm(**json.loads(sys.argv[1]))))
"""


def bench_ours(models_root: Path, steps: int) -> dict[str, Any]:
    """`bench_tm` like for like in a child process importing `models` from `models_root`."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(models_root), str(ROOT)])}
    proc = subprocess.run([sys.executable, "-c", OURS, json.dumps({"steps": steps, **LIKE_FOR_LIKE})],
                          env=env, cwd=models_root, capture_output=True, text=True, timeout=1800, check=True)
    return json.loads(proc.stdout)


def side_by_side(steps: int, rounds: int, peer_python: Path, before: list[str]) -> dict[str, Any]:
    """`rounds` interleaved rounds of this tree, each `before` commit and the peer (see the docstring)."""
    with tempfile.TemporaryDirectory(prefix="cortexloc-tm-peer-") as tmp:
        roots = {"cortexloc": ROOT}
        for ref in before:
            dest = Path(tmp) / ref.replace("/", "_")
            dest.mkdir()
            archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref, "models"],
                                     capture_output=True, check=True).stdout
            subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
            roots[f"before ({ref})"] = dest
        runs: dict[str, list[dict[str, Any]]] = {name: [] for name in [*roots, "brainblocks"]}
        for r in range(rounds):
            order = [*roots, "brainblocks"]
            for name in order if r % 2 == 0 else order[::-1]:
                got = (bench_peer(peer_python, steps) if name == "brainblocks"
                       else bench_ours(roots[name], steps))
                runs[name].append(got)
                ms = got.get("ms_per_step_median")
                print(f"round {r + 1}/{rounds} {name}: " + (f"{ms:.3f} ms/step" if ms else got["error"]),
                      flush=True)
    out: dict[str, Any] = {}
    peer_ok = all("error" not in g for g in runs["brainblocks"])
    for name, got in runs.items():
        if "error" in got[0]:
            out[name] = got[0]
            continue
        medians = [g["ms_per_step_median"] for g in got]
        out[name] = {**got[-1], "ms_per_step_median": float(np.median(medians)), "round_medians": medians}
        if name != "brainblocks" and peer_ok:
            ratios = [a / b["ms_per_step_median"] for a, b in zip(medians, runs["brainblocks"], strict=True)]
            out[name]["round_ratios_over_peer"] = ratios
            out[name]["ratio_over_peer"] = float(np.median(ratios))
    return out


def bench_peer(python: Path, steps: int, seed: int = 0) -> dict[str, Any]:
    """BrainBlocks' SequenceLearner on the same random sequence, in `python` (its own environment)."""
    if not python.exists():
        return {"error": f"peer interpreter {python} not found (see this script's docstring to build it)"}
    seqs = [x.tolist() for x in random_sequence(steps, 2048, 40, seed + 1)]
    proc = subprocess.run([str(python), "-c", PEER], input=json.dumps({"seqs": seqs}), capture_output=True,
                          text=True, timeout=1800, check=False)
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else "peer failed"}
    t = np.array(json.loads(proc.stdout)["times"][50:])  # the first steps include the peer's warm-up
    return {"ms_per_step_median": float(np.median(t) * 1e3),
            "ms_per_step_p90": float(np.percentile(t, 90) * 1e3)}


def service_breakdown(warm: int = 300, steps: int = 60, seed: int = 0) -> dict[str, float]:
    """Where the service preset's step goes: one saved state (after `warm` random steps) stepped `steps`
    times with learning, with learning but predictedSegmentDecrement 0 (no punishment), and without
    learning; each the median ms of the step kernel and of dendrite activation (docs/benchmarks.md §12)."""
    import time

    from models import presets
    from models.memory import _tm_kernels as kern
    from models.memory import _tm_synapses as syn
    from models.memory.temporal_memory import TemporalMemory

    tm = TemporalMemory(presets.tm_options(SERVICE["preset"]))
    for x in random_sequence(warm, 2048, SERVICE["active"], seed + 1):
        tm.compute(x)
    state = {k: np.copy(v) for k, v in tm.state_dict().items()}
    seq = random_sequence(steps, 2048, SERVICE["active"], seed + 2)
    out: dict[str, float] = {}
    saved = kern.step, kern.activity
    try:
        for variant in ("learn", "learn_without_punishment", "infer"):
            times: dict[str, list[float]] = {"step": [], "activity": []}

            def timed(name: str, fn: Any) -> Any:
                def call(*a: Any) -> Any:
                    t0 = time.perf_counter()
                    r = fn(*a)
                    times[name].append(time.perf_counter() - t0)  # noqa: B023 - used within the loop
                    return r
                return call

            kern.step, kern.activity = timed("step", saved[0]), timed("activity", saved[1])
            t = TemporalMemory.from_state(state)
            if variant == "learn_without_punishment":
                t._p[syn.P_PDEC] = 0
            c0 = t.counters.copy()
            for x in seq:
                t.compute(x, learn=variant != "infer")
            out[f"{variant}_step_ms"] = float(np.median(times["step"]) * 1e3)
            out[f"{variant}_activity_ms"] = float(np.median(times["activity"]) * 1e3)
            out[f"{variant}_overrun_per_step"] = float((t.counters - c0)[syn.C_OVERRUN] / steps)
    finally:
        kern.step, kern.activity = saved
    return out


def main(*, steps: int, rounds: int, before: list[str], peer_python: Path | None, quick: bool,
         out: Path | None) -> None:
    if peer_python is None:
        peer_python = ROOT / ".venv-peer" / "bin" / "python"
    steps = 300 if quick_mode(quick) else steps
    rounds = 1 if quick_mode(quick) else rounds
    sides = side_by_side(steps, rounds, peer_python, before)
    ours, peer = sides["cortexloc"], sides["brainblocks"]
    service = bench_tm(steps=max(steps // 5, 100), **SERVICE)
    breakdown = service_breakdown(warm=50 if quick_mode(quick) else 300,
                                  steps=10 if quick_mode(quick) else 60)
    ratio = ours.get("ratio_over_peer")
    print(f"like for like, {steps} steps, median of {rounds} rounds: cortexloc "
          f"{ours['ms_per_step_median']:.3f} ms/step, BrainBlocks "
          + (f"{peer['ms_per_step_median']:.3f} ms/step, ratio {ratio:.2f} (median of the rounds' ratios)"
             if ratio else peer["error"]))
    for name in sides:
        if name.startswith("before") and "ratio_over_peer" in sides[name]:
            print(f"  {name}: {sides[name]['ms_per_step_median']:.3f} ms/step, ratio "
                  f"{sides[name]['ratio_over_peer']:.2f}")
    b = breakdown
    print(f"service preset (308 active): {service['ms_per_step_median']:.3f} ms/step "
          f"(p90 {service['ms_per_step_p90']:.3f}); its step kernel on one saved state: learning "
          f"{b['learn_step_ms']:.2f} ms, without punishment {b['learn_without_punishment_step_ms']:.2f} ms, "
          f"not learning {b['infer_step_ms']:.2f} ms; activation {b['learn_activity_ms']:.2f} ms; "
          f"{b['learn_overrun_per_step']:.0f} synapses overrun per step")
    path = write_json("tm_peer.json", {"like_for_like": ours, "brainblocks": peer,
                                       "ratio_cortexloc_over_peer": ratio, "rounds": rounds,
                                       "before": {k: v for k, v in sides.items() if k.startswith("before")},
                                       "service_preset": service,
                                       "service_breakdown": breakdown},
                      out)
    print(f"wrote {path}")

