"""The cross-season tables of docs/results.md §7: every method at two path lengths, both metrics.

Run: `cortexloc eval nordland-tables --backbone efficientnet-lite0 [--seeds 3] [--json OUT]`.
nordland_tiny_64x32, summer database, winter query, squash resize, `cortexloc-default`, reset between
database and query, tolerance 0 (docs/design/science.md §8.5). Per window (tune, test and five windows of 200
files) and per ds (10, 20) it runs what `cortexloc eval images --reset --ds DS --offset O --limit N` runs:
cosine, sLSBH, HTM (one frame), openseqslam (the reference on grey pixels), and the same sequence matcher
on cosine, sLSBH and winner cells (cosine-seq, slsbh-seq, htm-seq). Every method is scored on the queries
with a full window of ds frames. The Temporal Memory's winner cells do not depend on ds: each seed's run
is kept for the second ds instead of repeated. Features and frames are read once for the whole route.
Nothing here is tuned: the reference's parameters are OpenSeqSLAM's, the memory's the service default.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from models import presets
from models.evaluation import seqslam as seq
from models.evaluation import sequences
from models.evaluation.datasets import nordland_dir
from models.frontend.embedding import Embedder

# Files (1-based, as in docs/design/science.md §10.1) -> (offset, count).
WINDOWS = {"1-200": (0, 200), "401-600": (400, 200), "801-1000": (800, 200), "1201-1400": (1200, 200),
           "1589-1788": (1588, 200), "test": (894, 894), "tune": (0, 894)}
METHODS = ["cosine", "slsbh", "htm", "openseqslam", "cosine-seq", "slsbh-seq", "htm-seq"]
PRESET = "cortexloc-default"


def _memoised_run_tm() -> None:
    """Keep each Temporal Memory run for the second ds (same codes, preset and seed: same winners)."""
    run = sequences.run_tm
    memo: dict[tuple, Any] = {}

    def cached(db_codes: np.ndarray, q_codes: np.ndarray, preset: str, seed: int, reset: bool, width: int,
               tm_overrides: dict[str, Any] | None = None) -> Any:
        key = (hashlib.sha256(db_codes.tobytes() + q_codes.tobytes()).hexdigest(), preset, seed, reset, width,
               json.dumps(tm_overrides, sort_keys=True))
        if key not in memo:
            memo[key] = run(db_codes, q_codes, preset, seed, reset, width, tm_overrides)
        return memo[key]

    sequences.run_tm = cached


def markdown(result: dict[str, Any], metric: str) -> str:
    """One markdown table of `metric` (e.g. "recall_at_1", "query_auc", "auc") from a --json result.

    Single-image methods are shown once (scored on the queries of the first ds); sequence methods as
    "first ds / second ds"; the last column is htm-seq minus slsbh-seq, what the memory adds.
    """
    windows = result["windows"]
    some = next(iter(windows.values()))
    ds_list = list(some)
    methods = result.get("methods", METHODS)
    fmt = "{:.4f}" if metric == "auc" else "{:.3f}"
    single = [m for m in methods if m in ("cosine", "slsbh", "htm")]
    multi = [m for m in methods if m not in single]
    # What the memory adds: each memory method against the same matcher on its own codes.
    gains = [(m, m.replace("htm", "slsbh")) for m in multi
             if "htm" in m and m.replace("htm", "slsbh") in multi]
    ds_label = " / ".join(map(str, ds_list))
    head = ["files", *single, *(f"{m} (ds {ds_label})" for m in multi), *(f"{a} − {b}" for a, b in gains)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for window, by_ds in windows.items():
        first = by_ds[ds_list[0]]
        cells = [window, *(fmt.format(first[m][f"{metric}_mean"]) for m in single)]
        for m in multi:
            vals = [fmt.format(by_ds[d][m][f"{metric}_mean"]) for d in ds_list]
            cells.append(" / ".join(vals))
        for a, b in gains:
            gain = [by_ds[d][a][f"{metric}_mean"] - by_ds[d][b][f"{metric}_mean"] for d in ds_list]
            cells.append(" / ".join(f"{g:+.3f}" for g in gain))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def run(*, backbone: str, seeds: int, ds: list[int], methods: list[str], windows: list[str],
        reverse_query: bool, crossing: bool, cache: Path, json_out: Path | None,
        markdown_of: Path | None) -> None:
    """The tables (module docstring); with `markdown_of`, print that JSON result's tables only."""
    if markdown_of:
        result = json.loads(markdown_of.read_text())
        for metric in ("recall_at_1", "query_auc", "auc"):
            print(f"\n{metric} ({result['backbone']}, {result['seeds']} seeds)\n" + markdown(result, metric))
        return
    root = nordland_dir()
    names = sequences.paired_names(root / "summer", root / "winter")
    enc = Embedder({"backbone": backbone, "resize": "squash"})
    feats = {season: sequences.cached_features(enc, [root / season / n for n in names], cache)
             for season in ("summer", "winter")}
    frames = {season: seq.load_frames([root / season / n for n in names]) for season in ("summer", "winter")}
    codes = presets.get(PRESET)["slsbh"]
    _memoised_run_tm()
    methods = sequences.with_ablations(methods)
    out: dict[str, Any] = {"backbone": enc.identity, "preset": PRESET, "seeds": seeds,
                           "methods": methods, "reverse_query": reverse_query, "crossing": crossing,
                           "windows": {}}
    for window in windows:
        o, n = WINDOWS[window]
        sl = slice(o, o + n)
        out["windows"][window] = {}
        for d in ds:
            r = sequences.image_experiment(
                feats["summer"][sl], feats["winter"][sl], methods=methods, preset=PRESET, k=codes["k"],
                s=codes["s"], seeds=seeds, reset=True, ds=d, reverse_query=reverse_query,
                crossing=crossing,
                frames=(frames["summer"][sl], frames["winter"][sl]))
            r.pop("first")
            out["windows"][window][d] = r["methods"]
            print(f"{backbone} {window} ds={d}: " + ", ".join(
                f"{m} R@1 {e['recall_at_1_mean']:.3f} qAUC {e['query_auc_mean']:.3f} AUC {e['auc_mean']:.4f}"
                for m, e in r["methods"].items()), flush=True)
            if json_out:
                json_out.write_text(json.dumps(out, indent=1))

