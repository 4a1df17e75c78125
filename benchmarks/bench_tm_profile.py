"""Where the service preset's learning step goes, by ablation (issue 25; docs/benchmarks.md §12).

Run: `cortexloc bench tm-profile [--warm 300] [--steps 30] [--repeats 3] [--before main ...]`.
Writes benchmarks/results/tm_profile.json.

The kernels are compiled (numba, with the small helpers inlined), so no profiler attributes time to
the parts of a step. Instead this script copies `models/` into a temporary folder once per variant,
removes one part of the step from the copy's source, and times the same steps in a child process that
imports the copy:

- `full`: the kernel as it is;
- `no_index`: no reverse-index upkeep in the step (`_rx_add` / `_rx_remove` return at once; the
  index is still rebuilt correctly on load, so the step starts from the right state);
- `no_index_no_select`: also no lowest-permanence scan for overrun victims (the first live slot);
- `no_index_no_select_no_draw`: also no draws for the new synapses' presynaptic cells;
each with predictedSegmentDecrement as set and 0 (no punishment). One saved state (the service preset
`cortexloc-default` after `--warm` random 308-of-2048 steps) is restored in place before every timed
step, so each variant steps from the same state; the differences between variants are the parts'
costs; `--before REF ...` adds the kernel of each commit REF (`git archive`) for a same-run comparison. The
variants run in turn, `--repeats` rounds of `--steps` steps each (after one untimed pass that warms the
caches). Times are the thread's CPU time (`time.thread_time`), so that time spent waiting for one of the
2 shared cores is not counted; medians over all the rounds' steps; the activation of
dendrites is timed on its own as well.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from benchmarks._common import ROOT, quick_mode, write_json

SYN = "models/memory/_tm_synapses.py"
SIG_ADD = "def _rx_add(q, cell, e, rev, rpos, bprev, bfill, tail, pool):\n"
ADD = (SIG_ADD, SIG_ADD + "    rpos[q] = 0\n    return\n")
DOC_REMOVE = '    """Drop synapse q (from `cell`) from the index; the cell\'s last entry fills the hole."""\n'
REMOVE = (DOC_REMOVE, DOC_REMOVE + "    return\n")
# The load-time rebuild keeps a working copy of `_rx_add`, so every variant starts from a right index.
REBUILD = ("_rx_add(q, np.int64(presyn[q]), _entry(", "_rx_add_kept(q, np.int64(presyn[q]), _entry(")
SELECT = ("            if perm[q] < best_v - EPS:\n                best = k\n"
          "                best_v = perm[q]\n",
          "            if perm[q] != np.inf:\n                best = k\n                break\n")
DRAW = ("        j = rng.integers(i, m)\n", "        j = i\n")
VARIANTS: dict[str, list[tuple[str, str]]] = {
    "full": [],
    "no_index": [ADD, REMOVE, REBUILD],
    "no_index_no_select": [ADD, REMOVE, REBUILD, SELECT],
    "no_index_no_select_no_draw": [ADD, REMOVE, REBUILD, SELECT, DRAW],
}

# Runs in the child, with the patched copy first on sys.path: prints {"step": [...], "activity": [...]}.
CHILD = """
import json, sys, time
import numpy as np
from models.memory.temporal_memory import StreamContext, TemporalMemory
from models.memory import _tm_synapses as syn
from models.evaluation.bench import random_sequence
job = json.loads(sys.argv[1])
st = dict(np.load(job["state"]))
tm, like = TemporalMemory.from_state(st), TemporalMemory.from_state(st)
S, K = int(tm._ip[syn.I_S]), int(tm._ip[syn.I_K])
seq = random_sequence(job["steps"], 2048, 308, 2)
out = {"step": [], "activity": [], "overrun": 0}
for rep in range(job["repeats"] + 1):  # the first pass warms the caches and is not kept
    for x in seq:
        for n in tm._CANONICAL:
            getattr(tm, n)[...] = st[n]
        tm.counters[...] = st["counters"]
        tm.iteration, tm.version = (int(v) for v in st["scalars"])
        tm.rng.bit_generator.state = like.rng.bit_generator.state
        syn.rebuild_index(tm.nsyn, tm.presyn, tm.perm, tm._p, K, tm._rx)
        tm._seg_count[...] = np.count_nonzero(tm.nsyn.reshape(-1, S), axis=1)
        tm.context = StreamContext.from_state({k[4:]: v for k, v in st.items() if k.startswith("ctx.")})
        if job["no_punishment"]:
            tm._p[syn.P_PDEC] = 0
        t0 = time.thread_time()
        tm._activate_dendrites(tm.context, tm.context.active_cells, False)
        t1 = time.thread_time()
        c0 = int(tm.counters[syn.C_OVERRUN])
        tm.compute(x)
        t2 = time.thread_time()
        if rep:
            out["activity"].append(t1 - t0)
            out["step"].append(t2 - t1)
            out["overrun"] = int(tm.counters[syn.C_OVERRUN]) - c0
print(json.dumps(out))
"""


