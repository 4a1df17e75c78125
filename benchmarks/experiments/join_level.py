"""Experiment of docs/results.md §11 ("A join that keeps its row"): how alike a frame's code is to the
stored row of its own place seen otherwise, and to the rows a wrong join would take, on the scale of
`consolidate` and `join_kept` (docs/design/science.md §11.8), on every window of both halves.

    cortexloc eval join-level 42 > join-level.jsonl
    cortexloc eval join-level sum < join-level.jsonl    # the quantiles over every window

Per window (`stress.windows`: every 200-file window of both halves slid by 100, from
../shared/data/nordland_tiny_64x32, labels = file index) and map seed: the window's summer frames are the
stored rows (their codes, as a served map of that seed hashes them, and the map's code statistics,
`CodeStats`: each share is (Dice − b) / (1 − b), b the frame's background likeness against those rows).
The frames read against them: `winter` (the same files in winter: another season), `noise8` (the summer
frames with σ 8 pixel noise: a noisier camera) and `summer` (the stored frames themselves). For each
frame i: `same`, its share with row i; `wrong`, for each back-step d in WRONG_STEPS, its largest share
with rows i − d − 1, i − d, i − d + 1 (what a warm-up join whose path stood d places off would weigh: the
most alike of the three rows its slack reads). Each line: per kind, the quantiles of both and the
fraction of frames at or above each level of LEVELS. Deterministic: the map seeds, the noise seeds.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from benchmarks.experiments import per_window
from models.frontend import slsbh
from models.localisation.trail import CodeStats, code_dice
from service.evaluation import service_path, stress

#: The back-steps of a wrong join's path (places off the row the frame shows).
WRONG_STEPS = (3, 5, 10, 20, 30)
#: The levels read: `join_kept`'s default, then `consolidate`'s.
LEVELS = (0.0, 0.1, 0.25)
QUANTILES = (1, 5, 25, 50, 75, 95, 99)
KINDS = ("winter", "noise8", "summer")


def shares(code: np.ndarray, rows: list[np.ndarray], stats: CodeStats) -> np.ndarray:
    """(len(rows),) the shares of `code` with each row, on the scale of `consolidate`."""
    b = stats.background(code)
    return np.array([(code_dice(code, r) - b) / (1.0 - b) for r in rows])


def run(frames: stress.Frames, half: str, lo: int, seed: int, map_conf: dict[str, Any]) -> dict[str, Any]:
    idx = range(lo, lo + stress.WINDOW)
    summer = [frames.image("summer", i) for i in idx]
    pngs = {"summer": [stress.png(im) for im in summer],
            "winter": [stress.png(frames.image("winter", i)) for i in idx],
            "noise8": [stress.variant(im, "noise:8", 1000 + j) for j, im in enumerate(summer)]}
    feats = {k: frames.features(v) for k, v in pngs.items()}
    _, hasher, config = service_path._model(feats["summer"].shape[1], seed=seed, memory="tm", create=None,
                                            **{k: v for k, v in map_conf.items() if k != "encoder_id"})
    s = float(config.sections.slsbh.s)
    codes = {k: [np.asarray(c, np.int64) for c in slsbh.hash_projected(hasher.project(f), s)]
             for k, f in feats.items()}
    stats = CodeStats(2 * int(config.sections.slsbh.k))
    for c in codes["summer"]:
        stats.add(c)
    stored = codes["summer"]
    out: dict[str, Any] = {"half": half, "lo": lo, "seed": seed}
    for kind in KINDS:
        same, wrong = [], []
        for i, code in enumerate(codes[kind]):
            same.append(shares(code, [stored[i]], stats)[0])
            for d in WRONG_STEPS:
                near = [j for j in (i - d - 1, i - d, i - d + 1) if j >= 0]
                if len(near) == 3:
                    wrong.append(shares(code, [stored[j] for j in near], stats).max())
        out[kind] = {name: _read(np.asarray(v)) for name, v in (("same", same), ("wrong", wrong))}
    return out


def _read(v: np.ndarray) -> dict[str, Any]:
    return {"n": int(v.size), "quantiles": {str(q): round(float(np.percentile(v, q)), 3) for q in QUANTILES},
            "at_or_above": {str(level): round(float((v >= level).mean()), 3) for level in LEVELS},
            "values": [round(float(x), 4) for x in v]}


def main(*, seeds: list[int]) -> None:
    per_window(run, seeds)


def total(lines: list[dict[str, Any]]) -> None:
    """The quantiles and fractions over every line's frames, per kind, and per window the fraction of
    `winter` frames at or above each level (the spread of the windows)."""
    for kind in KINDS:
        for name in ("same", "wrong"):
            v = np.concatenate([np.asarray(line[kind][name]["values"]) for line in lines])
            print(kind, name, json.dumps({k: w for k, w in _read(v).items() if k != "values"}))
    for level in LEVELS:
        per = [line["winter"]["same"]["at_or_above"][str(level)] for line in lines]
        print(f"winter same at or above {level} per window: min {min(per)} max {max(per)}")
