"""`cortexloc eval grid | images`: reproduce and measure the science (docs/design/science.md §2, §8.5).

    cortexloc eval grid --sdr FILE --places FILE [--scoring paper|clean] [--preset NAME] [--seeds K]
                        [--ds N] [--json OUT] [--plots DIR]
    cortexloc eval grid --generate --aliasing A --noise N [--loops L] [...same options]
    cortexloc eval images --db DIR --query DIR [--methods M,...] [--ds N] [--gt FILE] [--preset NAME]
                          [--backbone B] [--resize R] [--seeds K] [--reset|--no-reset] [--json OUT]
                          [--plots DIR]

Defaults: grid --seeds 10; images --seeds 3 and --no-reset (the paper's protocol; the tables of
docs/results.md pass --reset, docs/design/science.md §8.5). The README's command list says the same
(tests/models/evaluation/test_sequences.py checks it against these options).

Tables go to stdout, progress and warnings to stderr, machine-readable results to --json.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from models import presets
from service.cli.common import check_backbone, check_presets, progress, provenance, write_json

app = typer.Typer(no_args_is_help=True, help="Reproduce and measure the science.")


@app.command("grid")
def eval_grid(
    sdr: Annotated[Path | None, typer.Option(help="Published SDR file (T rows of 2048 0/1 values).",
                                             exists=True, dir_okay=False)] = None,
    places: Annotated[Path | None, typer.Option(help="Published places file (header, then x,y rows).",
                                                exists=True, dir_okay=False)] = None,
    generate: Annotated[bool, typer.Option("--generate", help="Simulate the grid world instead.")] = False,
    aliasing: Annotated[int, typer.Option(min=0, max=6, help="Aliased place pairs (with --generate).")] = 0,
    noise: Annotated[float, typer.Option(min=0.0, max=1.0, help="Noise fraction (with --generate).")] = 0.0,
    loops: Annotated[int, typer.Option(min=1, help="Loops of the trajectory (with --generate).")] = 11,
    mode: Annotated[str, typer.Option(help="Place SDRs: bernoulli | exact.")] = "bernoulli",
    scoring: Annotated[str, typer.Option(help="paper (reproduces the published numbers) | clean.")] = "paper",
    preset: Annotated[str, typer.Option(help="Temporal Memory preset.")] = "cba2020-grid",
    mcn_preset: Annotated[str, typer.Option(help="MCN preset.")] = "mcn-grid",
    seeds: Annotated[int, typer.Option(min=1, help="Runs; seeds spawned from --seed.")] = 10,
    seed: Annotated[int, typer.Option(help="Experiment seed.")] = 0,
    methods: Annotated[str, typer.Option(help="Comma-separated: "
                                          "pairwise,pairwise-seq,mcn,htm,online-pairwise,"
                                          "online-htm (pairwise-seq: the sequence matcher on the input "
                                          "codes; it and pairwise always run beside mcn and htm; online-X: "
                                          "the service's localiser, online-pairwise beside online-htm)."
                                          )] = "pairwise,pairwise-seq,mcn,htm",
    ds: Annotated[int, typer.Option(min=2, help="Steps per sequence path of pairwise-seq.")] = 10,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write results as JSON here.")] = None,
    plots_dir: Annotated[Path | None, typer.Option("--plots", help="Write PR and similarity PNGs here.")]
    = None,
) -> None:
    """Grid-world evaluation (docs/design/science.md §2): pairwise InputSDR, MCN and HTM, over seeds."""
    from models.evaluation import gridworld, runner

    if scoring not in ("paper", "clean"):
        raise typer.BadParameter("must be paper or clean", param_hint="--scoring")
    check_presets(preset, mcn_preset)
    method_list = [m.strip() for m in methods.split(",") if m.strip()]
    bad = set(method_list) - set(runner.METHODS)
    if bad or not method_list:
        raise typer.BadParameter(f"methods must be among {', '.join(runner.METHODS)}", param_hint="--methods")
    if generate == (sdr is not None or places is not None):
        raise typer.BadParameter("give either --sdr and --places, or --generate")
    if generate:
        def data_for_seed(s: int) -> gridworld.GridData:
            return gridworld.generate(aliasing, noise, loops=loops, seed=s, mode=mode)
    else:
        if sdr is None or places is None:
            raise typer.BadParameter("--sdr and --places go together")
        try:
            published = gridworld.load_published(sdr, places)
        except ValueError as e:
            raise typer.BadParameter(str(e)) from e

        def data_for_seed(s: int) -> gridworld.GridData:
            return published

    with progress("grid", show=seeds > 1) as tick:
        result = runner.grid_experiment(
            data_for_seed, scoring=scoring, preset=preset, mcn_preset=mcn_preset, seeds=seeds, seed=seed,
            methods=method_list, ds=ds, plots_dir=plots_dir, progress=tick)
    for w in result["methods"].get("htm", {}).get("warnings", []):
        typer.echo(f"warning ({preset}): {w}", err=True)
    result["provenance"] = provenance()
    write_json(json_out, result)
    typer.echo(format_grid_table(result))


def _legend(query_auc: str, recall_100p: str, spread: str) -> list[str]:
    """The lines under a result table that say what its columns are (docs/design/science.md §8.2, §8.3);
    "AUC pairs" near 0.5 beside R@1 1.000 is not a contradiction, and says why."""
    return ["AUC pairs = the paper's AUC (§8.2): precision-recall over all pairs (database row, query) at "
            "one threshold shared by every query;",
            "  it also asks that scores compare across queries, so it can sit near 0.5 beside R@1 1.000 "
            "(right answers, scores on different scales);",
            f"{query_auc} = per query: each query's best match ranked by its confidence; R@1 / R@5 = the "
            "right place is the best match / among the 5 best;",
            f"{recall_100p}; {spread} over the seeds"]


def _table(entries: dict[str, dict[str, Any]], columns: list[tuple[str, str, str]]) -> list[str]:
    """Header and one row per method, every column as wide as its widest cell (method names differ in
    length: `service-without-tm`). `columns`: (header, key of the entry, format spec)."""
    cells = {m: [format(e[key], spec) for _, key, spec in columns] for m, e in entries.items()}
    name_w = max([len("method"), *map(len, entries)])
    widths = [max([len(head), *(len(c[i]) for c in cells.values())])
              for i, (head, _, _) in enumerate(columns)]

    def line(name: str, values: list[str], notes: str) -> str:
        padded = (f"{v:>{w}}" for v, w in zip(values, widths, strict=True))
        return " ".join([f"{name:<{name_w}}", *padded]) + f"  {notes}"

    return [line("method", [head for head, _, _ in columns], "notes"),
            *(line(m, cells[m], _method_notes(m, e)) for m, e in entries.items())]


def format_grid_table(result: dict[str, Any]) -> str:
    """A readable table of a grid result (stdout)."""
    data = result["data"]
    if data.get("source") == "generated":
        what = f"generated a={data['aliasing']} n={data['noise']} loops={data['loops']} ({data['mode']})"
    else:
        what = f"published {Path(str(data.get('sdr_file', '?'))).name}"
    columns = [("AUC pairs", "auc_mean", ".6f"), ("sd", "auc_sd", ".4f"), ("min", "auc_min", ".4f"),
               ("max", "auc_max", ".4f"), ("R@1", "recall_at_1_mean", ".3f"),
               ("R@5", "recall_at_5_mean", ".3f"), ("R@100P", "recall_at_100p_mean", ".3f"),
               ("qAUC", "query_auc_mean", ".3f"), ("qR@100P", "query_recall_at_100p_mean", ".3f")]
    return "\n".join([f"grid world: {what}; scoring={result['scoring']}; seeds={result['seeds']}",
                      *_table(result["methods"], columns),
                      *_legend("qAUC", "R@100P / qR@100P = recall at 100 % precision, all pairs / per query",
                               "sd, min, max")])


def _method_notes(method: str, entry: dict[str, Any]) -> str:
    """The notes column of a result table: preset, and how much the memory predicted or grew."""
    method = method.removesuffix("-seq")
    if method == "htm":
        if "predicted_column_fraction_mean" in entry:
            return f"{entry['preset']}, predicted columns {entry['predicted_column_fraction_mean']:.3f}"
        return (f"{entry['preset']}, query predicted {entry['query_predicted_fraction_mean']:.3f} "
                f"(chance {entry['chance_predicted_fraction_mean']:.3f}), {entry['bytes'] / 2**20:.1f} MiB")
    if method == "mcn":
        return f"{entry['preset']}, columns {entry['columns_mean']:.0f}"
    return ""


@app.command("images")
def eval_images(
    db: Annotated[Path, typer.Option(help="Database image folder (e.g. summer).", exists=True,
                                     file_okay=False)],
    query: Annotated[Path, typer.Option(help="Query image folder (e.g. winter); same name = same place "
                                        "unless --gt is given.", exists=True, file_okay=False)],
    offset: Annotated[int, typer.Option(min=0, help="First pair (in sorted name order).")] = 0,
    limit: Annotated[int | None, typer.Option(min=2, help="Number of pairs (default: all).")] = None,
    gt: Annotated[Path | None, typer.Option(help="Ground truth file instead of equal names: CSV "
                                            "query_index,query_file,matching_ref_indices or VPR-Bench "
                                            "ground_truth_new.npy (models/evaluation/ground_truth.py); "
                                            "indices count in each folder's sorted names, whole folders.",
                                            exists=True, dir_okay=False)] = None,
    backbone: Annotated[str | None, typer.Option(help="a backbone registered in models.frontend.backbones "
                                                      "(default: the service's, resolved as serve "
                                                      "does)")] = None,
    resize: Annotated[str | None, typer.Option(help="crop | squash (default: a new map's, "
                                                    "service.maps.config.DEFAULT_RESIZE)")] = None,
    methods: Annotated[str, typer.Option(help="Comma-separated: cosine,slsbh,mcn,htm (one frame); "
                                          "openseqslam (the reference on grey pixels); cosine-seq,"
                                          "slsbh-seq,mcn-seq,htm-seq (the same sequence matcher on each "
                                          "single-image similarity); online-X (the causal localiser on X); "
                                          "service, service-without-tm (the service's own path: a real map, "
                                          "learn db, localise the query stream); service-slam, "
                                          "service-slam-without-tm (db then query as ONE learning stream: "
                                          "loop closure while mapping). Memory methods bring their "
                                          "ablations.")]
    = "cosine,slsbh,htm,openseqslam,cosine-seq,slsbh-seq,htm-seq",
    operating_point: Annotated[str | None, typer.Option(
        help="precision=P: print, per method, the confidence threshold whose answers reach precision P "
             "(per query, first seed)")] = None,
    ds: Annotated[int, typer.Option(min=2, help="Frames per sequence path, centred on the query.")] = 10,
    preset: Annotated[str | None, typer.Option(help="Temporal Memory preset (default: the service's; the "
                                                    "paper's is cba2020-nordland).")] = None,
    mcn_preset: Annotated[str, typer.Option(help="MCN preset.")] = "mcn-nordland",
    s: Annotated[float | None, typer.Option(help="sLSBH sparsity in (0, 0.5] (default: the preset's, else "
                                                 "0.25).")] = None,
    tolerance: Annotated[int, typer.Option(min=0, help="±database images that count as the same place.")]
    = 0,
    reset: Annotated[bool, typer.Option("--reset/--no-reset",
                                        help="Reset between database and query (the paper does not).")]
    = False,
    adapt: Annotated[int, typer.Option(min=0, help="Running-mean subtraction time constant in frames "
                                       "(models.frontend.adaptation), for every feature method; 0 = off.")]
    = 0,
    reverse_query: Annotated[bool, typer.Option("--reverse-query", help="Drive the query sequence "
                                                "backwards (a route driven the other way).")] = False,
    drop_dark: Annotated[float, typer.Option(min=0.0, help="Drop pairs where either frame's mean grey is "
                                                          "below this (0 = keep all; §8.5 uses 20).")] = 0.0,
    seeds: Annotated[int, typer.Option(min=1, help="Runs; seeds spawned from --seed (a claim wants 10, "
                                                   "docs/design/science.md §8.6).")] = 3,
    seed: Annotated[int, typer.Option(help="Experiment seed.")] = 0,
    cache: Annotated[Path | None, typer.Option(help="Feature cache folder (default: "
                                                    "$CORTEXLOC_CACHE_DIR or ~/.cache/cortexloc).")] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write results as JSON here.")] = None,
    plots_dir: Annotated[Path | None, typer.Option("--plots", help="Write PR curves (all pairs and per "
                                                   "query), similarity images and match galleries here.")]
    = None,
    gallery: Annotated[int, typer.Option(min=1, help="Queries shown in each match gallery.")] = 12,
) -> None:
    """Cross-season evaluation on image sequences (docs/design/science.md §8.5, §10.1): learn db, then
    query."""
    import os

    from pydantic import ValidationError

    from models.evaluation import ground_truth, plots, sequences
    from models.evaluation import seqslam as seq
    from models.frontend import embedding, images
    from service.evaluation import service_path
    from service.frontend import resolve_backbone
    from service.maps.config import DEFAULT_RESIZE
    from service.settings import Settings

    # The service's defaults, read from their one home each (docs/design/service.md §8,
    # models.frontend.embedding).
    preset = preset or Settings.model_fields["default_preset"].default
    backbone = backbone or resolve_backbone(Settings.from_env()).backbone
    resize = resize or DEFAULT_RESIZE  # a new map's (service.maps.config)
    method_list = [m.strip() for m in methods.split(",") if m.strip()]
    service_list = [m for m in method_list if m in service_path.METHODS]
    slam_list = [m for m in method_list if m in service_path.SLAM_METHODS]
    method_list = [m for m in method_list if m not in service_path.METHODS and m not in slam_list]
    bad = set(method_list) - set(sequences.METHODS)
    if bad or not (method_list or service_list or slam_list):
        known = ", ".join((*sequences.METHODS, *service_path.METHODS, *service_path.SLAM_METHODS))
        raise typer.BadParameter(f"must be among {known}", param_hint="--methods")
    method_list = sequences.with_ablations(method_list)
    wanted_precision = _operating_point(operating_point)
    check_presets(preset, mcn_preset)
    check_backbone(backbone)
    if resize not in images.MODES:
        raise typer.BadParameter(f"must be one of {', '.join(images.MODES)}", param_hint="--resize")
    s_conf = presets.slsbh_params(preset)
    s_options = presets.SlsbhOptions.of(s_conf)
    sparsity = float(s if s is not None else s_options.s)
    try:  # the sLSBH rules have one home: presets.SlsbhParams
        presets.SlsbhParams(**{**s_conf, "s": sparsity})
    except ValidationError as e:
        raise typer.BadParameter("; ".join(err["msg"] for err in e.errors()), param_hint="--s") from e
    gt_matrix = None
    try:
        if gt is not None:
            if offset or limit is not None or drop_dark > 0:
                raise typer.BadParameter("--gt indexes the whole folders: leave out --offset, --limit and "
                                         "--drop-dark", param_hint="--gt")
            db_names, q_names = sequences.image_names(db), sequences.image_names(query)
            gt_matrix = ground_truth.load(gt, len(db_names), len(q_names), q_names)
        else:
            # Only the window's frames (less the dark ones) are read and encoded, cached under their own key.
            db_names = q_names = sequences.paired_names(db, query, offset, limit)
            if drop_dark > 0:
                dark = (sequences.dark_frames([db / n for n in db_names], drop_dark)
                        | sequences.dark_frames([query / n for n in q_names], drop_dark))
                db_names = q_names = [n for n, d in zip(q_names, dark, strict=True) if not d]
                if len(q_names) < 2:
                    raise typer.BadParameter("fewer than two pairs are left", param_hint="--drop-dark")
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
    cache_dir = cache or Path(os.environ.get("CORTEXLOC_CACHE_DIR", Path.home() / ".cache" / "cortexloc"))
    if slam_list and gt is not None:
        raise typer.BadParameter("the service-slam methods pair the folders by file name: leave out "
                                 "--gt", param_hint="--methods")
    if method_list == ["openseqslam"] and not (service_list or slam_list):  # pixels only: no backbone
        enc = None
        feats = {label: np.zeros((len(names), 0), np.float32)
                 for label, names in (("db", db_names), ("query", q_names))}
    else:
        enc = embedding.Embedder({"backbone": backbone, "resize": resize})  # features only: no projection
        feats = {}
        for label, folder, names in (("db", db, db_names), ("query", query, q_names)):
            with progress(f"features {label}") as tick:
                feats[label] = sequences.cached_features(enc, [folder / n for n in names],
                                                         cache_dir / "features", progress=tick)
    db_paths, q_paths = [db / n for n in db_names], [query / n for n in q_names]
    # Each frame's contrast, as the service measures it at decode (docs/design/science.md §11.7).
    contrast = (service_path.contrasts(p.read_bytes() for p in [*db_paths, *q_paths])
                if service_list or slam_list else None)
    frames = ((seq.load_frames(db_paths), seq.load_frames(q_paths)) if "openseqslam" in method_list
              else None)
    n_q = len(feats["query"])
    columns = seq.full_window(n_q, ds)  # the service answers causally, scored on the others' queries
    result: dict[str, Any] = {"methods": {}, "queries": np.flatnonzero(columns).tolist(), "first": {}}
    try:
        if method_list:
            with progress("runs", show=seeds > 1) as tick:
                result = sequences.image_experiment(
                    feats["db"], feats["query"], methods=method_list, preset=preset, mcn_preset=mcn_preset,
                    k=int(s_options.k), s=sparsity, seeds=seeds, seed=seed, tolerance=tolerance, reset=reset,
                    adapt_tau=adapt, reverse_query=reverse_query, ds=ds, gt=gt_matrix, frames=frames,
                    progress=tick)
        if service_list:
            assert enc is not None
            with progress("service") as tick:
                summary, first = service_path.experiment(
                    feats["db"], feats["query"], methods=service_list, columns=columns, tolerance=tolerance,
                    gt=gt_matrix, seeds=seeds, seed=seed, reverse_query=reverse_query, progress=tick,
                    contrast=contrast,
                    map_conf={"encoder_id": enc.identity, "backbone": backbone, "preset": preset,
                              "create": {"slsbh": {"s": sparsity, "adapt_tau": adapt}, "resize": resize}})
            result["methods"].update(summary)
            result["first"].update(first)
        if slam_list:
            assert enc is not None
            result["loop_closure"] = _loop_closure(
                feats, slam_list, tolerance=tolerance, seed=seed, contrast=contrast,
                map_conf={"encoder_id": enc.identity, "backbone": backbone, "preset": preset,
                          "create": {"slsbh": {"s": sparsity, "adapt_tau": adapt}}})
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
    first = result.pop("first")
    what = f"{db.name} -> {query.name}, {len(q_names)} queries"
    if plots_dir is not None:
        plots_dir.mkdir(parents=True, exist_ok=True)
        plots.plot_pr_curves({m: (r["P"], r["R"]) for m, r in first.items()}, plots_dir / "pr.png",
                             f"{what}: all pairs (paper, §8.2), first seed")
        plots.plot_pr_curves({m: (r["query_P"], r["query_R"]) for m, r in first.items()},
                             plots_dir / "pr_query.png", f"{what}: per query (best match), first seed")
        for m, r in first.items():
            plots.plot_similarity(np.asarray(r["S"], dtype=float), plots_dir / f"similarity_{m}.png",
                                  f"{m}: similarity (database rows, query columns)")
            plots.match_gallery(db_paths, q_paths, result["queries"], r["best"], r["correct"],
                                r["confidence"], plots_dir / f"gallery_{m}.png", n=gallery)
    result["config"] = {"db": str(db), "query": str(query), "offset": offset, "limit": limit,
                        "gt": str(gt) if gt is not None else "same file name",
                        "pairs": len(q_names), "first": q_names[0], "last": q_names[-1],
                        "encoder": enc.identity if enc else "none",
                        "backbone": backbone if enc else "none", "resize": resize if enc else "none",
                        "weights": enc.describe()["weights"] if enc else "none", "preset": preset,
                        "mcn_preset": mcn_preset,
                        "k": int(s_options.k), "s": sparsity, "ds": ds, "adapt_tau": adapt,
                        "drop_dark": drop_dark, "reverse_query": reverse_query, "tolerance": tolerance,
                        "reset": reset, "seeds": seeds, "seed": seed}
    result["provenance"] = provenance()
    if wanted_precision is not None:
        result["operating_points"] = {
            m: service_path.operating_point(r["confidence"], r["correct"], wanted_precision)
            for m, r in first.items()}
    write_json(json_out, result)
    if result["methods"]:
        typer.echo(format_images_table(result))
    for m, s in result.get("loop_closure", {}).items():
        lap1, lap2 = s["lap"][0], s["lap"][1]
        typer.echo(f"{m} (lap 1 = --db, lap 2 = --query, one learning stream, at the map's threshold "
                   f"{s['threshold']}): lap 1 false revisits {lap1['false_revisits']}; lap 2 precision "
                   f"{_fmt(lap2['precision'])}, recall {_fmt(lap2['recall'])}, "
                   f"R@1 {_fmt(lap2['recall_at_1'])}, "
                   f"query AUC {_fmt(lap2.get('query_auc'))}, recall at 100% precision "
                   f"{_fmt(lap2.get('recall_at_100p'))}")
    for m, point in result.get("operating_points", {}).items():
        typer.echo(f"operating point {m}: " + (
            f"confidence >= {point['threshold']:.4f} gives precision {point['precision']:.3f}, recall "
            f"{point['recall']:.3f}" if point else f"no threshold reaches precision {wanted_precision}"))


def _fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"


def _loop_closure(feats: dict[str, np.ndarray], methods: list[str], *, tolerance: int, seed: int,
                  map_conf: dict[str, Any], contrast: np.ndarray | None = None) -> dict[str, Any]:
    """`service-slam*`: the database then the query traverse posted as ONE learning stream
    (`service_path.slam_replay`), scored per lap (`models.evaluation.slam.score`; file i of either
    folder is place i) at the map's threshold."""
    from models.evaluation import slam
    from service.evaluation import service_path

    n_db, n_q = len(feats["db"]), len(feats["query"])
    labels = np.r_[np.arange(n_db), np.arange(n_q)]
    laps = np.r_[np.zeros(n_db, np.int64), np.ones(n_q, np.int64)]
    out = {}
    for m in methods:
        run = np.concatenate([feats["db"], feats["query"]])
        found, threshold = service_path.slam_replay(run, seed=seed, memory=service_path.SLAM_METHODS[m],
                                                    contrast=contrast, **map_conf)
        out[m] = {"threshold": threshold,
                  **slam.score(found.best, found.confidence, labels, threshold, tolerance, laps)}
    return out


