"""Dense versus very sparse sLSBH projection: is the cheaper one as good? (issue: front end, §3)

Run: `cortexloc eval projection-parity [--windows 0,1000] [--n 200] [--seeds 3]`.
Encodes Nordland summer (database) and winter (query) frames once with the AlexNet conv3 encoder, then
hashes the same features with dense and sparse projections of several seeds, at s = 0.25 and
s = 0.025, and reports the pairwise-sLSBH AUC (S = Dice, GT = same file name) of each. The sparse
projection may become the default only if its AUC matches the dense one within the seed spread.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from models import sdr
from models.evaluation import metrics
from models.evaluation.datasets import shared_data_dir
from models.frontend import slsbh
from models.frontend.embedding import Embedder


def _features(enc: Embedder, folder: Path, names: list[str]) -> np.ndarray:
    out = []
    for i in range(0, len(names), 32):
        out.append(enc.embed([(folder / n).read_bytes() for n in names[i:i + 32]]).features)
    return np.concatenate(out)


def run(*, windows: list[int], n: int, seeds: int, resize: str, backbone: str, json_out: Path | None) -> None:
    """AUC of dense and sparse projections per window start in `windows` (module docstring)."""
    root = shared_data_dir() / "nordland_tiny_64x32"
    names = sorted(p.name for p in (root / "summer").glob("*.png"))
    enc = Embedder({"backbone": backbone, "resize": resize})  # features only: no projection built
    results = []
    for start in windows:
        window = names[start:start + n]
        db, q = _features(enc, root / "summer", window), _features(enc, root / "winter", window)
        gt = np.eye(len(window), dtype=bool)
        cos = metrics.auc(*metrics.pr_curve(db @ q.T, gt))
        for s in (0.25, 0.025):
            row = {"window": start, "n": len(window), "s": s, "cosine_auc": cos, "encoder": enc.identity}
            for kind in ("dense", "sparse"):
                aucs = []
                for seed in range(seeds):
                    P = (slsbh.make_projection(db.shape[1], 1024, seed) if kind == "dense"
                         else slsbh.make_sparse_projection(db.shape[1], 1024, seed))
                    h = slsbh.Hasher(P, s)
                    S = sdr.dice_matrix(list(h(db)), list(h(q)))
                    aucs.append(metrics.auc(*metrics.pr_curve(S, gt)))
                row[kind] = {"auc_mean": float(np.mean(aucs)), "auc_min": float(np.min(aucs)),
                             "auc_max": float(np.max(aucs))}
            results.append(row)
            print(f"{enc.identity} window {start}+{len(window)} s={s}: cosine {cos:.4f}; "
                  f"dense {row['dense']['auc_mean']:.4f} "
                  f"[{row['dense']['auc_min']:.4f}, {row['dense']['auc_max']:.4f}]; sparse "
                  f"{row['sparse']['auc_mean']:.4f} [{row['sparse']['auc_min']:.4f}, "
                  f"{row['sparse']['auc_max']:.4f}]", flush=True)
    if json_out:
        json_out.write_text(json.dumps(results, indent=2))

