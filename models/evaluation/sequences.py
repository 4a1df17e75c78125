"""Cross-season image sequences: pairing, cached features, and the database/query protocol.

docs/design/science.md §8.5: the memory learns the database sequence (learn = true), then runs the query
sequence with learning off; the paper does this without a reset in between, the project's protocol may reset.
S has database items as rows and queries as columns, higher = more similar (§8.1).
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from models import presets, sdr
from models.evaluation import metrics, online
from models.evaluation import seqslam as seq
from models.frontend import slsbh
from models.frontend.adaptation import running_mean_subtract
from models.frontend.embedding import Embedder
from models.memory.mcn import MCN
from models.memory.temporal_memory import TemporalMemory
from storage.base.files import atomic_write, sha256_file

# "X-seq" is method X's single-image similarity through the OpenSeqSLAM matcher (models.evaluation.
# seqslam: contrast enhancement, full straight paths of ds frames centred on the query); `openseqslam` is
# that matcher on its own pixel front end with its own match score, the reference
# (docs/design/science.md §10.1).
# "online-X" is method X's similarity through the causal sequence localiser (models.evaluation.online,
# docs/design/science.md §11): what the service answers per stream.
SEQUENCE_FILTERED = ("cosine", "slsbh", "mcn", "htm")
METHODS = ("cosine", "slsbh", "mcn", "htm", "openseqslam", *(f"{m}-seq" for m in SEQUENCE_FILTERED),
           *(f"online-{m}" for m in SEQUENCE_FILTERED))
# What always runs beside a memory method (seqslam.with_ablations).
ABLATIONS = {"htm": ("cosine", "slsbh"), "mcn": ("cosine", "slsbh"),
             "htm-seq": ("cosine-seq", "slsbh-seq"), "mcn-seq": ("cosine-seq", "slsbh-seq"),
             "online-htm": ("online-cosine", "online-slsbh"), "online-mcn": ("online-cosine", "online-slsbh")}
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".webp")


def image_names(folder: Path) -> list[str]:
    """The image file names in `folder`, sorted (the order ground-truth files index).

    Raises:
        ValueError: `folder` is not a folder or holds no image.
    """
    if not Path(folder).is_dir():
        raise ValueError(f"not a folder: {folder}")
    out = sorted(p.name for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not out:
        raise ValueError(f"no image in {folder}")
    return out


def paired_names(db_dir: Path, query_dir: Path, offset: int = 0, limit: int | None = None) -> list[str]:
    """File names present in both folders (same name = same place), sorted, then sliced.

    Raises:
        ValueError: a folder is missing or the two have no name in common.
    """
    common = sorted(set(image_names(db_dir)) & set(image_names(query_dir)))
    if not common:
        raise ValueError(f"no image file name is in both {db_dir} and {query_dir}")
    out = common[offset: None if limit is None else offset + limit]
    if not out:
        raise ValueError(f"offset {offset} leaves no pair of the {len(common)} in common")
    return out


def cached_features(encoder: Embedder, paths: Sequence[Path], cache_dir: Path | None,
                    progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """(N, D) float32 backbone features of `paths`, cached on disk by content.

    The cache key hashes the encoder identity (backbone, weights, resize mode) and every file's SHA-256,
    so a sweep over memory parameters never recomputes features, and a changed file or encoder never
    reuses stale ones.
    """
    h = hashlib.sha256(encoder.identity.encode())
    for p in paths:
        h.update(sha256_file(p).encode())
    key = h.hexdigest()
    if cache_dir is not None:
        cached = Path(cache_dir) / f"features-{key}.npy"
        if cached.exists():
            return np.load(cached)
    out = []
    for i in range(0, len(paths), 32):
        chunk = [Path(p).read_bytes() for p in paths[i:i + 32]]
        out.append(encoder.embed(chunk).features)
        if progress:
            progress(min(i + 32, len(paths)), len(paths))
    feats = np.concatenate(out).astype(np.float32)
    if cache_dir is not None:
        Path(cache_dir).mkdir(parents=True, exist_ok=True)
        atomic_write(cached, lambda f: np.save(f, feats))
    return feats


def dark_frames(paths: Sequence[Path], threshold: float = 20.0) -> np.ndarray:
    """(n,) bool: frames whose mean grey level is below `threshold` (tunnels, stations;
    docs/design/science.md §8.5)."""
    import cv2  # only this helper needs it; the rest of the module works on features

    out = []
    for p in paths:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise ValueError(f"cannot read image {p}")
        out.append(float(img.mean()) < threshold)
    return np.array(out, dtype=bool)


def _predicted_fraction(tm: TemporalMemory, codes: Sequence[np.ndarray]) -> tuple[list[np.ndarray], float]:
    winners, predicted, active = [], 0, 0
    for c in codes:
        winners.append(tm.compute(c, learn=False))
        predicted += tm.context.stats.predicted_columns
        active += tm.context.stats.active_columns
    return winners, predicted / max(active, 1)


def run_tm(db_codes: np.ndarray, q_codes: np.ndarray, preset: str, seed: int, reset: bool,
           width: int, tm_overrides: dict[str, Any] | None = None
           ) -> tuple[list[np.ndarray], list[np.ndarray], dict[str, Any]]:
    """Learn the database codes, then run the query codes with learning off.

    Returns:
        db winners, query winners (sorted cell arrays), and statistics: the fraction of active columns
        predicted in the query pass in true order, the same in a random order of the query frames (the
        chance-prediction rate, docs/design/science.md §3.8: the difference is what sequence memory
        contributes), and the preallocated bytes.
    """
    tm = TemporalMemory(presets.tm_options(preset, {**(tm_overrides or {}), "seed": int(seed),
                                                   "columnDimensions": width}))
    db_w = [tm.compute(c, learn=True) for c in db_codes]
    if reset:
        tm.reset()
    q_w, in_order = _predicted_fraction(tm, q_codes)
    tm.reset()  # learn=False changed nothing, so the shuffled pass sees the same learned memory
    order = np.random.default_rng(seed).permutation(len(q_codes))
    _, shuffled = _predicted_fraction(tm, [q_codes[i] for i in order])
    return db_w, q_w, {"query_predicted_fraction": in_order, "chance_predicted_fraction": shuffled,
                       "bytes": tm.size()["bytes"]}


def run_mcn(db_codes: np.ndarray, q_codes: np.ndarray, preset: str, seed: int, reset: bool,
            width: int) -> tuple[list[np.ndarray], list[np.ndarray], dict[str, Any]]:
    """MCN on the same codes: learn the database, infer the queries (docs/design/science.md §4)."""
    params = presets.mcn_params(preset, {"seed": int(seed)})
    if params["nInConPerCol"] is None:
        params["nInConPerCol"] = round(float(np.mean([len(c) for c in db_codes])))
    mcn = MCN(params, input_width=width)
    db_w = [mcn.step(c, learn=True) for c in db_codes]
    if reset:
        mcn.reset()
    q_w = [mcn.step(c, learn=False) for c in q_codes]
    return db_w, q_w, {"columns": mcn.n_columns}


def codes(hasher: slsbh.Hasher, feats: np.ndarray, adapt_tau: int = 0) -> np.ndarray:
    """(N, 2n) sLSBH codes of one stream's features (N, D) in time order, adapted with time constant
    `adapt_tau` (0 = not) in projection space, exactly as the service does it (models.frontend.adaptation)."""
    Y = hasher.project(feats)
    return slsbh.hash_projected(running_mean_subtract(Y, adapt_tau) if adapt_tau else Y, hasher.s)


def with_ablations(methods: Sequence[str]) -> list[str]:
    """`methods` with each memory method's ablations (ABLATIONS) added before it, in order, once each."""
    return seq.with_ablations(methods, ABLATIONS)


