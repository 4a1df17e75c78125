"""The searches behind the localiser's defaults and the backbone block (docs/results.md §8.3, §8.4).

Run:
    cortexloc eval localiser-sweep grid [--grid decay=0.9,0.95 --grid top_k=50,100]
    cortexloc eval localiser-sweep layers [--split tune] [--blocks stage5-pool2,...]

nordland_tiny_64x32, summer database, winter query, squash resize, tolerance 0, the ds-10 queries of
docs/results.md §7. `grid`: `online-cosine` on EfficientNet-Lite0 stage 7 over every combination of
localiser options (docs/design/science.md §11.3), R@1 and query AUC. `layers`: one forward pass of
EfficientNet-Lite0 per image keeps several blocks; per block, single-image R@1 / query AUC of cosine and
sLSBH (`cortexloc-default` k and s, projection seed 1) and the same through the localiser, with the
dense projection plus Temporal Memory bytes per map. A block `stageN-pool2` is stage N averaged over
2x2 cells (half the side, a quarter of the values). Choose on `tune`; check once on `test`.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.nn import functional

from models import presets, sdr
from models.evaluation import online, sequences
from models.evaluation.datasets import nordland_dir
from models.evaluation.seqslam import full_window
from models.frontend import images, slsbh
from models.frontend.backbones.efficientnet_lite0 import LAYERS
from models.frontend.embedding import Embedder

SPLITS = {"tune": (0, 894), "test": (894, 894)}
BLOCKS = ("stage4", "stage4-pool2", "stage5", "stage5-pool2", "stage6", "stage7", "head-gap")
TM_BYTES = 62.5 * 2**20  # cortexloc-default's preallocated Temporal Memory (docs/results.md §7.7)


def _describe(model: torch.nn.Module, x: torch.Tensor, blocks: list[str]) -> dict[str, np.ndarray]:
    """{block: (N, D) L2-normalised descriptors} of one preprocessed batch, the network run once."""
    h = functional.relu6(model._bn0(model._conv_stem(x)))
    maps, done = {}, 0
    for stage in ("stage4", "stage5", "stage6", "stage7"):
        for b in model._blocks[done:LAYERS[stage]]:
            h = b(h)
        done = LAYERS[stage]
        maps[stage] = h
    maps["head"] = functional.relu6(model._bn1(model._conv_head(h)))
    out = {}
    for block in blocks:
        name, _, pool = block.partition("-")
        m = maps[name]
        m = m.mean(dim=(2, 3)) if pool == "gap" else functional.avg_pool2d(m, 2) if pool == "pool2" else m
        out[block] = functional.normalize(m.flatten(1), dim=1).numpy()
    return out


def layer_features(blocks: list[str], offset: int, limit: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{block: (summer, winter) descriptors} of files offset .. offset + limit - 1."""
    root = nordland_dir()
    names = sequences.paired_names(root / "summer", root / "winter", offset, limit)
    enc = Embedder({"backbone": "efficientnet-lite0", "resize": "squash"})
    model = enc.backbone.module
    out: dict[str, list[list[np.ndarray]]] = {b: [[], []] for b in blocks}
    for s, season in enumerate(("summer", "winter")):
        for i in range(0, len(names), 32):
            x = np.stack([images.preprocess(images.decode((root / season / n).read_bytes()), mode="squash",
                                            mean=enc.input_mean, std=enc.input_std) for n in names[i:i + 32]])
            with torch.inference_mode():
                for b, f in _describe(model, torch.from_numpy(x), blocks).items():
                    out[b][s].append(f)
    return {b: (np.concatenate(v[0]), np.concatenate(v[1])) for b, v in out.items()}


def scores(S: np.ndarray, conf: dict[str, Any] | None = None) -> tuple[float, float, float, float]:
    """(R@1, query AUC) single-image, then (R@1, query AUC) through the localiser, ds-10 queries."""
    cols = full_window(S.shape[1], 10)
    single = sequences.evaluate(S, 0, None, cols)
    found = online.localise(S, conf)
    loc = sequences.evaluate(found.S, 0, None, cols, (found.best, found.confidence))
    return single["recall_at_1"], single["query_auc"], loc["recall_at_1"], loc["query_auc"]


def run(*, what: str, split: str, grid: list[str], blocks: list[str], cache: Path) -> None:
    """`what` grid: the localiser over every combination of `grid` (OPTION=V1,V2 items); layers: a table of
    `blocks` (module docstring)."""
    offset, limit = SPLITS[split]
    if what == "grid":
        root = nordland_dir()
        names = sequences.paired_names(root / "summer", root / "winter", offset, limit)
        enc = Embedder({"backbone": "efficientnet-lite0", "resize": "squash"})
        db, q = (sequences.cached_features(enc, [root / season / n for n in names], cache)
                 for season in ("summer", "winter"))
        S = db @ q.T
        grid = {k: [tuple(float(x) for x in v.split("/")) if "/" in v else float(v) for v in vals.split(",")]
                for k, _, vals in (g.partition("=") for g in grid)}
        for values in itertools.product(*grid.values()):
            conf = {k: int(v) if k in ("top_k", "beam", "warmup", "exclusion") else v
                    for k, v in zip(grid, values, strict=True)}
            print(conf, "online-cosine R@1 {2:.3f} query AUC {3:.3f}".format(*scores(S, conf)), flush=True)
        return
    p = presets.get("cortexloc-default")["slsbh"]
    print("| block | D | projection + TM | cosine | online-cosine | slsbh | online-slsbh |")
    print("|---|---|---|---|---|---|---|")
    for block, (db, q) in layer_features(blocks, offset, limit).items():
        hasher = slsbh.Hasher(slsbh.make_projection(db.shape[1], p["k"], 1), p["s"])
        dice = sdr.dice_matrix(list(sequences.codes(hasher, db)), list(sequences.codes(hasher, q)))
        c, d = scores(db @ q.T), scores(dice)
        mib = (db.shape[1] * p["k"] * 4 + TM_BYTES) / 2**20
        cells = [f"{a:.3f} / {b:.3f}" for a, b in ((c[0], c[1]), (c[2], c[3]), (d[0], d[1]), (d[2], d[3]))]
        print(f"| {block} | {db.shape[1]} | {mib:.1f} MiB | " + " | ".join(cells) + " |", flush=True)