def _operating_point(value: str | None) -> float | None:
    """`precision=P` -> P in (0, 1]."""
    if value is None:
        return None
    name, _, number = value.partition("=")
    try:
        p = float(number)
    except ValueError:
        p = -1.0
    if name.strip() != "precision" or not 0 < p <= 1:
        raise typer.BadParameter("expected precision=P with P in (0, 1]", param_hint="--operating-point")
    return p


def format_images_table(result: dict[str, Any]) -> str:
    """A readable table of an image result (stdout): the settings it ran with, both metrics, a legend."""
    c = result["config"]
    columns = [("AUC pairs", "auc_mean", ".4f"), ("min", "auc_min", ".4f"), ("max", "auc_max", ".4f"),
               ("AUC query", "query_auc_mean", ".4f"), ("R@1", "recall_at_1_mean", ".3f"),
               ("R@5", "recall_at_5_mean", ".3f"), ("R@100P", "query_recall_at_100p_mean", ".3f"),
               ("s/run", "seconds_mean", ".2f")]
    return "\n".join([
        f"{Path(c['db']).name} -> {Path(c['query']).name}: {c['pairs']} queries "
        f"({c['first']} .. {c['last']}), ground truth {c['gt']}, tolerance ±{c['tolerance']}",
        f"preset {c['preset']}, backbone {c['backbone']} [{c['weights']} weights], resize {c['resize']}, "
        f"s={c['s']}, adapt={c['adapt_tau']}, {'reset' if c['reset'] else 'no reset'}, seeds={c['seeds']}, "
        f"ds={c['ds']}; {len(result['queries'])} queries scored",
        *_table(result["methods"], columns),
        *_legend("AUC query", "R@100P = recall at 100 % precision, per query", "min, max"),
        "s/run = seconds per seed"])


