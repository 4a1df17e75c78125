"""The `cortexloc` command line: a stable contract that scripts and acceptance checks call.

    cortexloc presets
    cortexloc eval grid --sdr FILE --places FILE [--scoring paper|clean] [--preset NAME] [--seeds K]
                        [--json OUT] [--plots DIR]
    cortexloc eval grid --generate --aliasing A --noise N [--loops L] [...same options]
    cortexloc bench tm [--columns C] [--cells K] [--active A] [--steps S] [--preset NAME] [--json OUT]
    cortexloc serve [--host H] [--port P] [--data-dir DIR]

Tables go to stdout, progress and warnings to stderr, machine-readable results to --json.
"""

from __future__ import annotations

import json
import platform
import sys
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from models import presets

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
    methods: Annotated[str, typer.Option(help="Comma-separated: pairwise,mcn,htm.")] = "pairwise,mcn,htm",
    json_out: Annotated[Path | None, typer.Option("--json", help="Write results as JSON here.")] = None,
    plots_dir: Annotated[Path | None, typer.Option("--plots", help="Write PR and similarity PNGs here.")]
    = None,
) -> None:
    """Grid-world evaluation (science.md §2): pairwise InputSDR, MCN and HTM, over seeds."""
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
        methods=method_list, plots_dir=plots_dir,
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
             f"{'method':<10} {'AUC mean':>9} {'sd':>7} {'min':>8} {'max':>8} {'R@1':>7} {'R@5':>7} "
             f"{'R@100P':>7}  notes"]
    for m, e in result["methods"].items():
        lines.append(f"{m:<10} {e['auc_mean']:>9.6f} {e['auc_sd']:>7.4f} {e['auc_min']:>8.4f} "
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
    query: Annotated[Path, typer.Option(help="Query image folder (e.g. winter); same name = same place.",
                                        exists=True, file_okay=False)],
    offset: Annotated[int, typer.Option(min=0, help="First pair (in sorted name order).")] = 0,
    limit: Annotated[int | None, typer.Option(min=2, help="Number of pairs (default: all).")] = None,
    backbone: Annotated[str, typer.Option(help="alexnet | efficientnet-lite0")] = "alexnet",
    resize: Annotated[str, typer.Option(help="crop | squash")] = "crop",
    methods: Annotated[str, typer.Option(help="Comma-separated: cosine,slsbh,mcn,htm,seqslam and "
                                          "slsbh-seq,mcn-seq,htm-seq (single-image similarity through "
                                          "the seqslam filter).")]
    = "cosine,slsbh,mcn,htm,seqslam,slsbh-seq,htm-seq",
    preset: Annotated[str, typer.Option(help="Temporal Memory preset.")] = "cba2020-nordland",
    mcn_preset: Annotated[str, typer.Option(help="MCN preset.")] = "mcn-nordland",
    s: Annotated[float | None, typer.Option(min=0.0, max=0.5, help="sLSBH sparsity (default: the "
                                                                    "preset's, else 0.25).")] = None,
    tolerance: Annotated[int, typer.Option(min=0, help="±files that count as the same place.")] = 0,
    reset: Annotated[bool, typer.Option("--reset/--no-reset",
                                        help="Reset between database and query (the paper does not).")]
    = False,
    adapt: Annotated[int, typer.Option(min=0, help="Running-mean subtraction time constant in frames "
                                       "(models.adaptation), for every method; 0 = off.")] = 0,
    reverse_query: Annotated[bool, typer.Option("--reverse-query", help="Drive the query sequence "
                                                "backwards (a route driven the other way).")] = False,
    drop_dark: Annotated[float, typer.Option(min=0.0, help="Drop pairs where either frame's mean grey is "
                                                          "below this (0 = keep all; §8.5 uses 20).")] = 0.0,
    seeds: Annotated[int, typer.Option(min=1)] = 3,
    seed: Annotated[int, typer.Option(help="Experiment seed.")] = 0,
    cache: Annotated[Path | None, typer.Option(help="Feature cache folder (default: "
                                                    "$CORTEXLOC_CACHE_DIR or ~/.cache/cortexloc).")] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write results as JSON here.")] = None,
    plots_dir: Annotated[Path | None, typer.Option("--plots", help="Write PR and similarity PNGs here.")]
    = None,
) -> None:
    """Cross-season evaluation on image sequences (science.md §8.5): learn db, then query, per method."""
    import os

    from models.encoder import Encoder
    from models.evaluation import plots, sequences

    method_list = [m.strip() for m in methods.split(",") if m.strip()]
    bad = set(method_list) - set(sequences.METHODS)
    if bad or not method_list:
        raise typer.BadParameter(f"must be among {', '.join(sequences.METHODS)}", param_hint="--methods")
    for name in (preset, mcn_preset):
        if name not in presets.confs:
            raise typer.BadParameter(f"unknown preset {name!r}; see `cortexloc presets`")
    if backbone not in ("alexnet", "efficientnet-lite0"):
        raise typer.BadParameter("must be alexnet or efficientnet-lite0", param_hint="--backbone")
    if resize not in ("crop", "squash"):
        raise typer.BadParameter("must be crop or squash", param_hint="--resize")
    s_conf = presets.get(preset).get("slsbh", {"k": 1024, "s": 0.25})
    sparsity = float(s if s is not None else s_conf["s"])
    if not 0 < sparsity <= 0.5:
        raise typer.BadParameter("must be in (0, 0.5]", param_hint="--s")
    try:
        names = sequences.paired_names(db, query, offset, limit)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
    if drop_dark > 0:
        dark = (sequences.dark_frames([db / n for n in names], drop_dark)
                | sequences.dark_frames([query / n for n in names], drop_dark))
        names = [n for n, d in zip(names, dark, strict=True) if not d]
        if len(names) < 2:
            raise typer.BadParameter("fewer than two pairs are left", param_hint="--drop-dark")
    cache_dir = cache or Path(os.environ.get("CORTEXLOC_CACHE_DIR", Path.home() / ".cache" / "cortexloc"))
    enc = Encoder({"backbone": backbone, "resize": resize})  # features only (embed): no projection built
    feats = {}
    for label, folder in (("db", db), ("query", query)):
        feats[label] = sequences.cached_features(enc, [folder / n for n in names], cache_dir / "features",
                                                 progress=_progress(f"features {label}"))
    result = sequences.image_experiment(
        feats["db"], feats["query"], methods=method_list, preset=preset, mcn_preset=mcn_preset,
        k=int(s_conf["k"]), s=sparsity, seeds=seeds, seed=seed, tolerance=tolerance, reset=reset,
        adapt_tau=adapt, reverse_query=reverse_query, progress=_progress("runs") if seeds > 1 else None)
    first = result.pop("first")
    if plots_dir is not None:
        plots_dir.mkdir(parents=True, exist_ok=True)
        plots.plot_pr_curves({m: (r["P"], r["R"]) for m, r in first.items()}, plots_dir / "pr.png",
                             f"{db.name} -> {query.name}, {len(names)} pairs (first seed)")
        for m, r in first.items():
            plots.plot_similarity(np.asarray(r["S"], dtype=float), plots_dir / f"similarity_{m}.png",
                                  f"{m}: similarity (database rows, query columns)")
    result["config"] = {"db": str(db), "query": str(query), "offset": offset, "limit": limit,
                        "pairs": len(names), "first": names[0], "last": names[-1], "encoder": enc.identity,
                        "weights": enc.describe()["weights"], "preset": preset, "mcn_preset": mcn_preset,
                        "k": int(s_conf["k"]), "s": sparsity, "adapt_tau": adapt,
                        "drop_dark": drop_dark, "reverse_query": reverse_query, "tolerance": tolerance,
                        "reset": reset,
                        "seeds": seeds, "seed": seed}
    result["provenance"] = _provenance()
    _write_json(json_out, result)
    typer.echo(f"{db.name} -> {query.name}: {len(names)} pairs ({names[0]} .. {names[-1]}), encoder "
               f"{enc.identity} [{result['config']['weights']} weights], s={sparsity}, adapt={adapt}, "
               f"tolerance ±{tolerance}, {'reset' if reset else 'no reset'}, seeds={seeds}")
    typer.echo(f"{'method':<9} {'AUC mean':>9} {'min':>7} {'max':>7} {'R@1':>6} {'R@5':>6} {'R@100P':>7} "
               f"{'s/run':>7}  notes")
    for m, e in result["methods"].items():
        typer.echo(f"{m:<9} {e['auc_mean']:>9.4f} {e['auc_min']:>7.4f} {e['auc_max']:>7.4f} "
                   f"{e['recall_at_1_mean']:>6.3f} {e['recall_at_5_mean']:>6.3f} "
                   f"{e['recall_at_100p_mean']:>7.3f} {e['seconds_mean']:>7.2f}  {_method_notes(m, e)}")


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
    from models.bench import bench_tm as run

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
    backbone: Annotated[str, typer.Option(help="alexnet | efficientnet-lite0")] = "alexnet",
    repeats: Annotated[int, typer.Option(min=1)] = 15,
    threads: Annotated[int, typer.Option(min=1, help="torch threads")] = 1,
    projection: Annotated[str, typer.Option(help="dense | sparse")] = "dense",
    json_out: Annotated[Path | None, typer.Option("--json")] = None,
) -> None:
    """Whole-encoder batch-1 latency and batch-16 throughput beside a bare backbone forward."""
    from models.bench import bench_encoder as run

    if backbone not in ("alexnet", "efficientnet-lite0"):
        raise typer.BadParameter("must be alexnet or efficientnet-lite0", param_hint="--backbone")
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
    from models import weights

    _install(lambda: weights.download_alexnet(dest, **({"url": url} if url else {})))