def is_sequence(method: str) -> bool:
    """A method that matches sequences of ds frames (scored only on queries with a full window)."""
    return method == "openseqslam" or method.endswith("-seq") or method.startswith("online-")


def base_method(method: str) -> str:
    """The single-image method whose similarity a sequence method runs on ("online-htm" -> "htm")."""
    return method.removesuffix("-seq").removeprefix("online-")


def evaluate(S: np.ndarray, tolerance: int, gt: np.ndarray | None = None, columns: np.ndarray | None = None,
             answers: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, Any]:
    """Both metrics of S (n_db, n_q): the paper's all-pairs PR (§8.2) and the per-query one (labelled).

    Args:
        S: similarities, higher = more similar; -inf where a sequence method has no full path.
        tolerance: ±database items counted as the same place (§8.3).
        gt: (n_db, n_q) bool exact matches (default identity: row i = query i).
        columns: (n_q,) bool, the queries scored (default all).
        answers: (best, confidence), each (n_q,): a method's own answers (OpenSeqSLAM's match score);
            default each query's most similar item and its similarity.

    Returns:
        all pairs: "auc", "recall_at_100p", "P", "R"; per query: "query_auc", "recall_at_1",
        "recall_at_5", "query_recall_at_100p", "query_P", "query_R", "best", "confidence", "correct"
        (over the scored queries, in column order).
    """
    S = np.asarray(S, dtype=np.float64)
    gt = np.eye(*S.shape, dtype=bool) if gt is None else np.asarray(gt, dtype=bool)
    cols = np.ones(S.shape[1], dtype=bool) if columns is None else np.asarray(columns, dtype=bool)
    S, gt = S[:, cols], gt[:, cols]
    finite = np.isfinite(S)
    if not finite.any():
        raise ValueError("no finite similarity among the scored queries")
    # Pairs without a full path rank below every scored pair; the curve's thresholds keep their range.
    S = np.where(finite, S, S[finite].min())
    if tolerance > 0:
        S_pr, hits = metrics.apply_tolerance(S, gt, tolerance)
    else:
        S_pr, hits = S, gt
    P, R = metrics.pr_curve(S_pr, gt)
    q = metrics.query_metrics(S, hits, *(() if answers is None else (answers[1][cols], answers[0][cols])))
    return {"auc": metrics.auc(P, R), "recall_at_100p": metrics.recall_at_100_precision(P, R), "P": P,
            "R": R, "query_auc": q["query_auc"], "recall_at_1": q["recall_at_1"],
            "recall_at_5": q["recall_at_5"], "query_recall_at_100p": q["query_recall_at_100p"],
            "query_P": q["P"], "query_R": q["R"], "best": q["best"], "confidence": q["confidence"],
            "correct": q["correct"]}


