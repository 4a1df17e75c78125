"""Do the backbone runtimes compute the same codes? The torch reference against ONNX Runtime on the real
Nordland route (issue 24, docs/design/science.md §6.1).

Run: `cortexloc eval runtime-parity [--windows 1-200,401-600,...] [--json OUT]` (default: every
window of `models.evaluation.nordland_tables.WINDOWS`). nordland_tiny_64x32, summer learned, winter
localised, squash resize, the service default backbone and preset, one seed. Per frame, the overlap
|a AND b| / |a| of the sLSBH codes the two runtimes' features give under the same projection (the
preset's k, s and seed); per window, the `service` method's R@1 (`service_path.experiment`: the
writer's own step, `models.pipeline.observe`) on each runtime's features, with the same map seed. The
parity test (tests/models/frontend/test_runtime_parity.py) runs the five 200-frame windows.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from models import presets
from models.evaluation import seqslam, sequences
from models.evaluation.datasets import nordland_dir
from models.evaluation.nordland_tables import WINDOWS
from models.frontend import slsbh
from models.frontend.embedding import Embedder
from service.evaluation import service_path

__all__ = ["BACKBONE", "PRESET", "code_overlap", "encode_route", "parity", "route_features"]

BACKBONE = "efficientnet-lite0-s5"
PRESET = "cortexloc-default"
RUNTIMES = ("torch", "onnxruntime")


def route_features(runtime: str, paths: Sequence[Path], backbone: str = BACKBONE) -> tuple[np.ndarray, str]:
    """(N, D) float32 features of `paths` on `runtime` (no cache: the cache is keyed by the encoder
    identity, which both runtimes share) and the encoder identity."""
    enc = Embedder({"backbone": backbone, "resize": "squash", "runtime": runtime})
    parts = [enc.embed([p.read_bytes() for p in paths[i:i + 32]]).features for i in range(0, len(paths), 32)]
    return np.concatenate(parts), enc.identity


def code_overlap(a: np.ndarray, b: np.ndarray, preset: str = PRESET) -> np.ndarray:
    """(N,) per-frame |codes(a) AND codes(b)| / |codes(a)| under the preset's projection, for features
    a, b (N, D)."""
    p = presets.SlsbhOptions.of(presets.slsbh_params(preset))
    seed = 0 if p.seed is None else int(p.seed)  # None: each map draws its own; any one will do
    hasher = slsbh.Hasher(slsbh.make_projection(a.shape[1], int(p.k), seed), float(p.s))
    ca, cb = hasher(a), hasher(b)
    return np.array([np.intersect1d(x, y, assume_unique=True).size / x.size
                     for x, y in zip(ca, cb, strict=True)])


Encoded = tuple[dict[str, dict[str, np.ndarray]], dict[str, list[int]], str]


def encode_route(windows: Sequence[str]) -> Encoded:
    """Features of the frames `windows` cover, on each runtime: ({runtime: {season: (N, D)}}, {window:
    its rows in them}, the encoder identity)."""
    root = nordland_dir()
    names = sequences.paired_names(root / "summer", root / "winter")
    spans = {w: list(range(len(names)))[WINDOWS[w][0]:WINDOWS[w][0] + WINDOWS[w][1]] for w in windows}
    used = sorted({i for span in spans.values() for i in span})
    row = {i: j for j, i in enumerate(used)}
    feats: dict[str, dict[str, np.ndarray]] = {}
    identity = ""
    for runtime in RUNTIMES:
        feats[runtime] = {}
        for season in ("summer", "winter"):
            paths = [root / season / names[i] for i in used]
            feats[runtime][season], identity = route_features(runtime, paths)
    return feats, {w: [row[i] for i in span] for w, span in spans.items()}, identity


def parity(windows: Sequence[str], ds: int = 10, seed: int = 0,
           encoded: Encoded | None = None) -> dict[str, Any]:
    """Code overlap and service R@1 of torch and ONNX Runtime on `windows` (names of `WINDOWS`).

    Args:
        encoded: `encode_route(windows)`, when already computed.

    Returns:
        {"overlap_mean", "overlap_min", "frames", "windows": {name: {"torch": R@1, "onnxruntime": R@1}}}.
    """
    feats, rows_of, identity = encoded if encoded is not None else encode_route(windows)
    overlap = np.concatenate([code_overlap(feats["torch"][s], feats["onnxruntime"][s])
                              for s in ("summer", "winter")])
    out: dict[str, Any] = {"backbone": identity, "preset": PRESET, "ds": ds, "seed": seed,
                           "frames": int(overlap.size), "overlap_mean": float(overlap.mean()),
                           "overlap_min": float(overlap.min()), "windows": {}}
    for w, rows in rows_of.items():
        out["windows"][w] = {}
        for runtime in RUNTIMES:
            db, q = feats[runtime]["summer"][rows], feats[runtime]["winter"][rows]
            summary, _ = service_path.experiment(
                db, q, methods=["service"], columns=seqslam.full_window(len(q), ds), tolerance=0, gt=None,
                seeds=1, seed=seed, reverse_query=False,
                map_conf={"encoder_id": identity, "backbone": BACKBONE, "preset": PRESET})
            out["windows"][w][runtime] = summary["service"]["recall_at_1_mean"]
    return out


def report(windows: list[str], json_path: Path | None = None) -> dict[str, Any]:
    """`parity` over `windows`, printed, and written to `json_path` if given."""
    result = parity(windows)
    print(f"{result['backbone']}: code overlap mean {result['overlap_mean']:.4f}, "
          f"min {result['overlap_min']:.4f} over {result['frames']} frames")
    for w, r in result["windows"].items():
        print(f"{w}: service R@1 torch {r['torch']:.3f}, onnxruntime {r['onnxruntime']:.3f}")
    if json_path:
        json_path.write_text(json.dumps(result, indent=1))
    return result
