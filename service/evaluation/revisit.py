"""Corridor-like revisits through the service's path: a second pass of the same frames under the same
conditions, with small image noise (docs/results.md §9.3).

    cortexloc eval revisit --folder ../shared/data/nordland_tiny_64x32/summer \
        --offset 0 --limit 894 --noise 8 --backbone efficientnet-lite0

The first pass (clean frames) is learned, the second (each frame plus Gaussian pixel noise of
`--noise` grey levels, re-encoded as PNG) is localised as one stream, by `service_path.replay` (the
service's path, `models.pipeline.observe`). Printed: R@1, the mean confidence of right and wrong
answers, the ROC AUC of confidence separating them, the precision and recall at the map's default
`revisit_threshold`, and the threshold that reaches precision 0.99.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np

from models.evaluation import sequences
from models.frontend.embedding import Embedder
from models.localisation.localiser import reaches
from service.evaluation import service_path
from service.maps.config import DEFAULT_RESIZE, DEFAULT_REVISIT_THRESHOLD
from service.settings import Settings


def noisy_png(path: Path, sigma: float, seed: int) -> bytes:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR).astype(np.float32)
    img += np.random.default_rng(seed).normal(0.0, sigma, img.shape)
    ok, buf = cv2.imencode(".png", np.clip(img, 0, 255).astype(np.uint8))
    assert ok
    return buf.tobytes()


def separability(right: np.ndarray, wrong: np.ndarray) -> float | None:
    """ROC AUC of confidence for right against wrong answers: P(a right one is more confident), ties half."""
    if not right.size or not wrong.size:
        return None
    greater = (right[:, None] > wrong[None, :]).mean()
    ties = (right[:, None] == wrong[None, :]).mean()
    return float(greater + 0.5 * ties)


def revisit(folder: Path, *, offset: int = 0, limit: int = 894, noise: float = 8.0,
            backbone: str = "efficientnet-lite0", resize: str = DEFAULT_RESIZE, seed: int = 0,
            json_path: Path | None = None) -> dict[str, Any]:
    """The experiment (module docstring); its summary, printed and written to `json_path` if given."""
    args = SimpleNamespace(folder=folder, offset=offset, limit=limit, noise=noise, backbone=backbone,
                           resize=resize, seed=seed, json=json_path)
    names = sequences.image_names(args.folder)[args.offset:args.offset + args.limit]
    paths = [args.folder / n for n in names]
    enc = Embedder({"backbone": args.backbone, "resize": args.resize})
    cache = Path(os.environ.get("CORTEXLOC_CACHE_DIR", Path.home() / ".cache" / "cortexloc")) / "features"
    db = sequences.cached_features(enc, paths, cache)
    q = np.concatenate([enc.embed([noisy_png(p, args.noise, args.seed + i) for p in paths[i:i + 16]]).features
                        for i in range(0, len(paths), 16)])
    preset = Settings.model_fields["default_preset"].default
    found = service_path.replay(db, q, encoder_id=enc.identity, backbone=args.backbone, preset=preset,
                                seed=args.seed)
    answered = found.best >= 0
    off_by = np.abs(found.best - np.arange(len(paths)))[answered]
    right = found.best == np.arange(len(paths))
    conf = found.confidence[answered]
    ok = right[answered]
    at = reaches(conf, DEFAULT_REVISIT_THRESHOLD)
    out = {"frames": len(paths), "answered": int(answered.sum()), "recall_at_1": float(ok.mean()),
           "confidence_right_mean": float(conf[ok].mean()) if ok.any() else None,
           "confidence_wrong_mean": float(conf[~ok].mean()) if (~ok).any() else None,
           "wrong": int((~ok).sum()),
           "wrong_within_one_row": int((off_by[~ok] <= 1).sum()),
           "roc_auc_right_vs_wrong": separability(conf[ok], conf[~ok]),
           "default_threshold": DEFAULT_REVISIT_THRESHOLD,
           "precision_at_default": float(ok[at].mean()) if at.any() else None,
           "recall_at_default": float(ok[at].sum() / ok.size),
           "operating_point_0.99": service_path.operating_point(conf, ok, 0.99),
           "config": {**{k: str(v) for k, v in vars(args).items()}, "encoder": enc.identity}}
    print(json.dumps(out, indent=2))
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    return out