@app.command("revisit")
def eval_revisit(
    folder: Annotated[Path, typer.Option(help="the traverse's image folder", exists=True, file_okay=False)],
    offset: Annotated[int, typer.Option(min=0)] = 0,
    limit: Annotated[int, typer.Option(min=1)] = 894,
    noise: Annotated[float, typer.Option(help="pixel noise, grey levels (std)")] = 8.0,
    backbone: Annotated[str, typer.Option(help="a backbone registered in models.frontend.backbones")]
    = "efficientnet-lite0",
    resize: Annotated[str | None, typer.Option(help="crop | squash (default: a new map's)")] = None,
    seed: int = 0,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the summary here too")] = None,
) -> None:
    """Corridor-like revisits through the service's path (service/evaluation/revisit.py)."""
    from service.evaluation.revisit import revisit
    from service.maps.config import DEFAULT_RESIZE

    revisit(folder, offset=offset, limit=limit, noise=noise, backbone=backbone,
            resize=resize or DEFAULT_RESIZE, seed=seed, json_path=json_out)


@app.command("unknown")
def eval_unknown(
    db: Annotated[Path, typer.Option(help="the database traverse's folder", exists=True, file_okay=False)],
    query: Annotated[Path, typer.Option(help="the query traverse's folder", exists=True, file_okay=False)],
    split: Annotated[int, typer.Option(help="first row of the second half, counted from --offset")],
    thresholds: Annotated[str, typer.Option(help="confidence thresholds, comma-separated")],
    offset: Annotated[int, typer.Option(min=0, help="first paired frame of the route")] = 0,
    limit: Annotated[int | None, typer.Option(min=2, help="frames of the route (default: all)")] = None,
    backbone: Annotated[str | None, typer.Option(help="default: the service's")] = None,
    seed: int = 1,
) -> None:
    """False revisits on places never stored, through the service's path (service/evaluation/unknown.py)."""
    from service.evaluation.unknown import route_names, unknown

    try:
        route_names(db, query, split=split, offset=offset, limit=limit)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
    unknown(db, query, split=split, thresholds=[float(t) for t in thresholds.split(",")], backbone=backbone,
            seed=seed, offset=offset, limit=limit)