def patched_copy(dest: Path, edits: list[tuple[str, str]]) -> None:
    """`models/` copied to `dest` with `edits` applied to the synapse module (each must match once)."""
    shutil.copytree(ROOT / "models", dest / "models", ignore=shutil.ignore_patterns("__pycache__"))
    path = dest / SYN
    src = path.read_text()
    if edits:
        # A kept copy of the working `_rx_add` for the load-time rebuild.
        head = src.index('@njit(cache=True, inline="always")\ndef _rx_add(')
        end = src.index('@njit(cache=True, inline="always")\ndef _rx_remove(')
        kept = src[head:end].replace("def _rx_add(", "def _rx_add_kept(")
        at = src.index("@njit(cache=True)\ndef rebuild_index(")
        src = src[:at] + kept + src[at:]
    for old, new in edits:
        if src.count(old) != 1:
            raise RuntimeError(f"the kernel source changed: cannot ablate {old.strip()[:60]!r}")
        src = src.replace(old, new)
    path.write_text(src)


def split(f: dict[str, Any]) -> dict[str, float]:
    """The parts' costs (ms) from the variants' medians. Each part is the median of its differences over
    every pair of variants that differ by it alone (with and without punishment), which is steadier
    than one difference on the shared cores."""
    import numpy as np

    def part(pairs: list[tuple[str, str]]) -> float:
        return float(np.median([f[a]["step_ms"] - f[b]["step_ms"] for a, b in pairs]))

    np_ = "_no_punishment"
    chain = ["full", "no_index", "no_index_no_select", "no_index_no_select_no_draw"]
    out = {
        "activation (in the step)": f["full"]["activity_ms"],
        "punishment of chance matches": part([(v, v + np_) for v in chain]),
        "reverse-index upkeep": part([("full", "no_index"), ("full" + np_, "no_index" + np_)]),
        "overrun victim scan": part([(chain[1], chain[2]), (chain[1] + np_, chain[2] + np_)]),
        "draws for new synapses": part([(chain[2], chain[3]), (chain[2] + np_, chain[3] + np_)]),
    }
    out["the rest (adapt, candidates, compaction, calls)"] = f["full"]["step_ms"] - sum(out.values())
    return out


def main(*, warm: int, steps: int, repeats: int, before: list[str], quick: bool) -> None:
    if quick_mode(quick):
        warm, steps, repeats = 50, 8, 1
    import numpy as np

    from models import presets
    from models.evaluation.bench import random_sequence
    from models.memory.temporal_memory import TemporalMemory

    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="cortexloc-tm-profile-") as tmp:
        tm = TemporalMemory(presets.tm_options("cortexloc-default"))
        for x in random_sequence(warm, 2048, 308, 1):
            tm.compute(x)
        state = Path(tmp) / "state.npz"
        np.savez(state, **tm.state_dict())
        size = tm.size()
        variants = dict(VARIANTS)
        for name, edits in VARIANTS.items():
            patched_copy(Path(tmp) / name, edits)
        for ref in before:
            # The kernel of another commit, for a same-run before/after comparison.
            variants[f"before ({ref})"] = []
            dest = Path(tmp) / f"before ({ref})"
            dest.mkdir()
            archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref, "models"],
                                     capture_output=True, check=True).stdout
            subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
        samples: dict[str, dict[str, list[float]]] = {}
        # Rounds of every variant in turn, so that what else the shared cores run weighs on all alike.
        for _ in range(repeats):
            for name in variants:
                env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(tmp) / name), str(ROOT)])}
                for no_pun in (False, True):
                    job = {"state": str(state), "steps": steps, "repeats": 1, "no_punishment": no_pun}
                    proc = subprocess.run([sys.executable, "-c", CHILD, json.dumps(job)], env=env, cwd=tmp,
                                          capture_output=True, text=True, check=True)
                    r = json.loads(proc.stdout)
                    got = samples.setdefault(name + ("_no_punishment" if no_pun else ""),
                                             {"step": [], "activity": [], "overrun": [r["overrun"]]})
                    got["step"] += r["step"]
                    got["activity"] += r["activity"]
        for key, got in samples.items():
            results[key] = {"step_ms": float(np.median(got["step"]) * 1e3),
                            "activity_ms": float(np.median(got["activity"]) * 1e3),
                            "overrun_per_step": got["overrun"][0]}
            print(f"{key:>42}: step (compute) {results[key]['step_ms']:.2f} ms CPU, activation alone "
                  f"{results[key]['activity_ms']:.2f} ms, {got['overrun'][0]} synapses overrun", flush=True)
    parts = split(results)
    print("parts of the full step (ms CPU): " + ", ".join(f"{k} {v:.2f}" for k, v in parts.items()))
    path = write_json("tm_profile.json", {
        "config": {"warm": warm, "steps": steps, "repeats": repeats, "before": before, "quick": quick,
                   "preset": "cortexloc-default"},
        "state": {"segments": size["segments"], "synapses": size["synapses"]},
        "variants": results, "parts_ms": parts})
    print(f"wrote {path}")

