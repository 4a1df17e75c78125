"""The Temporal Memory in its own setting, on routes that are not saturated (docs/results.md §10.2):
`service-slam` against `service-slam-without-tm` over several map seeds on harder, shorter routes.

    cortexloc eval slam-ablation --data ../shared/data/nordland_tiny_64x32 --seeds 3

Routes, each ONE learning stream (`service_path.slam_replay`), from each Nordland half (`tune`, `test`):
- `seasons@o`: 100 summer frames from half-relative file o, then the same 100 winter frames (o = 0,
  200, 400, 600, 790): cross-season short windows, where few frames mean little sequence support;
- `noise σ@o`: the same 100 summer frames twice, the second with pixel noise of σ = 24 or 48 grey
  levels (re-encoded PNGs, as `revisit_eval`).
Scored at the map's threshold (`models.evaluation.slam.score`, tolerance 1): lap-2 R@1 of `place`,
per-query AUC, recall; printed per route, memory and seed, then the median per-seed difference (tm −
none) and how many of the route-seed pairs the memory wins, ties and loses on R@1.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from models.evaluation import slam
from models.frontend.embedding import Embedder
from service.evaluation import service_path
from service.evaluation.slam import HALVES, Frames

OFFSETS = (0, 200, 400, 600, 790)
WINDOW = 100
SIGMAS = (24.0, 48.0)


def routes(frames: Frames) -> dict[str, dict[str, Any]]:
    """{name: {"feats" (2W, D), "contrast" (2W,), "labels" (2W,), "laps" (2W,)}} of one half."""
    out = {}
    for o in OFFSETS:
        idx = np.arange(o, o + WINDOW)
        summer = (frames.feats["summer"][idx], [frames.images["summer"][i] for i in idx])
        laps = {f"seasons@{o}": (frames.feats["winter"][idx], [frames.images["winter"][i] for i in idx])}
        for sigma in SIGMAS:
            laps[f"noise {sigma:g}@{o}"] = frames.noisy(idx, sigma, 7 + o)
        for name, (f2, png2) in laps.items():
            pngs = summer[1] + list(png2)
            out[name] = {"feats": np.concatenate([summer[0], f2]),
                         "contrast": service_path.contrasts(pngs),
                         "labels": np.r_[idx, idx] + frames.lo,
                         "laps": np.r_[np.zeros(WINDOW, np.int64), np.ones(WINDOW, np.int64)]}
    return out


def ablation(data: Path, seeds: int = 3, backbone: str = "efficientnet-lite0-s5",
             json_path: Path | None = None) -> None:
    """The experiment (module docstring), printed per run and summarised; `json_path`: every run too."""
    from service.settings import Settings

    enc = Embedder({"backbone": backbone, "resize": "squash"})
    cache = Path(os.environ.get("CORTEXLOC_CACHE_DIR", Path.home() / ".cache" / "cortexloc")) / "features"
    preset = Settings.from_env().default_preset
    rows: list[dict[str, Any]] = []
    for half in HALVES:
        for name, r in routes(Frames(data, half, enc, cache)).items():
            for seed in range(1, seeds + 1):
                for memory in ("tm", "none"):
                    found, t = service_path.slam_replay(r["feats"], encoder_id=enc.identity,
                                                        backbone=backbone, preset=preset, seed=seed,
                                                        memory=memory, contrast=r["contrast"])
                    s = slam.score(found.best, found.confidence, r["labels"], t, 1, r["laps"])
                    lap2 = s["lap"][1]
                    row = {"half": half, "route": name, "seed": seed, "memory": memory,
                           "lap1_false": s["lap"][0]["false_revisits"], "r1": lap2["recall_at_1"],
                           "auc": lap2["query_auc"], "recall": lap2["recall"],
                           "precision": lap2["precision"]}
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    _summary(rows)
    if json_path:
        json_path.write_text(json.dumps(rows) + "\n")


def _summary(rows: list[dict[str, Any]]) -> None:
    """Per route family and half: median R@1 and AUC with and without the memory, the median per-seed
    difference, and the memory's wins / ties / losses on R@1."""
    key = {(r["half"], r["route"], r["seed"], r["memory"]): r for r in rows}
    for half in HALVES:
        for family in ("seasons", *(f"noise {s:g}" for s in SIGMAS)):
            pairs = [(key[(h, n, s, "tm")], key[(h, n, s, "none")]) for (h, n, s, m) in key
                     if h == half and m == "tm" and n.split("@")[0] == family]
            if not pairs:
                continue
            d_r1 = np.array([a["r1"] - b["r1"] for a, b in pairs])
            d_auc = np.array([a["auc"] - b["auc"] for a, b in pairs])
            wins = f"{int((d_r1 > 0).sum())}/{int((d_r1 == 0).sum())}/{int((d_r1 < 0).sum())}"
            print(f"{half} {family}: R@1 tm {np.median([a['r1'] for a, _ in pairs]):.3f} "
                  f"none {np.median([b['r1'] for _, b in pairs]):.3f}, median diff {np.median(d_r1):+.3f} "
                  f"(mean {d_r1.mean():+.3f}); AUC diff median {np.median(d_auc):+.3f}; tm wins/ties/losses "
                  f"{wins} of {len(pairs)}; "
                  f"lap-1 false revisits tm {sum(a['lap1_false'] for a, _ in pairs)} "
                  f"none {sum(b['lap1_false'] for _, b in pairs)}")
