"""Experiments of docs/results.md §10.6: changes to the localiser's evidence tried against the season
bias of one learning stream, over the `cortexloc eval slam` routes. Not the service's code: each
wraps `SequenceLocaliser.step` for the run only, so the rest of the path is the service's.

    PYTHONPATH=$PWD python benchmarks/experiments/slam_seasons.py own 0.5 --half test
    PYTHONPATH=$PWD python benchmarks/experiments/slam_seasons.py contrast 5 --half test

`own X`: the evidence of candidate rows on the stream's own trail lowered by X candidate spreads.
`contrast W`: each candidate's score less the mean of its ±W route neighbours' (rows outside the
candidates at the weakest candidate's score): SeqSLAM's local contrast along the links.
(Stream adaptation, the third, is a map option: `cortexloc eval slam --adapt-tau 20`.)
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from models.localisation import localiser as loc


def own(x: float):
    def change(graph, seqs, scores, own_trail):
        if own_trail is not None and x and seqs.size:
            scores = scores.copy()
            scores[graph.trail[seqs] == own_trail.trail] -= x * (scores.std() + 1e-9)
        return scores
    return change


def contrast(w: int):
    def change(graph, seqs, scores, own_trail):
        if not w or seqs.size < 2:
            return scores
        floor, look, h = scores.min(), dict(zip(seqs.tolist(), scores.tolist(), strict=True)), seqs.size
        nb = np.full((h, 2 * w), floor)
        fw, bw = seqs.copy(), seqs.copy()
        for k in range(w):
            fw, bw = graph.walk(fw, np.ones(h, np.int8), 1), graph.walk(bw, -np.ones(h, np.int8), 1)
            nb[:, 2 * k] = [look.get(int(r), floor) for r in fw]
            nb[:, 2 * k + 1] = [look.get(int(r), floor) for r in bw]
        return scores - nb.mean(1)
    return change


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("kind", choices=["own", "contrast"])
    ap.add_argument("value", type=float)
    ap.add_argument("--half", default="test")
    ap.add_argument("--routes", default="seasons")
    ap.add_argument("--methods", default="service-slam,service")
    ap.add_argument("--data", type=Path, default=Path("../shared/data/nordland_tiny_64x32"))
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    change = own(a.value) if a.kind == "own" else contrast(int(a.value))
    step = loc.SequenceLocaliser.step

    def changed(self, state, graph, seqs, scores, own_trail=None, informative=True):
        seqs, scores = np.asarray(seqs, np.int64), np.asarray(scores, np.float64)
        return step(self, state, graph, seqs, change(graph, seqs, scores, own_trail), own_trail, informative)

    loc.SequenceLocaliser.step = changed
    from service.evaluation import slam

    slam.slam_runs(data=a.data, half=a.half, routes=a.routes, methods=a.methods, json_path=a.json)


if __name__ == "__main__":
    main()
