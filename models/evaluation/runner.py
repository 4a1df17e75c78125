"""Grid-world experiments: the protocol of docs/design/science.md §2.4 run over seeds, aggregated per §8.6.

One pass over all observations with learning on at every step and no reset; each step yields the input
SDR (pairwise / InputSDR), the MCN winner cells and the TM winner cells; each descriptor sequence is
scored against place identity with `paper` or `clean` scoring (§8.4).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from models import presets
from models.evaluation import metrics, online, plots, seqslam
from models.evaluation.gridworld import GridData
from models.memory.mcn import MCN, resolve_in_con
from models.memory.temporal_memory import TemporalMemory
from models.sdr import dice_matrix

METHODS = ("pairwise", "pairwise-seq", "mcn", "htm", "online-pairwise", "online-htm")
# What the memory adds beyond any sequence matcher: the same matcher on the input codes runs beside it.
ABLATIONS = {"htm": ("pairwise", "pairwise-seq"), "mcn": ("pairwise", "pairwise-seq"),
             "online-htm": ("online-pairwise",)}
_METRICS = ("auc", "recall_at_1", "recall_at_5", "recall_at_100p", "query_auc", "query_recall_at_100p")


def run_htm(data: GridData, preset: str, seed: int) -> tuple[list[np.ndarray], dict[str, Any]]:
    """Feed the grid sequence to a Temporal Memory (learning on, no reset).

    Returns:
        winners: one (w,) sorted cell array per step; info: predicted-column fraction, sizes, warnings.
    """
    tm = TemporalMemory(presets.tm_options(preset, {"seed": int(seed), "columnDimensions": data.width}))
    winners, predicted, active, predictive = [], 0, 0, 0
    for x in data.sdrs:
        winners.append(tm.compute(x, learn=True))
        predicted += tm.context.stats.predicted_columns
        active += tm.context.stats.active_columns
        predictive += tm.context.stats.predictive_cells
    size = tm.size()
    return winners, {
        "predicted_column_fraction": predicted / max(active, 1),
        "predictive_cells_per_step": predictive / max(len(data.sdrs), 1),
        "segments": size["segments"],
        "synapses": size["synapses"],
        "bytes": size["bytes"],
        "warnings": tm.warnings,
    }


def run_mcn(data: GridData, preset: str, seed: int) -> tuple[list[np.ndarray], dict[str, Any]]:
    """Feed the grid sequence to an MCN (learning on); nInConPerCol from the data's mean weight."""
    mean_ones = float(np.mean([len(x) for x in data.sdrs]))
    params = resolve_in_con(presets.mcn_params(preset, {"seed": int(seed)}), mean_ones)
    mcn = MCN(params, input_width=data.width)
    winners, predicted = [], 0
    for x in data.sdrs:
        winners.append(mcn.step(x, learn=True))
        predicted += mcn.stats.predicted_cells
    return winners, {"columns": mcn.n_columns, "predicted_cells_per_step": predicted / len(data.sdrs),
                     "nInConPerCol": params["nInConPerCol"]}


def run_grid_once(data: GridData, scoring: str, preset: str, mcn_preset: str, tm_seed: int,
                  mcn_seed: int, methods: Iterable[str] = METHODS, ds: int = seqslam.DS
                  ) -> dict[str, dict[str, Any]]:
    """All methods on one data set. Returns {method: {auc, recall_at_1, ..., P, R, S, info}}.

    `pairwise-seq` is the OpenSeqSLAM matcher (models.evaluation.seqslam, ds steps centred on each step,
    full paths only) over the Dice of the input SDRs: what a plain sequence filter gets from the codes,
    beside what the Temporal Memory gets (docs/design/science.md §10.1). `online-X` is the service's
    localiser run as loop closure over the Dice of X's descriptors (`online.loop_closure`): each step
    localised against the steps before it, linked in order; its all-pairs AUC reads the beam's scores.
    Per query (every method): step i's answer among the steps j < i, scored by `metrics.query_metrics`
    (R@1, query_auc, query_recall_at_100p); the online methods answer with the localiser's place and
    confidence, the others with their best match and its similarity.
    """
    out: dict[str, dict[str, Any]] = {}
    tm: tuple[list[np.ndarray], dict[str, Any]] | None = None  # one TM run serves htm and online-htm
    for method in methods:
        similarity, answers = None, None
        if method == "pairwise":
            descriptors, info = data.sdrs, {}
        elif method == "pairwise-seq":
            descriptors, info = data.sdrs, {"ds": ds}
            similarity = seqslam.seqslam(dice_matrix(data.sdrs), ds)
        elif method == "mcn":
            descriptors, info = run_mcn(data, mcn_preset, mcn_seed)
        elif method in ("htm", "online-htm"):
            tm = tm or run_htm(data, preset, tm_seed)
            descriptors, info = tm
        elif method == "online-pairwise":
            descriptors, info = data.sdrs, {}
        else:
            raise ValueError(f"unknown method {method!r}; known: {', '.join(METHODS)}")
        if method.startswith("online-"):
            answers = online.loop_closure(dice_matrix(descriptors), data.sdrs)
            similarity = answers.S
        result = metrics.grid_evaluation(descriptors, data.places, scoring, similarity)
        result.update(_per_query(dice_matrix(descriptors) if similarity is None else similarity,
                                 data.places, answers))
        result["info"] = info
        out[method] = result
    return out