@weights_app.command("import")
def weights_import(
    path: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="alexnet-owt-7be5be79.pth")],
    dest: Annotated[Path | None, typer.Option(help="Cache directory.")] = None,
) -> None:
    """Install weights from a local copy of torchvision's checkpoint (verified the same way)."""
    from models import weights

    _install(lambda: weights.import_alexnet(path, dest))


def _install(run: Any) -> None:
    """Run a weights install; say where it went and how to point the service at it, or why not."""
    from models import weights

    try:
        path = run()
    except (weights.WeightsError, ValueError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from e
    typer.echo(f"installed {path}\nthe encoder finds it there; or set CORTEXLOC_WEIGHTS_PATH={path}")


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
    import os

    from service.settings import ConfigError, Settings

    env = dict(os.environ)
    for var, value in (("CORTEXLOC_HOST", host), ("CORTEXLOC_PORT", port), ("CORTEXLOC_DATA_DIR", data_dir)):
        if value is not None:
            env[var] = str(value)
    try:
        settings = Settings.from_env(env)  # read once, here; the app gets this object
    except ConfigError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from e
    # OpenCV reads its pixel guard once, when cv2 is imported (by the app's modules, below).
    os.environ["OPENCV_IO_MAX_IMAGE_PIXELS"] = str(settings.max_pixels)

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
    """Create a map from a snapshot tar, verifying every checksum (run while the server is stopped)."""
    import os
    from types import SimpleNamespace

    from service.runtime import MapRegistry
    from storage.snapshots import SnapshotInvalid

    root = data_dir or Path(os.environ.get("CORTEXLOC_DATA_DIR", "./var"))
    registry = MapRegistry(root, SimpleNamespace(identity="", feature_dim=0), settings=None)
    try:
        map_id = registry.import_snapshot(tar)
    except (SnapshotInvalid, ValueError, OSError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from e
    finally:
        registry.catalog.close()
    typer.echo(f"imported map {map_id!r} into {root}; it recovers from the snapshot when the server starts")


def main() -> None:  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
