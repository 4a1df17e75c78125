"""The `cortexloc` command line: a stable contract that scripts and acceptance checks call.

    cortexloc presets
    cortexloc eval grid --sdr FILE --places FILE [--scoring paper|clean] [--preset NAME] [--seeds K]
                        [--ds N] [--json OUT] [--plots DIR]
    cortexloc eval grid --generate --aliasing A --noise N [--loops L] [...same options]
    cortexloc eval images --db DIR --query DIR [--methods M,...] [--ds N] [--gt FILE] [--preset NAME]
                          [--backbone B] [--resize R] [--seeds K] [--json OUT] [--plots DIR]
    cortexloc bench tm [--columns C] [--cells K] [--active A] [--steps S] [--preset NAME] [--json OUT]
    cortexloc serve [--host H] [--port P] [--data-dir DIR]
    cortexloc import FILE.tar [--data-dir DIR]
    cortexloc verify [--map M] [--data-dir DIR]
    cortexloc ingest SOURCE --map M [--stream S] [--learn | --localise] [--url URL | --data-dir DIR]
                     [--topic T] [--every N] [--json] [--prefetch K] [--label-stamp] [--api-key KEY]

Tables go to stdout, progress and warnings to stderr, machine-readable results to --json.
"""

from __future__ import annotations

import json
import platform
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
import typer

from models import presets
from service.ingest.command import ingest_command

if TYPE_CHECKING:
    from service.settings import Settings

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="cortexloc: visual place recognition with a Hierarchical Temporal Memory.")
eval_app = typer.Typer(no_args_is_help=True, help="Reproduce and measure the science.")
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks (medians; run on demand).")
weights_app = typer.Typer(no_args_is_help=True, help="Install AlexNet conv1..conv3 weights.")
app.add_typer(eval_app, name="eval")
app.add_typer(bench_app, name="bench")
app.add_typer(weights_app, name="weights")


def _progress(label: str):
    """A one-line progress bar on stderr (stdout stays a clean table)."""
    def show(done: int, total: int) -> None:
        width = 30
        filled = int(width * done / max(total, 1))
        end = "\n" if done >= total else ""
        sys.stderr.write(f"\r{label} [{'#' * filled}{'.' * (width - filled)}] {done}/{total}{end}")
        sys.stderr.flush()
    return show


def _write_json(path: Path | None, payload: dict[str, Any]) -> None:
    if path is None:
        return
    from models.files import atomic_write

    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(payload, indent=2, default=_jsonable).encode()
    atomic_write(path, lambda f: f.write(text))


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _check_backbone(name: str) -> None:
    """--backbone must name a backbone of the registry (models.frontend.backbones)."""
    from models.frontend import backbones

    if name not in backbones.names():
        raise typer.BadParameter(f"must be one of {', '.join(backbones.names())}", param_hint="--backbone")


def _provenance() -> dict[str, Any]:
    return {"command": " ".join(["cortexloc", *sys.argv[1:]]), "python": platform.python_version(),
            "numpy": np.__version__}


@app.command("presets")
def list_presets() -> None:
    """Print every preset name, a tab, and its one-line description."""
    for name in presets.names():
        typer.echo(f"{name}\t{presets.describe(name)}")


@eval_app.command("grid")
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
    methods: Annotated[str, typer.Option(help="Comma-separated: pairwise,pairwise-seq,mcn,htm (pairwise-seq: "
                                          "the sequence matcher on the input codes; it and pairwise always "
                                          "run beside mcn and htm).")] = "pairwise,pairwise-seq,mcn,htm",
    ds: Annotated[int, typer.Option(min=2, help="Steps per sequence path of pairwise-seq.")] = 10,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write results as JSON here.")] = None,
    plots_dir: Annotated[Path | None, typer.Option("--plots", help="Write PR and similarity PNGs here.")]
    = None,
) -> None:
    """Grid-world evaluation (docs/design/science.md §2): pairwise InputSDR, MCN and HTM, over seeds."""
    from models.evaluation import gridworld, runner

    if scoring not in ("paper", "clean"):
        raise typer.BadParameter("must be paper or clean", param_hint="--scoring")
    for name in (preset, mcn_preset):
        if name not in presets.confs:
            raise typer.BadParameter(f"unknown preset {name!r}; see `cortexloc presets`")
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

    result = runner.grid_experiment(
        data_for_seed, scoring=scoring, preset=preset, mcn_preset=mcn_preset, seeds=seeds, seed=seed,
        methods=method_list, ds=ds, plots_dir=plots_dir,
        progress=_progress("grid") if seeds > 1 else None)
    for w in result["methods"].get("htm", {}).get("warnings", []):
        typer.echo(f"warning ({preset}): {w}", err=True)
    result["provenance"] = _provenance()
    _write_json(json_out, result)
    typer.echo(format_grid_table(result))


