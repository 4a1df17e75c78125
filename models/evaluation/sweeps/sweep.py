"""Parameter search for a grid-world TM preset that really predicts (issue: "beyond the paper").

Run: `cortexloc eval grid-sweep [--seeds K] [--grid main|followup]`. Every configuration is
scored with clean scoring on the published (a=5, n=0.5) file (when ../shared/data has it) and on
generated (a=5, n=0.5), (a=1, n=0.05), (a=0, n=0) and (a=5, n=0) worlds, so a choice cannot be tuned
to one file; the objective is the worst of these AUCs. One line per configuration, the best last.
"""

from __future__ import annotations

import itertools

import numpy as np

from models import presets
from models.evaluation import gridworld, metrics
from models.evaluation.datasets import GRID_PLACES_FILE, GRID_SDR_FILES, grid_dir
from models.evaluation.runner import run_htm

GRIDS = {
    "main": {
        "activationThreshold": [4, 8, 13],
        "minThreshold": [2, 3],
        "maxNewSynapseCount": [20, 32],
        "initialPermanence": [0.21, 0.35, 0.55],
        "permanenceDecrement": [0.02, 0.1],
        "maxSegmentsPerCell": [16],
        "maxSynapsesPerSegment": [32],
    },
    # Around the main grid's finding that maxNewSynapseCount near the ~40 winners per step is what
    # keeps noiseless loops stable.
    "followup": {
        "maxNewSynapseCount": [24, 28, 40],
        "minThreshold": [2, 3],
        "activationThreshold": [4, 8],
        "initialPermanence": [0.55],
        "permanenceDecrement": [0.02],
        "maxSegmentsPerCell": [16],
        "maxSynapsesPerSegment": [32, 48],
    },
}


def _datasets(seed: int) -> dict[str, gridworld.GridData]:
    root = grid_dir()
    out = {}
    if root.is_dir():
        out["file a5 n0.5"] = gridworld.load_published(root / GRID_SDR_FILES["a5n05"],
                                                       root / GRID_PLACES_FILE)
    out["gen a5 n0.5"] = gridworld.generate(5, 0.5, seed=seed)
    out["gen a1 n0.05"] = gridworld.generate(1, 0.05, seed=seed + 1)
    # Noiseless loops without a reset are the hard case for a predicting TM: every loop pushes a new
    # high-order representation one place further (see docs/results.md), so they are in the objective.
    out["gen a0 n0"] = gridworld.generate(0, 0.0, seed=seed + 2)
    out["gen a5 n0"] = gridworld.generate(5, 0.0, seed=seed + 3)
    return out


def run(*, seeds: int, grid: str) -> None:
    """Score every configuration of GRIDS[grid] over `seeds` seeds; print one line each, the best last."""
    data = _datasets(0)
    base = presets.tm_params("cortexloc-grid")
    configurations = GRIDS[grid]
    keys = list(configurations)
    rows = []
    for values in itertools.product(*(configurations[k] for k in keys)):
        over = dict(zip(keys, values, strict=True))
        if over["minThreshold"] > over["activationThreshold"]:
            continue
        if over["maxNewSynapseCount"] > over["maxSynapsesPerSegment"]:
            continue
        presets.confs["_sweep"] = {"description": "sweep", "tm": {**base, **over}}
        scores = {}
        for name, d in data.items():
            aucs, pred = [], []
            for s in range(seeds):
                w, info = run_htm(d, "_sweep", seed=s)
                aucs.append(metrics.grid_evaluation(w, d.places, "clean")["auc"])
                pred.append(info["predicted_column_fraction"])
            scores[name] = (float(np.mean(aucs)), float(np.mean(pred)))
        rows.append((min(v[0] for v in scores.values()), over, scores))
        print(f"{over} " + " ".join(f"{k}: auc {a:.4f} pred {p:.3f}" for k, (a, p) in scores.items()),
              flush=True)
    rows.sort(key=lambda r: r[0])
    print("best (by worst data set):", rows[-1][1], rows[-1][2])

