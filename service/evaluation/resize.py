"""Crop or squash: the two resize modes through the service's path, on frames of several shapes cut
from the same footage (issue 23; docs/results.md §9.6).

    cortexloc eval resize --db ../shared/data/nordland_tiny_64x32/summer \
        --query ../shared/data/nordland_tiny_64x32/winter --offset 894 --limit 300 --shapes 2:1,4:3

Each frame is cut to each shape by a centre crop of the stored frame (2:1 is the 64 x 32 frame itself;
4:3 keeps its middle 43 x 32), so the shapes show the same places. For each shape and mode the window
of the database traverse is learned and the same window of the query traverse localised as one stream
(`service_path.replay`: the step a served map's writer runs), with the map's features computed as a map
with that `resize` option computes them. Reported per run: the answers (a place once the warm-up is
over), right places (answers at the query's own row, tolerance 0) as a fraction of the answers, R@1
over the scored queries, and revisits (answers at or above the default revisit threshold) with how
many of them are right.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np

from models.evaluation import sequences
from models.frontend.embedding import Embedder
from models.frontend.images import RawFrame
from models.localisation.localiser import reaches
from service.evaluation import service_path
from service.maps.config import DEFAULT_REVISIT_THRESHOLD
from service.settings import Settings
from storage.base.files import sha256_file

MODES = ("crop", "squash")


def cut(rgb: np.ndarray, shape: str) -> np.ndarray:
    """The centre of an (H, W, 3) frame with width : height = `shape` ("4:3"), as wide as the frame
    allows (the full height when the frame is wider than the shape, else the full width)."""
    w_ratio, h_ratio = (float(x) for x in shape.split(":"))
    h, w = rgb.shape[:2]
    if w * h_ratio >= h * w_ratio:  # wider than the shape: keep the height
        new_w, new_h = min(w, round(h * w_ratio / h_ratio)), h
    else:
        new_w, new_h = w, min(h, round(w * h_ratio / w_ratio))
    top, left = (h - new_h) // 2, (w - new_w) // 2
    return np.ascontiguousarray(rgb[top:top + new_h, left:left + new_w])


def features(enc: Embedder, paths: list[Path], shape: str, cache: Path) -> np.ndarray:
    """(N, D) backbone features of `paths` cut to `shape`, cached by encoder, shape and file contents."""
    h = hashlib.sha256(f"{enc.identity}|{shape}".encode())
    for p in paths:
        h.update(sha256_file(p).encode())
    cached = cache / f"resize-eval-{h.hexdigest()}.npy"
    if cached.exists():
        return np.load(cached)
    frames = []
    for p in paths:
        rgb = cut(cv2.cvtColor(cv2.imread(str(p), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB), shape)
        frames.append(RawFrame(rgb.tobytes(), "rgb8", rgb.shape[1], rgb.shape[0]))
    out = np.concatenate([enc.embed(frames[i:i + 32]).features for i in range(0, len(frames), 32)])
    cache.mkdir(parents=True, exist_ok=True)
    np.save(cached, out.astype(np.float32))
    return out.astype(np.float32)


def resize_runs(db_dir: Path, query_dir: Path, *, offset: int = 0, limit: int = 300,
                shapes: list[str] | None = None, backbone: str | None = None,
                seeds: list[int] | None = None) -> None:
    """The experiment (module docstring), printed."""
    from service.frontend import resolve_backbone  # the service's own resolution of its default

    args = SimpleNamespace(db=db_dir, query=query_dir, offset=offset, limit=limit,
                           shapes=shapes or ["2:1", "4:3"], backbone=backbone, seeds=seeds or [1])
    settings = Settings.from_env()
    backbone = args.backbone or resolve_backbone(settings).backbone
    names = sequences.paired_names(args.db, args.query, args.offset, args.limit)
    cache = Path(os.environ.get("CORTEXLOC_CACHE_DIR", Path.home() / ".cache" / "cortexloc")) / "features"
    n = len(names)
    scored = np.zeros(n, bool)
    scored[10:] = True  # past any warm-up (the localiser's is 5 frames)
    print(f"backbone {backbone}, preset {settings.default_preset}, frames {names[0]} .. {names[-1]} ({n}), "
          f"map seeds {args.seeds}, revisit threshold {DEFAULT_REVISIT_THRESHOLD}")
    print(f"{'shape':<6} {'resize':<7} {'seed':>4} {'answers':>7} {'right':>6} {'R@1':>6} {'revisits':>8} "
          f"{'right revisits':>14}")
    for shape in args.shapes:
        for mode in MODES:
            enc = Embedder({"backbone": backbone, "resize": mode})
            db = features(enc, [args.db / x for x in names], shape, cache)
            q = features(enc, [args.query / x for x in names], shape, cache)
            for seed in args.seeds:
                found = service_path.replay(db, q, encoder_id=enc.identity, backbone=backbone,
                                            preset=settings.default_preset, seed=seed,
                                            create={"resize": mode})
                answered = found.best >= 0
                right = answered & (found.best == np.arange(n))
                revisit = answered & reaches(found.confidence, DEFAULT_REVISIT_THRESHOLD)
                print(f"{shape:<6} {mode:<7} {seed:>4} {int(answered.sum()):>7} "
                      f"{right.sum() / max(int(answered.sum()), 1):>6.3f} {right[scored].mean():>6.3f} "
                      f"{int(revisit.sum()):>8} {int((revisit & right).sum()):>14}")