def format_grid_table(result: dict[str, Any]) -> str:
    """A readable table of a grid result (stdout)."""
    data = result["data"]
    if data.get("source") == "generated":
        what = f"generated a={data['aliasing']} n={data['noise']} loops={data['loops']} ({data['mode']})"
    else:
        what = f"published {Path(str(data.get('sdr_file', '?'))).name}"
    lines = [f"grid world: {what}; scoring={result['scoring']}; seeds={result['seeds']}",
             f"{'method':<12} {'AUC mean':>9} {'sd':>7} {'min':>8} {'max':>8} {'R@1':>7} {'R@5':>7} "
             f"{'R@100P':>7}  notes"]
    for m, e in result["methods"].items():
        lines.append(f"{m:<12} {e['auc_mean']:>9.6f} {e['auc_sd']:>7.4f} {e['auc_min']:>8.4f} "
                     f"{e['auc_max']:>8.4f} {e['recall_at_1_mean']:>7.3f} {e['recall_at_5_mean']:>7.3f} "
                     f"{e['recall_at_100p_mean']:>7.3f}  {_method_notes(m, e)}")
    return "\n".join(lines)


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


@eval_app.command("images")
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
    backbone: Annotated[str | None, typer.Option(help="a registered backbone: alexnet | efficientnet-lite0 "
                                                      "(default: the service's)")] = None,
    resize: Annotated[str | None, typer.Option(help="crop | squash (default: the service's)")] = None,
    methods: Annotated[str, typer.Option(help="Comma-separated: cosine,slsbh,mcn,htm (one frame); "
                                          "openseqslam (the reference on grey pixels); cosine-seq,"
                                          "slsbh-seq,mcn-seq,htm-seq (the same sequence matcher on each "
                                          "single-image similarity). Memory methods bring their ablations.")]
    = "cosine,slsbh,htm,openseqslam,cosine-seq,slsbh-seq,htm-seq",
    ds: Annotated[int, typer.Option(min=2, help="Frames per sequence path, centred on the query.")] = 10,
    preset: Annotated[str | None, typer.Option(help="Temporal Memory preset (default: the service's; the "
                                                    "paper's is cba2020-nordland).")] = None,
    mcn_preset: Annotated[str, typer.Option(help="MCN preset.")] = "mcn-nordland",
    s: Annotated[float | None, typer.Option(min=0.0, max=0.5, help="sLSBH sparsity (default: the "
                                                                    "preset's, else 0.25).")] = None,
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
    seeds: Annotated[int, typer.Option(min=1)] = 3,
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

    from models.evaluation import ground_truth, plots, sequences
    from models.evaluation import seqslam as seq
    from models.frontend import encoder as encoder_mod
    from service.settings import Settings

    # The service's defaults, read from their one home each (docs/design/service.md §8,
    # models.frontend.encoder).
    preset = preset or Settings.model_fields["default_preset"].default
    backbone = backbone or encoder_mod.default_conf["backbone"]
    resize = resize or encoder_mod.default_conf["resize"]
    method_list = [m.strip() for m in methods.split(",") if m.strip()]
    bad = set(method_list) - set(sequences.METHODS)
    if bad or not method_list:
        raise typer.BadParameter(f"must be among {', '.join(sequences.METHODS)}", param_hint="--methods")
    method_list = sequences.with_ablations(method_list)
    for name in (preset, mcn_preset):
        if name not in presets.confs:
            raise typer.BadParameter(f"unknown preset {name!r}; see `cortexloc presets`")
    _check_backbone(backbone)
    if resize not in ("crop", "squash"):
        raise typer.BadParameter("must be crop or squash", param_hint="--resize")
    s_conf = presets.slsbh_params(preset)
    sparsity = float(s if s is not None else s_conf["s"])
    if not 0 < sparsity <= 0.5:
        raise typer.BadParameter("must be in (0, 0.5]", param_hint="--s")
    gt_matrix = None
    try:
        if gt is not None:
            if offset or limit is not None or drop_dark > 0:
                raise typer.BadParameter("--gt indexes the whole folders: leave out --offset, --limit and "
                                         "--drop-dark", param_hint="--gt")
            db_names, q_names = sequences.image_names(db), sequences.image_names(query)
            gt_matrix = ground_truth.load(gt, len(db_names), len(q_names), q_names)
            db_keep = q_keep = None
        else:
            # Features are computed (and cached) for the whole paired route once; a window is a slice.
            db_names = q_names = sequences.paired_names(db, query)
            db_keep = q_keep = np.arange(len(q_names))[offset: None if limit is None else offset + limit]
            if db_keep.size == 0:
                raise ValueError(f"offset {offset} leaves no pair of the {len(q_names)} in common")
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
    cache_dir = cache or Path(os.environ.get("CORTEXLOC_CACHE_DIR", Path.home() / ".cache" / "cortexloc"))
    if method_list == ["openseqslam"]:  # it reads pixels: no backbone to run
        enc = None
        feats = {label: np.zeros((len(names), 0), np.float32)
                 for label, names in (("db", db_names), ("query", q_names))}
    else:
        enc = encoder_mod.Encoder({"backbone": backbone, "resize": resize})  # features only: no projection
        feats = {label: sequences.cached_features(enc, [folder / n for n in names], cache_dir / "features",
                                                  progress=_progress(f"features {label}"))
                 for label, folder, names in (("db", db, db_names), ("query", query, q_names))}
    if db_keep is not None:
        if drop_dark > 0:
            dark = (sequences.dark_frames([db / db_names[i] for i in db_keep], drop_dark)
                    | sequences.dark_frames([query / q_names[i] for i in q_keep], drop_dark))
            db_keep = q_keep = db_keep[~dark]
            if len(db_keep) < 2:
                raise typer.BadParameter("fewer than two pairs are left", param_hint="--drop-dark")
        feats = {"db": feats["db"][db_keep], "query": feats["query"][q_keep]}
        db_names = q_names = [q_names[i] for i in q_keep]
    db_paths, q_paths = [db / n for n in db_names], [query / n for n in q_names]
    frames = ((seq.load_frames(db_paths), seq.load_frames(q_paths)) if "openseqslam" in method_list
              else None)
    try:
        result = sequences.image_experiment(
            feats["db"], feats["query"], methods=method_list, preset=preset, mcn_preset=mcn_preset,
            k=int(s_conf["k"]), s=sparsity, seeds=seeds, seed=seed, tolerance=tolerance, reset=reset,
            adapt_tau=adapt, reverse_query=reverse_query, ds=ds, gt=gt_matrix, frames=frames,
            progress=_progress("runs") if seeds > 1 else None)
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
                        "k": int(s_conf["k"]), "s": sparsity, "ds": ds, "adapt_tau": adapt,
                        "drop_dark": drop_dark, "reverse_query": reverse_query, "tolerance": tolerance,
                        "reset": reset, "seeds": seeds, "seed": seed}
    result["provenance"] = _provenance()
    _write_json(json_out, result)
    typer.echo(format_images_table(result))


