"""Experiment of docs/results.md §10.11 "With poses": the stress suite's routes (service/evaluation/
stress.py) given poses, one learning stream through the service's step (`service_path.slam_replay` with
each frame's `Motion`), at the suite's `tune` windows (7, from file 0 slid by 100) and seeds 1, 7, 42.

    cortexloc eval short-term-poses 1.0 1.0 '{}' rate3 rate10 parked flat \
        short-loop seasons noise repeat

Arguments: metres per label (each frame's pose is its label x this along x), seconds per frame (its
stamp is its index x this), the maps' localiser options as JSON (`'{"short_term_metres": 40}'`,
`'{"max_speed": 5}'`), then the cases. A lap starts again at x = 0 (a reset). Prints
`stress.summary` per case (false revisits while mapping, merged places, wrong consolidations, lap-2
precision and recall); `'{"short_term_metres": 0}'` gives the memory by appearance on the same runs.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from models.evaluation import slam
from models.localisation.motion import Motion
from service.evaluation import service_path, stress
from service.evaluation.slam import encoder_setup

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "nordland_tiny_64x32"
SEEDS = (1, 7, 42)


def main(*, metres: float, seconds: float, localiser: dict, cases: list[str]) -> None:
    """`cortexloc eval short-term-poses`: `stress.summary` per case over the tune windows and seeds."""
    enc, cache, map_conf = encoder_setup(None, localiser or None)
    frames = stress.Frames(DATA, enc, cache)
    t, results = time.time(), []
    for _, lo in stress.windows(quick=False):
        if lo >= stress.HALVES["tune"][1]:
            break
        for case in cases:
            r = stress.route(frames, case, lo)
            feats, contrast = frames.features(r.pngs), service_path.contrasts(r.pngs)
            motions = [Motion((float(label) * metres, 0.0), i * seconds) for i, label in enumerate(r.labels)]
            per = []
            for seed in SEEDS:
                trace: dict = {}
                found, threshold = service_path.slam_replay(feats, seed=seed, memory="tm", contrast=contrast,
                                                            trace=trace, motions=motions, **map_conf)
                s = slam.score(found.best, found.confidence, r.labels, threshold, stress.TOLERANCE, r.laps)
                per.append({"seed": seed, "false_revisits": s["false_revisits"], **stress._lap2(s),
                            **stress.merges(r.labels, trace)})
            results.append({"half": "tune", "lo": lo, "case": case, "service-slam": per})
    for case, per_method in stress.summary(results).items():
        acc = per_method["service-slam"]
        print(case, json.dumps({k: round(v, 3) if isinstance(v, float) else v for k, v in acc.items()}))
    print(f"{time.time() - t:.0f} s", file=sys.stderr)