METRICS = ("auc", "query_auc", "recall_at_1", "recall_at_5", "recall_at_100p", "query_recall_at_100p")


def image_experiment(db_feats: np.ndarray, q_feats: np.ndarray, *, methods: Sequence[str],
                     preset: str, mcn_preset: str = "mcn-nordland", k: int | None = None,
                     s: float | None = None, seeds: int = 3, seed: int = 0, tolerance: int = 0,
                     reset: bool = False, adapt_tau: int = 0, tm_overrides: dict[str, Any] | None = None,
                     reverse_query: bool = False, ds: int = seq.DS, gt: np.ndarray | None = None,
                     frames: tuple[np.ndarray, np.ndarray] | None = None, crossing: bool = False,
                     localiser: dict[str, Any] | None = None,
                     progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """All methods on one database/query pair of feature sequences, over seeds.

    Args:
        db_feats, q_feats: (n_db, D), (n_q, D) L2-normalised features in route order.
        methods: subset of METHODS; each memory method's ablations (ABLATIONS) are added.
        preset: TM preset; mcn_preset: MCN preset.
        k, s: sLSBH size and sparsity (2k = TM columns); None: the TM preset's (`presets.slsbh_params`).
        seeds: runs; projection, TM and MCN seeds spawned from `seed` (docs/design/science.md §8.6).
        tolerance: ±database items counted as the same place.
        reset: reset the sequence memory between database and query (the paper does not).
        adapt_tau: > 0: each sequence minus its running mean (models.frontend.adaptation) before every feature
            method; 0: the features as they are.
        tm_overrides: Temporal Memory parameters replacing the preset's (sweeps).
        reverse_query: the query sequence is driven backwards (last row first); S keeps file order.
        ds: frames per sequence path. When any sequence method runs, every method is scored on the same
            queries, those with ds frames centred on them (in driven order).
        gt: (n_db, n_q) bool exact matches; default identity (row i of both = the same place).
        frames: (db, query) patch-normalised grey frames (`seqslam.load_frames`), for `openseqslam`.
        crossing: every sequence method answers the row where its best path crosses the query instead
            of OpenSeqSLAM's start row + ds // 2 (seqslam.path_sums); a measurement, not a default.
        localiser: options of the `online-X` methods over `models.localisation.default_conf`.

    Returns:
        {"methods": {name: {"auc_mean", "auc_min", "auc_max", "query_auc_mean", ..., "recall_at_1_mean",
         ..., "per_seed"}}, "queries": scored query indices (file order),
         "first": {name: {"S", "P", "R", "query_P", "query_R", "best", "confidence", "correct"}}}
        (the first seed's matrices and answers, for plots and the match gallery).
    """
    defaults = presets.SlsbhOptions.of(presets.slsbh_params(preset))
    k = defaults.k if k is None else k
    s = defaults.s if s is None else s
    methods = with_ablations(methods)
    bad = set(methods) - set(METHODS)
    if bad:
        raise ValueError(f"unknown method(s) {sorted(bad)}; known: {', '.join(METHODS)}")
    if "openseqslam" in methods and frames is None:
        raise ValueError("openseqslam needs the frames (seqslam.load_frames)")
    n_q = len(q_feats)
    runs: dict[str, list[dict[str, Any]]] = {m: [] for m in methods}
    first: dict[str, dict[str, Any]] = {}
    columns = seq.full_window(n_q, ds) if any(map(is_sequence, methods)) else np.ones(n_q, dtype=bool)
    if reverse_query:
        q_feats = q_feats[::-1]
        columns = columns[::-1]  # full windows in driven order, indexed in file order
        if frames is not None:
            frames = (frames[0], frames[1][::-1])
    if not columns.any():
        raise ValueError(f"{n_q} queries leave none with a full window of ds = {ds}")
    raw = {"db": db_feats, "q": q_feats}
    if adapt_tau:
        db_feats = running_mean_subtract(db_feats, adapt_tau)
        q_feats = running_mean_subtract(q_feats, adapt_tau)
    cos = db_feats @ q_feats.T
    children = np.random.SeedSequence(seed).spawn(seeds)
    for i, child in enumerate(children):
        proj_seed, tm_seed, mcn_seed = (int(v) for v in child.generate_state(3))
        bases = {base_method(m) for m in methods}
        if bases & {"slsbh", "mcn", "htm"}:
            hasher = slsbh.Hasher(slsbh.make_projection(db_feats.shape[1], k, proj_seed), s)
            db_codes, q_codes = (codes(hasher, raw[key], adapt_tau) for key in ("db", "q"))
        single: dict[str, tuple[np.ndarray, dict[str, Any], float]] = {}  # this seed's S per base method
        for m in methods:
            if i > 0 and m in ("cosine", "cosine-seq", "online-cosine", "openseqslam"):
                continue  # deterministic given the features and frames
            base = base_method(m)
            t0 = time.perf_counter()
            answers = None
            info: dict[str, Any] = {}
            if m == "openseqslam":
                found = seq.openseqslam(*frames, ds=ds, crossing=crossing)
                S, answers = found.S, (found.best, found.confidence)
            else:
                if base not in single:
                    if base == "cosine":
                        S = cos
                    elif base == "slsbh":
                        S = sdr.dice_matrix(list(db_codes), list(q_codes))
                    else:
                        if base == "htm":
                            db_w, q_w, info = run_tm(db_codes, q_codes, preset, tm_seed, reset, 2 * k,
                                                     tm_overrides)
                        else:
                            db_w, q_w, info = run_mcn(db_codes, q_codes, mcn_preset, mcn_seed, reset, 2 * k)
                        S = sdr.dice_matrix(db_w, q_w)
                    single[base] = (S, info, time.perf_counter() - t0)
                    t0 = time.perf_counter()
                S, info, base_seconds = single[base]
                info = {**info, "seconds": base_seconds}
                if m.endswith("-seq"):
                    S = seq.seqslam(S, ds, crossing=crossing)
                elif m != base:
                    found = online.localise(S, localiser)
                    S, answers = found.S, (found.best, found.confidence)
                    info["support_mean"] = float(found.support[found.best >= 0].mean())
            info["seconds"] = info.get("seconds", 0.0) + time.perf_counter() - t0
            if reverse_query:
                S = S[:, ::-1]  # back to file order: column j is query place j again
                answers = None if answers is None else (answers[0][::-1], answers[1][::-1])
            r = evaluate(S, tolerance, gt, columns, answers)
            if m not in first:
                first[m] = {key: r[key] for key in ("P", "R", "query_P", "query_R", "best", "confidence",
                                                    "correct")} | {"S": S}
            runs[m].append({"seed": {"projection": proj_seed, "tm": tm_seed, "mcn": mcn_seed},
                            **{key: float(r[key]) for key in METRICS}, **info})
        if progress:
            progress(i + 1, seeds)
    summary: dict[str, Any] = {}
    for m, rs in runs.items():
        entry: dict[str, Any] = {}
        for key in METRICS:
            vals = np.array([r[key] for r in rs])
            entry.update({f"{key}_mean": float(vals.mean()), f"{key}_min": float(vals.min()),
                          f"{key}_max": float(vals.max())})
        if base_method(m) == "htm":
            entry["preset"] = preset
            for key in ("query_predicted_fraction", "chance_predicted_fraction"):
                entry[f"{key}_mean"] = float(np.mean([r[key] for r in rs]))
            entry["bytes"] = rs[0]["bytes"]
        if base_method(m) == "mcn":
            entry["preset"] = mcn_preset
            entry["columns_mean"] = float(np.mean([r["columns"] for r in rs]))
        if is_sequence(m):
            entry["ds"] = ds
        entry["seconds_mean"] = float(np.mean([r["seconds"] for r in rs]))
        entry["per_seed"] = rs
        summary[m] = entry
    return {"methods": summary, "queries": np.flatnonzero(columns).tolist(), "first": first}