def format_images_table(result: dict[str, Any]) -> str:
    """A readable table of an image result (stdout): the settings it ran with, then both metrics."""
    c = result["config"]
    lines = [f"{Path(c['db']).name} -> {Path(c['query']).name}: {c['pairs']} queries ({c['first']} .. "
             f"{c['last']}), ground truth {c['gt']}, tolerance ±{c['tolerance']}",
             f"preset {c['preset']}, backbone {c['backbone']} [{c['weights']} weights], "
             f"resize {c['resize']}, s={c['s']}, adapt={c['adapt_tau']}, "
             f"{'reset' if c['reset'] else 'no reset'}, seeds={c['seeds']}, ds={c['ds']}; "
             f"{len(result['queries'])} queries scored",
             "all pairs = the paper's AUC (§8.2); per query = each query's best match and its confidence",
             f"{'method':<12} {'AUC pairs':>9} {'min':>7} {'max':>7} {'AUC query':>9} {'R@1':>6} {'R@5':>6} "
             f"{'R@100P':>7} {'s/run':>7}  notes"]
    for m, e in result["methods"].items():
        lines.append(f"{m:<12} {e['auc_mean']:>9.4f} {e['auc_min']:>7.4f} {e['auc_max']:>7.4f} "
                     f"{e['query_auc_mean']:>9.4f} {e['recall_at_1_mean']:>6.3f} "
                     f"{e['recall_at_5_mean']:>6.3f} {e['query_recall_at_100p_mean']:>7.3f} "
                     f"{e['seconds_mean']:>7.2f}  {_method_notes(m, e)}")
    return "\n".join(lines)