@app.command("runtime-parity")
def eval_runtime_parity(
    windows: Annotated[str | None, typer.Option(help="comma-separated Nordland windows (default: all)")]
    = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the result here too")] = None,
) -> None:
    """The backbone's runtimes against each other on the Nordland route
    (service/evaluation/runtime_parity.py)."""
    from models.evaluation.nordland_tables import WINDOWS
    from service.evaluation.runtime_parity import report

    chosen = windows.split(",") if windows else list(WINDOWS)
    if unknown := [w for w in chosen if w not in WINDOWS]:  # before any frame is encoded
        raise typer.BadParameter(f"--windows: no window {', '.join(unknown)}; the windows are "
                                 f"{', '.join(WINDOWS)}")
    report(chosen, json_out)


@app.command("resize")
def eval_resize(
    db: Annotated[Path, typer.Option(help="the database traverse's folder", exists=True, file_okay=False)],
    query: Annotated[Path, typer.Option(help="the query traverse's folder", exists=True, file_okay=False)],
    offset: Annotated[int, typer.Option(min=0)] = 0,
    limit: Annotated[int, typer.Option(min=1)] = 300,
    shapes: Annotated[str, typer.Option(help="frame shapes, comma-separated")] = "2:1,4:3",
    backbone: Annotated[str | None, typer.Option(help="default: the service's")] = None,
    seeds: Annotated[str, typer.Option(help="map seeds, comma-separated")] = "1",
) -> None:
    """Crop or squash through the service's path on frames of several shapes
    (service/evaluation/resize.py)."""
    from service.evaluation.resize import resize_runs

    resize_runs(db, query, offset=offset, limit=limit, shapes=shapes.split(","), backbone=backbone,
                seeds=[int(x) for x in seeds.split(",")])