def _per_query(S: np.ndarray, places: np.ndarray, answers: online.OnlineAnswers | None) -> dict[str, float]:
    """Per-query metrics of online loop closure: step i against the steps j < i (docs/design/science.md
    §8.3, §8.4). S: (T, T), rows the older steps; answers: the localiser's (else each step's best match).
    Steps without an older step (the first) answer nothing; steps with no same-place older step count
    only as wrong answers in the query PR curve."""
    T = len(places)
    older = np.triu(np.ones((T, T), dtype=bool), k=1)
    gt = metrics.place_ground_truth(places) & older
    s = np.where(older, np.asarray(S, dtype=np.float64), -np.inf)
    if answers is None:
        best, confidence = metrics.best_matches(s)
    else:
        best, confidence = answers.best, answers.confidence
    answered = (best >= 0) & np.isfinite(confidence)
    floor = confidence[answered].min() if answered.any() else 0.0
    best, confidence = np.where(answered, best, -1), np.where(answered, confidence, floor)
    q = metrics.query_metrics(np.where(np.isfinite(s), s, floor), gt, confidence, best)
    return {"recall_at_1": q["recall_at_1"], "query_auc": q["query_auc"],
            "query_recall_at_100p": q["query_recall_at_100p"]}


def _summary(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    return {"mean": float(a.mean()), "sd": float(a.std(ddof=1)) if a.size > 1 else 0.0,
            "min": float(a.min()), "max": float(a.max())}


def grid_experiment(
    data_for_seed: Callable[[int], GridData],
    *,
    scoring: str = "paper",
    preset: str = "cba2020-grid",
    mcn_preset: str = "mcn-grid",
    seeds: int = 10,
    seed: int = 0,
    methods: Iterable[str] = METHODS,
    ds: int = seqslam.DS,
    plots_dir: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Run the grid protocol over `seeds` seeds and aggregate (docs/design/science.md §8.6).

    Seeds for data, TM and MCN are spawned from the experiment `seed` with `numpy.random.SeedSequence`,
    so every run is reproducible from one number.

    Args:
        data_for_seed: builds the data set for a data seed (published files ignore it).
        methods: subset of METHODS; each memory method's ablations (ABLATIONS) are added.
        ds: steps per sequence path of `pairwise-seq`.
        progress: called as progress(done, total) after each seed.

    Returns:
        JSON-ready dict: {"scoring", "data", "seeds", "methods": {name: {"auc_mean", "auc_sd",
        "auc_min", "auc_max", "recall_at_1_mean", ..., "per_seed": [...], ...}}}.
    """
    methods = tuple(seqslam.with_ablations(list(methods), ABLATIONS))
    children = np.random.SeedSequence(seed).spawn(seeds)
    per_method: dict[str, list[dict[str, Any]]] = {m: [] for m in methods}
    first: dict[str, dict[str, Any]] | None = None
    data_meta: dict[str, Any] = {}
    for i, child in enumerate(children):
        data_seed, tm_seed, mcn_seed = (int(v) for v in child.generate_state(3))
        data = data_for_seed(data_seed)
        data_meta = dict(data.meta)
        results = run_grid_once(data, scoring, preset, mcn_preset, tm_seed, mcn_seed, methods, ds)
        for m, r in results.items():
            per_method[m].append({"seed": {"data": data_seed, "tm": tm_seed, "mcn": mcn_seed},
                                  **{k: float(r[k]) for k in _METRICS}, **r["info"]})
        if first is None:
            first = results
        if progress:
            progress(i + 1, seeds)

    summary: dict[str, Any] = {}
    for m, runs in per_method.items():
        entry: dict[str, Any] = {}
        for k in _METRICS:
            stats = _summary([r[k] for r in runs])
            entry.update({f"{k}_{s}": v for s, v in stats.items()})
        if m == "htm":
            entry["preset"] = preset
            entry["params"] = presets.tm_params(preset)
            entry["predicted_column_fraction_mean"] = float(np.mean([r["predicted_column_fraction"]
                                                                     for r in runs]))
            entry["bytes"] = runs[0]["bytes"]
            entry["warnings"] = runs[0]["warnings"]
        if m == "mcn":
            entry["preset"] = mcn_preset
            entry["columns_mean"] = float(np.mean([r["columns"] for r in runs]))
        entry["per_seed"] = runs
        summary[m] = entry

    if plots_dir is not None and first is not None:
        out = Path(plots_dir)
        out.mkdir(parents=True, exist_ok=True)
        tag = f"{scoring}"
        plots.plot_pr_curves({m: (r["P"], r["R"]) for m, r in first.items()},
                             out / f"pr_{tag}.png", f"Grid world, {scoring} scoring (first seed)")
        for m, r in first.items():
            plots.plot_similarity(np.asarray(r["S"], dtype=float), out / f"similarity_{m}_{tag}.png",
                                  f"{m}: similarity ({scoring} scoring)")
    return {"scoring": scoring, "data": data_meta, "experiment_seed": seed, "seeds": seeds,
            "methods": summary}