@bench_app.command("tm")
def bench_tm(
    columns: Annotated[int, typer.Option(min=1)] = 2048,
    cells: Annotated[int, typer.Option(min=1)] = 4,
    active: Annotated[int, typer.Option(min=1)] = 40,
    steps: Annotated[int, typer.Option(min=1)] = 5000,
    preset: Annotated[str, typer.Option(help="TM preset supplying caps and thresholds.")] = "cortexloc-grid",
    period: Annotated[int, typer.Option(min=0, help="Repeat a sequence of this length (0: all novel).")] = 0,
    max_segments: Annotated[int | None, typer.Option(min=1, help="Override maxSegmentsPerCell.")] = None,
    max_synapses: Annotated[int | None, typer.Option(min=1, help="Override maxSynapsesPerSegment.")] = None,
    json_out: Annotated[Path | None, typer.Option("--json")] = None,
) -> None:
    """Temporal Memory speed and memory: median ms/step and RSS growth over learning steps."""
    from models.evaluation.bench import bench_tm as run

    if preset not in presets.confs:
        raise typer.BadParameter(f"unknown preset {preset!r}; see `cortexloc presets`")
    if active > columns:
        raise typer.BadParameter("--active must not exceed --columns")
    overrides = {k: v for k, v in (("maxSegmentsPerCell", max_segments),
                                   ("maxSynapsesPerSegment", max_synapses)) if v is not None}
    result = run(columns=columns, cells=cells, active=active, steps=steps, preset=preset, period=period,
                 overrides=overrides)
    result["provenance"] = _provenance()
    _write_json(json_out, result)
    typer.echo(f"TM {columns}x{cells}, {active} active, {steps} steps ({preset}): "
               f"median {result['ms_per_step_median']:.3f} ms/step, p90 {result['ms_per_step_p90']:.3f}, "
               f"RSS growth {result['rss_growth_mb']:.1f} MB, segments {result['segments']}, "
               f"synapses {result['synapses']}, bytes {result['bytes']}")