@app.command("slam-ablation")
def eval_slam_ablation(
    data: Annotated[Path, typer.Option(help="the Nordland folder (summer/, winter/)")],
    seeds: Annotated[int, typer.Option(min=1, help="map seeds 1..N")] = 3,
    backbone: str = "efficientnet-lite0-s5",
    json_out: Annotated[Path | None, typer.Option("--json", help="write every run here too")] = None,
) -> None:
    """The Temporal Memory in its own setting on short, unsaturated routes over seeds
    (service/evaluation/slam_ablation.py, docs/results.md §10.2)."""
    from service.evaluation import slam_ablation

    slam_ablation.ablation(data, seeds=seeds, backbone=backbone, json_path=json_out)

# The options `eval rules` and `eval projections` share (one window-by-seed experiment each).
_DataOpt = Annotated[Path | None, typer.Option(help="the Nordland folder (summer/, winter/)")]
_LinesOpt = Annotated[Path, typer.Option(help="JSON lines, one per job, written as each ends; the tables "
                                              "beside it (.md)")]
_JobsOpt = Annotated[int, typer.Option(min=1, help="processes")]
_SeedsOpt = Annotated[str, typer.Option(help="map seeds, comma-separated")]
_MemoriesOpt = Annotated[str, typer.Option(help="tm,none (none: the memory's ablation)")]
_BackboneOpt = Annotated[str | None, typer.Option(help="default: the service's")]
_TablesOpt = Annotated[Path | None, typer.Option(help="only the tables, from these JSON lines")]


