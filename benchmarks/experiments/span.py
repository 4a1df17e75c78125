"""Experiments of docs/results.md §10.13: the span (docs/design/science.md §11.11) in the localise mode, a
window's summer frames learned as one traverse and the same window driven again by another stream that
localises, read at several margins and span caps from one run (the span is read from the stream's beam
after each frame, so the answers are the run's, whatever the margin), one JSON line per window and seed.

    cortexloc eval span flat,winter 1,42 '{}' > span.jsonl
    cortexloc eval span sum < span.jsonl    # totals per kind, margin and cap

Arguments: lap-2 kinds (`winter`: the window in winter; `flat`: in winter, blurred and its contrast cut
to 35 %, `stress.variant`'s low-texture frames, a featureless other season), map seeds, and the maps'
localiser options as JSON. Windows: every 200-file window of both halves slid by 100
(`stress.windows`), from ../shared/data/nordland_tiny_64x32 (labels = file index). Each line: the
window, `answered` (lap-2 answers past the warm-up), and per margin m (in temperatures) and cap S:
`called` (confident, informative answers whose span at m is at most S: the revisits at that setting),
`right` (of those, named within 1 file of the truth) and `inside` (the true file within 1 of a row of
the span); S = 4096 is no gate. A revisit is called at the map's `revisit_threshold`.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from models.evaluation import datasets
from models.localisation.localiser import reaches
from models.pipeline import Stream, observe
from service.evaluation import service_path, stress
from service.evaluation.slam import encoder_setup

MARGINS = (1.0, 1.25, 1.5, 2.0)
CAPS = (2, 3, 4, 4096)


def run(frames: stress.Frames, kind: str, lo: int, seed: int, map_conf: dict[str, Any]) -> dict[str, Any]:
    idx = range(lo, lo + stress.WINDOW)
    lap1 = [stress.png(frames.image("summer", i)) for i in idx]
    lap2 = [stress.png(frames.image("winter", i)) if kind == "winter" else
            stress.variant(frames.image("winter", i), kind, 7 + 7919 * j + i) for j, i in enumerate(idx)]
    pngs = lap1 + lap2
    feats, contrast = frames.features(pngs), service_path.contrasts(pngs)
    n = len(lap1)
    model, hasher, config = service_path._model(feats.shape[1], max_observations=n, seed=seed, memory="tm",
                                                create=None,
                                                **{k: v for k, v in map_conf.items() if k != "encoder_id"})
    codes: dict[int, np.ndarray] = {}
    database, query = Stream(), Stream()
    Y = hasher.project(feats)
    for i in range(n):
        codes[i + 1] = observe(model, database, Y[i], learn=True, stream="database", top_k=0, seq=i + 1,
                               code_of=codes.__getitem__, contrast=float(contrast[i])).code
    graph, conf = model.place_map.graph, model.place_map.options
    counts = {f"{m}/{s}": {"called": 0, "right": 0, "inside": 0} for m in MARGINS for s in CAPS}
    answered = 0
    for j in range(n, 2 * n):
        place = observe(model, query, Y[j], learn=False, stream="query", top_k=0, code_of=codes.__getitem__,
                        contrast=float(contrast[j])).place
        if place is None:
            continue
        answered += 1
        if not (place.informative and reaches(place.confidence, config.revisit_threshold)):  # no span gate
            continue
        truth = lo + j - n
        state = query.localiser
        assert state is not None
        live = int((state.rows >= 0).sum())
        rows, scores = state.rows[:live], state.scores[:live]
        for m in MARGINS:
            near = rows[scores >= scores[0] - m * float(conf.temperature)]
            _, first = np.unique(graph.place[near], return_index=True)
            span_labels = lo + near[first] - 1
            for s in CAPS:
                if first.size <= s:
                    c = counts[f"{m}/{s}"]
                    c["called"] += 1
                    c["right"] += int(abs(lo + place.seq - 1 - truth) <= 1)
                    c["inside"] += int(bool((np.abs(span_labels - truth) <= 1).any()))
    return {"kind": kind, "lo": lo, "seed": seed, "answered": answered, "counts": counts}


def total(lines: list[dict[str, Any]]) -> None:
    """Print, per kind, margin and cap, the totals over the lines: precision of the revisits called
    (`right` / `called`), the share of them whose span holds the truth, and recall over the answers."""
    for kind in sorted({line["kind"] for line in lines}):
        mine = [line for line in lines if line["kind"] == kind]
        answered = sum(line["answered"] for line in mine)
        for key in mine[0]["counts"]:
            c = {k: sum(line["counts"][key][k] for line in mine) for k in ("called", "right", "inside")}
            print(kind, key, c, "precision", round(c["right"] / max(c["called"], 1), 3), "recall",
                  round(c["right"] / max(answered, 1), 3))


def main(*, kinds: list[str], seeds: list[int], localiser: dict | None) -> None:
    """`cortexloc eval span KINDS SEEDS [LOCALISER]`: one JSON line per kind, window and seed."""
    enc, cache, map_conf = encoder_setup(None, localiser)
    frames = stress.Frames(Path(datasets.nordland_dir()), enc, cache)
    for kind in kinds:
        for _, lo in stress.windows(False):
            for seed in seeds:
                t = time.time()
                out = run(frames, kind, lo, seed, map_conf)
                out["s"] = round(time.time() - t, 1)
                print(json.dumps(out), flush=True)