@bench_app.command("encoder")
def bench_encoder(
    backbone: Annotated[str, typer.Option(help="a registered backbone: alexnet | efficientnet-lite0")]
    = "alexnet",
    repeats: Annotated[int, typer.Option(min=1)] = 15,
    threads: Annotated[int, typer.Option(min=1, help="torch threads")] = 1,
    projection: Annotated[str, typer.Option(help="dense | sparse")] = "dense",
    json_out: Annotated[Path | None, typer.Option("--json")] = None,
) -> None:
    """Whole-encoder batch-1 latency and batch-16 throughput beside a bare backbone forward."""
    from models.evaluation.bench import bench_encoder as run

    _check_backbone(backbone)
    if projection not in ("dense", "sparse"):
        raise typer.BadParameter("must be dense or sparse", param_hint="--projection")
    result = run(backbone=backbone, repeats=repeats, threads=threads, projection=projection)
    result["provenance"] = _provenance()
    _write_json(json_out, result)
    st = result["batch16_stage_ms_median"]
    typer.echo(f"encoder {result['encoder']} ({projection} projection, {threads} thread(s)): batch 1 "
               f"{result['batch1_ms_median']:.1f} ms; batch 16 {result['batch16_images_per_s']:.1f} img/s "
               f"vs bare backbone {result['bare_conv3_batch16_images_per_s']:.1f} img/s "
               f"(ratio {result['ratio_to_bare']:.2f}); stages at batch 16 (ms): "
               + ", ".join(f"{k} {v:.1f}" for k, v in st.items()))


@weights_app.command("download")
def weights_download(
    dest: Annotated[Path | None, typer.Option(help="Cache directory (default: $CORTEXLOC_WEIGHTS_DIR "
                                                   "or ~/.cache/cortexloc/weights).")] = None,
    url: Annotated[str | None, typer.Option(help="Checkpoint URL (default: torchvision's).")] = None,
) -> None:
    """Fetch torchvision's AlexNet checkpoint, verify its SHA-256 (7be5be79...), keep conv1..conv3."""
    from models.frontend import weights

    _install(lambda: weights.download_alexnet(dest, **({"url": url} if url else {})))


@weights_app.command("import")
def weights_import(
    path: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="alexnet-owt-7be5be79.pth")],
    dest: Annotated[Path | None, typer.Option(help="Cache directory.")] = None,
) -> None:
    """Install weights from a local copy of torchvision's checkpoint (verified the same way)."""
    from models.frontend import weights

    _install(lambda: weights.import_alexnet(path, dest))


def _install(run: Any) -> None:
    """Run a weights install; say where it went and how to point the service at it, or why not."""
    from models.frontend import weights

    try:
        path = run()
    except (weights.WeightsError, ValueError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from e
    typer.echo(f"installed {path}\nthe encoder finds it there; or set CORTEXLOC_WEIGHTS_PATH={path}")


def process_settings(*, host: str | None = None, port: int | None = None, data_dir: Path | None = None,
                     **env_defaults: str) -> Settings:
    """The settings of a service run by this process (`serve`, in-process `ingest`): CORTEXLOC_* with the
    given options over them and `env_defaults` under them, read once; exits 2 naming a bad variable.

    Also sets OpenCV's pixel guard, which OpenCV reads once when cv2 is first imported (by the app)."""
    import os

    from service.settings import ConfigError, Settings

    env = {**env_defaults, **os.environ}
    for var, value in (("CORTEXLOC_HOST", host), ("CORTEXLOC_PORT", port), ("CORTEXLOC_DATA_DIR", data_dir)):
        if value is not None:
            env[var] = str(value)
    try:
        settings = Settings.from_env(env)  # read once, here; the app gets this object
    except ConfigError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from e
    os.environ["OPENCV_IO_MAX_IMAGE_PIXELS"] = str(settings.max_pixels)
    return settings


@app.command("serve")
def serve(
    host: Annotated[str | None, typer.Option(help="Bind address (default: $CORTEXLOC_HOST or 127.0.0.1).")]
    = None,
    port: Annotated[int | None, typer.Option(min=0, max=65535,
                                             help="Bind port (default: $CORTEXLOC_PORT or 8000).")] = None,
    data_dir: Annotated[Path | None, typer.Option(help="Root of all state (default: $CORTEXLOC_DATA_DIR "
                                                       "or ./var).")] = None,
) -> None:
    """Run the HTTP service (one uvicorn worker: maps live in process memory). Other settings: CORTEXLOC_*."""
    settings = process_settings(host=host, port=port, data_dir=data_dir)

    import uvicorn

    from service.app import create_app
    from service.limits import HEAD_MAX_BYTES
    from service.server import ProblemH11Protocol

    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, workers=1, lifespan="on",
                log_level=settings.log_level.lower(), http=ProblemH11Protocol,
                h11_max_incomplete_event_size=HEAD_MAX_BYTES)