@app.command("rules")
def eval_rules(
    data: _DataOpt = None,
    out: _LinesOpt = Path("rules.jsonl"),
    jobs: _JobsOpt = 1,
    seeds: _SeedsOpt = "42,1,7,100,2024",
    rules: Annotated[str, typer.Option(help="rules switched off, comma-separated (all: none)")] = "",
    memories: _MemoriesOpt = "tm,none",
    windows: Annotated[int, typer.Option(min=0, help="the first N windows of each half (0: every one)")] = 0,
    backbone: _BackboneOpt = None,
    tables: _TablesOpt = None,
) -> None:
    """Every learning and answering rule switched off one at a time, over every window of both halves,
    in both modes, over map seeds, with and without the memory; and the revisit threshold chosen on
    `tune` (service/evaluation/rules.py, docs/results.md §10.14)."""
    from service.evaluation import rules as costed

    _lines_then_tables(costed, tables, data, lambda d: costed.rules_runs(
        data=d, out=out, jobs=jobs, seeds=tuple(int(s) for s in seeds.split(",")),
        rules=tuple(rules.split(",")) if rules else costed.RULES, memories=tuple(memories.split(",")),
        windows=windows, backbone=backbone))


@app.command("starts")
def eval_starts(
    data: _DataOpt = None,
    seed: Annotated[int, typer.Option(help="the map's seed (42: a new map's)")] = 42,
    starts: Annotated[str, typer.Option(help="files into the window each lap starts, comma-separated")]
    = "0,23,57",
    kinds: Annotated[str, typer.Option(help="winter, flat, noise (rules' lap kinds), comma-separated")]
    = "winter,flat",
    windows: Annotated[str, typer.Option(help="half:lo,... (default: every window of both halves)")] = "",
    backbone: _BackboneOpt = None,
) -> None:
    """The localise mode's laps of `eval rules` started part-way into their window: the share of frames
    named within one file (service/evaluation/rules.py `start_shares`, docs/results.md §11)."""
    from service.evaluation import rules as costed

    if data is None:
        raise typer.BadParameter("--data is needed (the Nordland folder)")
    try:
        pairs = [w.split(":") for w in windows.split(",")] if windows else []
        chosen = tuple((h, int(lo)) for h, lo in pairs) or None
    except ValueError as e:
        raise typer.BadParameter(f"--windows takes half:lo,... (e.g. test:994): {windows!r}") from e
    try:
        at = tuple(int(s) for s in starts.split(","))
    except ValueError as e:
        raise typer.BadParameter(f"--starts takes files into the window, e.g. 0,23,57: {starts!r}") from e
    try:
        costed.check_starts(at, tuple(kinds.split(",")), chosen)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
    lines = costed.start_shares(data=data, seed=seed, starts=at, kinds=tuple(kinds.split(",")),
                                windows=chosen, backbone=backbone)
    print(costed.starts_table(lines), end="")


