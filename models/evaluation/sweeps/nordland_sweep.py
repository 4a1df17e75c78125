"""Parameter search for the cross-season default (issue: cross-season evaluation,
docs/design/science.md §8.5).

Run: `cortexloc eval nordland-sweep [--split tune] [--json OUT]` (one seed: a sweep
ranks).
Protocol `tune` (files 1-894 of nordland_tiny_64x32, summer database, winter query, reset between them,
squash resize): every configuration of sLSBH density, stream adaptation and Temporal Memory parameters
is run on both backbones (random-weight AlexNet conv3, ImageNet EfficientNet-Lite0 stage 7). Per
configuration it prints HTM AUC / R@1 single-image and through the seqslam filter (`htm-seq`), the sLSBH
AUC on the same codes (single-image and filtered), and the predicted fraction of query columns in true
and in shuffled order (docs/design/science.md §3.8). The objective is the mean `htm-seq` AUC over the two
backbones: single-image HTM AUC stays within noise of sLSBH everywhere on these frames (docs/results.md §7),
so the sequence-compared winner cells are what tell configurations apart. Choose on `tune`; report on
`test` with `cortexloc eval images`.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from typing import Any

import numpy as np

from models import sdr
from models.evaluation import sequences
from models.evaluation.datasets import shared_data_dir
from models.evaluation.seqslam import full_window, seqslam
from models.frontend import slsbh
from models.frontend.embedding import Embedder

K = 1024  # sLSBH projections: 2K = 2048 TM columns
SPLITS = {"tune": (0, 894), "test": (894, 894)}
BACKBONES = ("alexnet", "efficientnet-lite0")  # the experiment's choice, each a registered backbone
GRID: dict[str, list[Any]] = {
    "s": [0.02, 0.05, 0.1, 0.15, 0.2],
    "adapt_tau": [0, 20],
    "activationThreshold": [8, 14, 20, 24],
    "minThreshold": [2, 6, 10],
    "initialPermanence": [0.55],  # one-shot; gradual (0.21) lost on every backbone in the first sweep
    "cellsPerColumn": [4],  # 8 cells gave the same AUC at twice the memory
}


def load_features(split: str, cache_dir: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{backbone: (summer, winter)} features of the split, from the shared feature cache."""
    root = shared_data_dir() / "nordland_tiny_64x32"
    offset, limit = SPLITS[split]
    # The whole route's features (the cache entry `cortexloc eval images` makes), then the split.
    names = sequences.paired_names(root / "summer", root / "winter")
    out = {}
    for backbone in BACKBONES:
        enc = Embedder({"backbone": backbone, "resize": "squash"})
        out[backbone] = tuple(sequences.cached_features(enc, [root / season / n for n in names], cache_dir)
                              [offset:offset + limit] for season in ("summer", "winter"))
    return out


def _codes(db: np.ndarray, q: np.ndarray, s: float, adapt_tau: int, seed: int) -> tuple[np.ndarray, ...]:
    hasher = slsbh.Hasher(slsbh.make_projection(db.shape[1], K, seed), s)
    return sequences.codes(hasher, db, adapt_tau), sequences.codes(hasher, q, adapt_tau)


def run(*, split: str, cache: Path, json_out: Path | None, codes_only: bool, grid: list[str]) -> None:
    """The search (module docstring); `grid` items KEY=V1,V2 replace GRID[KEY] (ValueError: unknown KEY)."""
    for item in grid:
        key, _, values = item.partition("=")
        if key not in GRID:
            raise ValueError(f"--grid: unknown key {key!r}; known: {', '.join(GRID)}")
        GRID[key] = [type(GRID[key][0])(v) for v in values.split(",")]
    feats = load_features(split, cache)
    tm_keys = [k for k in GRID if k not in ("s", "adapt_tau")]
    rows = []
    # Codes depend on (backbone, s, adaptation) only: hash once, then run every TM configuration on them.
    for s, adapt_tau in itertools.product(GRID["s"], GRID["adapt_tau"]):
        codes = {b: _codes(db, q, s, adapt_tau, seed=1) for b, (db, q) in feats.items()}
        dice = {b: sdr.dice_matrix(list(c[0]), list(c[1])) for b, c in codes.items()}
        # Every method on the queries with a full path window, as `cortexloc eval images` scores them.
        cols = full_window(len(next(iter(dice.values()))))
        base = {b: sequences.evaluate(D, 0, columns=cols) for b, D in dice.items()}
        base_seq = {b: sequences.evaluate(seqslam(D), 0, columns=cols) for b, D in dice.items()}
        for b, D in dice.items():
            ones = codes[b][0].shape[1]
            off = ~np.eye(len(D), dtype=bool)
            print(f"codes s={s} adapt_tau={adapt_tau} {b}: bits shared of {ones}: same place "
                  f"{np.diag(D).mean() * ones:.1f}, different places {D[off].mean() * ones:.1f}; sLSBH AUC "
                  f"{base[b]['auc']:.4f}, R@1 {base[b]['recall_at_1']:.3f}", flush=True)
        if codes_only:
            continue
        for values in itertools.product(*(GRID[k] for k in tm_keys)):
            tm = dict(zip(tm_keys, values, strict=True))
            conf = {"s": s, "adapt_tau": adapt_tau, **tm}
            per_backbone = {}
            for backbone, (db_codes, q_codes) in codes.items():
                db_w, q_w, info = sequences.run_tm(db_codes, q_codes, "cortexloc-grid", seed=1, reset=True,
                                                   width=2 * K, tm_overrides=tm)
                T = sdr.dice_matrix(db_w, q_w)
                r = sequences.evaluate(T, 0, columns=cols)
                r_seq = sequences.evaluate(seqslam(T), 0, columns=cols)
                per_backbone[backbone] = {
                    "htm_auc": r["auc"], "htm_r1": r["recall_at_1"], "htm_seq_auc": r_seq["auc"],
                    "htm_seq_r1": r_seq["recall_at_1"], "slsbh_seq_auc": base_seq[backbone]["auc"],
                    "slsbh_auc": base[backbone]["auc"],
                    "slsbh_r1": base[backbone]["recall_at_1"], "predicted": info["query_predicted_fraction"],
                    "chance": info["chance_predicted_fraction"], "mib": info["bytes"] / 2**20}
            score = float(np.mean([v["htm_seq_auc"] for v in per_backbone.values()]))
            rows.append({"conf": conf, "objective": score, "backbones": per_backbone})
            print(f"{conf} objective {score:.4f} | " + " | ".join(
                f"{b[:4]}: htm {v['htm_auc']:.4f}/{v['htm_r1']:.3f} htm-seq {v['htm_seq_auc']:.4f} slsbh "
                f"{v['slsbh_auc']:.4f}/{v['slsbh_r1']:.3f} slsbh-seq {v['slsbh_seq_auc']:.4f} "
                f"pred {v['predicted']:.2f} chance {v['chance']:.2f}"
                for b, v in per_backbone.items()), flush=True)
    rows.sort(key=lambda r: r["objective"])
    for adapt in GRID["adapt_tau"] if rows else ():
        best = [r for r in rows if r["conf"]["adapt_tau"] == adapt][-1]
        print(f"best with adapt_tau={adapt}: {best['conf']} objective {best['objective']:.4f}")
    if json_out:
        json_out.write_text(json.dumps({"split": split, "rows": rows}, indent=1))