@app.command("import")
def import_map(
    tar: Annotated[Path, typer.Argument(exists=True, dir_okay=False,
                                        help="A snapshot tar from /v1/maps/{map}/snapshots/{id}/download")],
    data_dir: Annotated[Path | None, typer.Option(help="Data directory (default: $CORTEXLOC_DATA_DIR "
                                                       "or ./var).")] = None,
) -> None:
    """Create a map from a snapshot tar, verifying every checksum (run while the server is stopped).

    Refused before anything is written: ids that the API would refuse, a map that exists, a tar that
    declares more than CORTEXLOC_MAX_IMPORT_BYTES or than the free space."""
    from types import SimpleNamespace

    from service.maps.registry import MapRegistry
    from storage.snapshots import SnapshotInvalid

    settings = process_settings(data_dir=data_dir)
    root = settings.data_dir
    registry = MapRegistry(root, SimpleNamespace(identity="", feature_dim=0), settings=settings)
    try:
        map_id = registry.import_snapshot(tar, settings.max_import_bytes)
    except (SnapshotInvalid, ValueError, OSError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from e
    finally:
        registry.catalog.close()
    typer.echo(f"imported map {map_id!r} into {root}; it recovers from the snapshot when the server starts")


@app.command("verify")
def verify(
    map_id: Annotated[str | None, typer.Option("--map", help="One map (default: every map).")] = None,
    data_dir: Annotated[Path | None, typer.Option(help="Data directory (default: $CORTEXLOC_DATA_DIR "
                                                       "or ./var).")] = None,
) -> None:
    """Check maps offline, changing nothing: replay every row from the first and compare its stored
    winner cells, verify every snapshot's checksums and the projection. Exit 1 on any problem."""
    from service.maps.recovery import verify_map
    from storage.catalog import Catalog

    root = process_settings(data_dir=data_dir).data_dir
    try:
        catalog = Catalog.open(root / "catalog.sqlite", readonly=True)
        records = [r for r in catalog.list_maps() if map_id is None or r.map_id == map_id]
    except Exception as e:  # a missing or garbage catalog: say so, as a failed check
        typer.echo(f"error: cannot read the catalog in {root}: {e}", err=True)
        raise typer.Exit(1) from e
    if map_id is not None and not records:
        catalog.close()
        typer.echo(f"error: no map {map_id!r} in {root}", err=True)
        raise typer.Exit(2)
    bad = 0
    try:
        for record in records:
            show = _progress(f"verify {record.map_id}")

            def tick(done: int, total: int, show: Any = show) -> None:
                # Every ~1% (and the last row): the bar is redrawn, not the terminal flooded.
                if done == total or done % max(1, total // 100) == 0:
                    show(done, total)

            check = verify_map(catalog, record, progress=tick)
            bad += not check.ok
            rate = check.rows / check.seconds if check.seconds else 0.0
            typer.echo(f"map {record.map_id}: {'ok' if check.ok else 'PROBLEMS'}; {check.rows} rows "
                       f"replayed in {check.seconds:.2f} s ({rate:.0f} rows/s), "
                       f"{len(check.mismatches)} mismatched; snapshots {len(check.snapshots_ok)} ok, "
                       f"{len(check.snapshots_bad)} bad")
            if check.mismatches:
                seqs = ", ".join(map(str, check.mismatches))
                typer.echo(f"  stored winner cells differ from the replay at seq {seqs}")
            for sid, why in check.snapshots_bad.items():
                typer.echo(f"  snapshot {sid}: {why}")
            for problem in check.problems:
                typer.echo(f"  {problem}")
    finally:
        catalog.close()
    typer.echo(f"{len(records)} map(s) checked, {bad} with problems")
    if bad:
        raise typer.Exit(1)
app.command("ingest")(ingest_command)


def main() -> None:  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