def _lines_then_tables(module: Any, tables: Path | None, data: Path | None,
                       run: Callable[[Path], list[dict[str, Any]]]) -> None:
    """`module`'s tables from the lines in `tables`, or from the lines of `run(data)` (a bad option:
    exit 2)."""
    if tables is not None:
        print(module.tables(module.read(tables)), end="")
        return
    if data is None:
        raise typer.BadParameter("--data is needed (the Nordland folder)")
    try:
        lines = run(data)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
    print(module.tables(lines), end="")


@app.command("projections")
def eval_projections(
    data: _DataOpt = None,
    out: _LinesOpt = Path("projections.jsonl"),
    jobs: _JobsOpt = 1,
    seeds: _SeedsOpt = "42,1,7,100,2024",
    variants: Annotated[str, typer.Option(help="today, centred, concat:K, wide:K, wide-dense:K, vote:K, "
                                               "pca:R, whiten:R, adapt:T, comma-separated (default: each "
                                               "once)")] = "",
    memories: _MemoriesOpt = "tm,none",
    halves: Annotated[str, typer.Option(help="tune,test")] = "tune,test",
    windows: Annotated[int, typer.Option(min=0, help="the first N windows of each half (0: every one; "
                                                     "`tune`'s first is the hardest)")] = 0,
    kinds: Annotated[str, typer.Option(help="lap-2 kinds: winter,flat,noise")] = "winter",
    backbone: _BackboneOpt = None,
    tables: _TablesOpt = None,
) -> None:
    """The localise mode with the sLSBH projection varied (several voted or stacked, fitted on the map's
    own frames), over map seeds, on the windows of `eval rules` (service/evaluation/projections.py,
    docs/results.md §10.16)."""
    from service.evaluation import projections

    _lines_then_tables(projections, tables, data, lambda d: projections.projection_runs(
        data=d, out=out, jobs=jobs, seeds=tuple(int(s) for s in seeds.split(",")),
        variants=tuple(variants.split(",")) if variants else projections.VARIANTS,
        memories=tuple(memories.split(",")), halves=tuple(halves.split(",")), windows=windows,
        kinds=tuple(kinds.split(",")), backbone=backbone))


@app.command("passes")
def eval_passes(
    data: Annotated[Path, typer.Option(help="the Nordland folder (summer/, winter/)")],
    half: Annotated[str, typer.Option(help="tune | test")] = "test",
    start: Annotated[int, typer.Option(min=0, help="the route's first frame in the half")] = 0,
    frames: Annotated[int, typer.Option(min=20, help="frames of the route")] = 200,
    passes: Annotated[str, typer.Option(help="numbers of learned passes, comma-separated")] = "1,2,3,5,10",
    kinds: Annotated[str, typer.Option(help="same,alternating conditions")] = "same,alternating",
    memory: Annotated[str, typer.Option(help="tm | none")] = "tm",
    month: Annotated[int, typer.Option(min=0, help="days of the three-robot month (0: none)")] = 0,
    stream: Annotated[bool, typer.Option(help="also one learning stream driving three laps")] = True,
    tolerance: int = 2,
    backbone: Annotated[str | None, typer.Option(help="default: the service's")] = None,
    seed: int = 1,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the result here too")] = None,
) -> None:
    """A route learned over many passes, then localised: place identity, consolidation and the map's
    growth, beside the same without consolidation (service/evaluation/passes.py)."""
    from service.evaluation.passes import passes_runs

    try:
        passes_runs(data=data, half=half, start=start, frames_n=frames, passes=passes, kinds=kinds,
                    memory=memory, month_days=month, stream=stream, tolerance=tolerance, backbone=backbone,
                    seed=seed, json_path=json_out)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e


def _json_object(text: str, option: str) -> dict[str, Any] | None:
    """An option's JSON object (None for an empty option); raises typer.BadParameter otherwise."""
    if not text:
        return None
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        raise typer.BadParameter(f"{option}: not JSON ({e})") from None
    if not isinstance(value, dict):
        raise typer.BadParameter(f"{option}: a JSON object is wanted")
    return value


@app.command("slam")
def eval_slam(
    data: Annotated[Path | None, typer.Option(help="the Nordland folder (summer/, winter/)")] = None,
    half: Annotated[str, typer.Option(help="tune | test")] = "tune",
    routes: Annotated[str | None, typer.Option(help="comma-separated routes (default: all)")] = None,
    methods: str = "service-slam,service-slam-without-tm,service,openseqslam",
    thresholds: Annotated[str, typer.Option(help="revisit thresholds, comma-separated")] = "",
    tolerance: int = 1,
    rate: Annotated[float, typer.Option(help="false-revisit rate of the calibration")] = 0.001,
    backbone: Annotated[str | None, typer.Option(help="default: the service's")] = None,
    seed: int = 1,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the result here too")] = None,
    grid: Annotated[Path | None, typer.Option(help="the grid world's folder instead of --data")] = None,
    adapt_tau: Annotated[int, typer.Option(help="the maps' slsbh.adapt_tau (0: none)")] = 0,
    seeds: Annotated[int, typer.Option(min=1, help="with --grid: the memory over TM seeds 1..N")] = 1,
    localiser: Annotated[str, typer.Option(help='the maps\' localiser options as JSON, e.g. '
                                                '\'{"condition_frames": 0}\'')] = "",
    suite: Annotated[bool, typer.Option(help="the stress suite instead (service/evaluation/stress.py): "
                                             "every window of both halves, 3 seeds")] = False,
    quick: Annotated[bool, typer.Option(help="with --suite: one window, five cases, two seeds")] = False,
    threshold: Annotated[float | None, typer.Option(min=0.0, max=1.0, help="with --suite: the maps' "
                                                    "revisit_threshold (default: a new map's)")] = None,
    cases: Annotated[str, typer.Option(help="with --suite: only these cases, comma-separated (default: "
                                            "the suite's, or --quick's)")] = "",
) -> None:
    """Loop closure while mapping on routes made from the Nordland halves, or the grid world's loops
    (service/evaluation/slam.py); `--suite`: the loop-closure stress suite (service/evaluation/stress.py)."""
    from service.evaluation import slam

    if suite:
        from service.evaluation import stress

        if data is None:
            raise typer.BadParameter("--suite needs --data (the Nordland folder)")
        chosen = tuple(c for c in cases.split(",") if c) or None
        unknown = sorted(set(chosen or ()) - set(stress.CASES))
        if unknown:
            known = ", ".join(stress.CASES)
            raise typer.BadParameter(f"unknown case(s) {', '.join(unknown)}; known: {known}",
                                     param_hint="--cases")
        stress.suite_runs(data=data, quick=quick, backbone=backbone, json_path=json_out,
                          localiser=_json_object(localiser, "--localiser"), threshold=threshold, cases=chosen)
        return
    try:
        slam.slam_runs(data=data, half=half, routes=routes or ",".join(slam.ROUTES), methods=methods,
                       thresholds=[float(t) for t in thresholds.split(",") if t], tolerance=tolerance,
                       rate=rate, backbone=backbone, seed=seed, json_path=json_out, grid_dir=grid,
                       adapt_tau=adapt_tau, seeds=seeds, localiser=_json_object(localiser, "--localiser"))
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
