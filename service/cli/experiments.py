"""`cortexloc eval <name>` for the searches and experiments whose run logic lives outside service/evaluation/:
the searches behind the presets (models/evaluation/sweeps/), the cross-season tables
(models/evaluation/nordland_tables.py), geometric verification (models/evaluation/geometry.py) and the
variants of benchmarks/experiments/ and benchmarks/bench_loops_http.py. `echo` and `null-entry` install
a variant for the process and then run another `cortexloc` command line given after it (`cortexloc eval
echo off eval slam --data D`), so the rest of that command's path is the service's.

Where a command goes is benchmarks/__init__.py's rule (docs/benchmarks.md): a table of docs/results.md
comes from `cortexloc eval <name>`, a speed or memory figure from `cortexloc bench <name>`. The commands
are registered on `service.cli.evaluate.app` beside grid, images, slam and the rest; each imports its run
logic only when it runs (so `--help` imports no torch or cv2) and hands it typed keyword arguments.
Comma-separated lists keep the form of the other `eval` options (`--methods`, `--ds`).
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from pathlib import Path
from typing import Annotated

import typer

from service.cli.common import check_backbone
from service.cli.evaluate import _json_object, app

__all__ = ["app"]

CACHE = "feature cache (default ~/.cache/cortexloc/features)"


def _cache(path: Path | None) -> Path:
    """The feature cache of the searches: `--cache`, else ~/.cache/cortexloc/features."""
    return path if path is not None else Path.home() / ".cache" / "cortexloc" / "features"


def _split(text: str, option: str, convert: type = str) -> list:
    """A comma-separated option as a list of `convert` values; a clear error names the option."""
    try:
        items = [convert(v.strip()) for v in text.split(",") if v.strip()]
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint=option) from e
    if not items:
        raise typer.BadParameter("must name at least one value", param_hint=option)
    return items


def _among(value: str, allowed: Collection[str], option: str) -> None:
    if value not in allowed:
        raise typer.BadParameter(f"must be one of {', '.join(sorted(allowed))}", param_hint=option)


@app.command("grid-sweep")
def eval_grid_sweep(
    seeds: Annotated[int, typer.Option(min=1, help="runs per configuration and data set")] = 3,
    grid: Annotated[str, typer.Option(help="main | followup")] = "main",
) -> None:
    """The grid-world search behind the `cortexloc-grid` preset (docs/results.md §3;
    models/evaluation/sweeps/sweep.py)."""
    from models.evaluation.sweeps import sweep

    _among(grid, sweep.GRIDS, "--grid")
    sweep.run(seeds=seeds, grid=grid)


@app.command("nordland-sweep")
def eval_nordland_sweep(
    split: Annotated[str, typer.Option(help="tune | test")] = "tune",
    cache: Annotated[Path | None, typer.Option(help=CACHE)] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the rows as JSON here")] = None,
    codes_only: Annotated[bool, typer.Option("--codes-only", help="only the code statistics per (s, "
                                             "adaptation): bits shared by the same place and by different "
                                             "places, and single-image sLSBH AUC")] = False,
    grid: Annotated[list[str] | None, typer.Option(metavar="KEY=V1,V2", help="replace GRID[KEY] by these "
                                                   "values (repeat; re-run single rows)")] = None,
) -> None:
    """The cross-season search behind the `cortexloc-default` preset (docs/results.md §7.6;
    models/evaluation/sweeps/nordland_sweep.py)."""
    from models.evaluation.sweeps import nordland_sweep

    _among(split, nordland_sweep.SPLITS, "--split")
    try:
        nordland_sweep.run(split=split, cache=_cache(cache), json_out=json_out, codes_only=codes_only,
                           grid=grid or [])
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--grid") from e


@app.command("localiser-sweep")
def eval_localiser_sweep(
    what: Annotated[str, typer.Argument(help="grid (the localiser's options) | layers (the backbone block)")],
    split: Annotated[str, typer.Option(help="tune | test")] = "tune",
    grid: Annotated[list[str] | None, typer.Option(metavar="OPTION=V1,V2", help="values of a localiser "
                                                   "option (repeat; numbers; move_costs as 3/0/3)")] = None,
    blocks: Annotated[str | None, typer.Option(help="comma-separated blocks (default: all)")] = None,
    cache: Annotated[Path | None, typer.Option(help=CACHE)] = None,
) -> None:
    """The searches behind the localiser's defaults and the backbone block (docs/results.md §8.3, §8.4;
    models/evaluation/sweeps/localiser_sweep.py)."""
    from models.evaluation.sweeps import localiser_sweep

    _among(what, ("grid", "layers"), "WHAT")
    _among(split, localiser_sweep.SPLITS, "--split")
    chosen = _split(blocks, "--blocks") if blocks is not None else list(localiser_sweep.BLOCKS)
    localiser_sweep.run(what=what, split=split, grid=grid or [], blocks=chosen, cache=_cache(cache))


@app.command("projection-parity")
def eval_projection_parity(
    windows: Annotated[str, typer.Option(help="comma-separated start indices of the windows")] = "0,1000",
    n: Annotated[int, typer.Option(min=1, help="frames per window")] = 200,
    seeds: Annotated[int, typer.Option(min=1)] = 3,
    resize: Annotated[str, typer.Option(help="crop | squash (64x32 frames: squash keeps the view)")]
    = "squash",
    backbone: Annotated[str, typer.Option(help="a backbone registered in models.frontend.backbones")]
    = "alexnet",
    json_out: Annotated[Path | None, typer.Option("--json", help="write the rows as JSON here")] = None,
) -> None:
    """Dense against very sparse sLSBH projection, pairwise AUC (docs/results.md §4;
    models/evaluation/sweeps/projection_parity.py)."""
    from models.evaluation.sweeps import projection_parity

    check_backbone(backbone)
    projection_parity.run(windows=_split(windows, "--windows", int), n=n, seeds=seeds, resize=resize,
                          backbone=backbone, json_out=json_out)


@app.command("nordland-tables")
def eval_nordland_tables(
    backbone: Annotated[str, typer.Option(help="a backbone registered in models.frontend.backbones")]
    = "efficientnet-lite0",
    seeds: Annotated[int, typer.Option(min=1)] = 3,
    ds: Annotated[str, typer.Option(help="comma-separated path lengths")] = "10,20",
    methods: Annotated[str | None, typer.Option(help="comma-separated methods of "
                                                "models.evaluation.sequences.METHODS, e.g. "
                                                "openseqslam,online-htm (its ablations join; default: the "
                                                "tables')")] = None,
    windows: Annotated[str | None, typer.Option(help="comma-separated names of WINDOWS (default: all)")]
    = None,
    reverse_query: Annotated[bool, typer.Option("--reverse-query", help="drive the query route backwards")]
    = False,
    crossing: Annotated[bool, typer.Option("--crossing", help="sequence methods answer the row where the "
                                           "best path crosses the query, not OpenSeqSLAM's start row + "
                                           "ds/2")] = False,
    cache: Annotated[Path | None, typer.Option(help=CACHE)] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="write the result as JSON here")] = None,
    markdown: Annotated[Path | None, typer.Option(help="print the tables of a --json result, run nothing",
                                                  exists=True, dir_okay=False)] = None,
) -> None:
    """The cross-season tables of docs/results.md §7 (models/evaluation/nordland_tables.py)."""
    from models.evaluation import nordland_tables, sequences

    check_backbone(backbone)
    method_list = _split(methods, "--methods") if methods is not None else list(nordland_tables.METHODS)
    bad = set(method_list) - set(sequences.METHODS)
    if bad:
        raise typer.BadParameter(f"unknown: {', '.join(sorted(bad))}", param_hint="--methods")
    window_list = _split(windows, "--windows") if windows is not None else list(nordland_tables.WINDOWS)
    for w in window_list:
        _among(w, nordland_tables.WINDOWS, "--windows")
    nordland_tables.run(backbone=backbone, seeds=seeds, ds=_split(ds, "--ds", int), methods=method_list,
                        windows=window_list, reverse_query=reverse_query, crossing=crossing,
                        cache=_cache(cache), json_out=json_out, markdown_of=markdown)


@app.command("geometry")
def eval_geometry(
    extractors: Annotated[str | None, typer.Option(help="comma-separated, e.g. orb,sift (default: those "
                                                   "available)")] = None,
    max_features: Annotated[int, typer.Option("--max", min=1, help="features per frame")] = 500,
    as_json: Annotated[bool, typer.Option("--json", help="print the rows as JSON too")] = False,
) -> None:
    """Geometric verification measured on real images (docs/results.md §12; models/evaluation/geometry.py)."""
    from models.evaluation import geometry

    geometry.run(extractors=_split(extractors, "--extractors") if extractors is not None else None,
                 max_features=max_features, as_json=as_json)


@app.command("slam-seasons")
def eval_slam_seasons(
    kind: Annotated[str, typer.Argument(help="own | contrast | hub | idf | local")],
    value: Annotated[float, typer.Argument(help="the variant's X, W, T or M")],
    beta: Annotated[float, typer.Argument(help="hub, idf, local: the discount")] = 2.0,
    half: Annotated[str, typer.Option(help="tune | test")] = "test",
    routes: Annotated[str, typer.Option(help="the `eval slam` routes")] = "seasons",
    methods: Annotated[str, typer.Option(help="the `eval slam` methods")] = "service-slam,service",
    data: Annotated[Path, typer.Option(help="the Nordland folder")]
    = Path("../shared/data/nordland_tiny_64x32"),
    json_out: Annotated[Path | None, typer.Option("--json", help="write the result as JSON here")] = None,
) -> None:
    """The localiser's evidence against the season bias, a variant per run (docs/results.md §10.6, §10.7;
    benchmarks/experiments/slam_seasons.py)."""
    from benchmarks.experiments import slam_seasons

    _among(kind, ("own", "contrast", "hub", "idf", "local"), "KIND")
    slam_seasons.main(kind=kind, value=value, beta=beta, half=half, routes=routes, methods=methods, data=data,
                      json_out=json_out)


@app.command("loops-http")
def eval_loops_http(
    data: Annotated[Path | None, typer.Option(help="the Nordland folder (default: the shared data's)")]
    = None,
    routes: Annotated[str, typer.Option(help="comma-separated: outdoor, corridor, slow, robots, dropped, "
                                        "station, faster, slower")]
    = "outdoor,corridor,slow,robots,dropped,station,faster,slower",
    seeds: Annotated[str, typer.Option(help="comma-separated map seeds; `default`: a map created with no "
                                       "seed option (a new map's)")] = "default,1,7",
    concurrency: Annotated[int, typer.Option(min=1, help="maps driven at once")] = 6,
    quick: Annotated[bool, typer.Option("--quick", help="tiny routes (also CORTEXLOC_BENCH_QUICK=1)")]
    = False,
    keep: Annotated[bool, typer.Option("--keep", help="keep the temporary data directory")] = False,
    poses: Annotated[bool, typer.Option("--poses", help="post each frame's stamp and pose as metadata (the "
                                        "corridor's true ones; outdoors the file index x 280 m on a line, "
                                        "assumed)")] = False,
    localiser: Annotated[str | None, typer.Option(help="the maps' localiser options as JSON, over the "
                                                  "defaults (an ablation), e.g. '{\"span_max\": 4096}'")]
    = None,
    drift: Annotated[str | None, typer.Option(help="with --poses: odometry, not the true poses: S,H = each "
                                             "step scaled by 1 + N(0, S), the heading walking N(0, H "
                                             "degrees) a step, e.g. 0.03,0.3")] = None,
    out: Annotated[Path | None, typer.Option(help="default benchmarks/results/loops_http.json")] = None,
) -> None:
    """Loop closure checked from outside: one robot mapping while it drives, through a real server
    (docs/results.md §10.15; benchmarks/bench_loops_http.py)."""
    from benchmarks import bench_loops_http

    route_list = _split(routes, "--routes")
    for r in route_list:
        _among(r, bench_loops_http.ROUTES, "--routes")
    drifts = None
    if drift is not None:
        try:
            scale_sd, heading_deg = (float(v) for v in drift.split(","))
        except ValueError as e:
            raise typer.BadParameter("expected S,H: two numbers", param_hint="--drift") from e
        if not poses or scale_sd < 0 or heading_deg < 0:
            raise typer.BadParameter("two numbers >= 0, with --poses", param_hint="--drift")
        drifts = (scale_sd, heading_deg)
    bench_loops_http.main(data=data, routes=route_list, seeds=_split(seeds, "--seeds"),
                          concurrency=concurrency, quick=quick, keep=keep, poses=poses,
                          localiser=_json_object(localiser or "", "--localiser"), out=out, drift=drifts)


PASS_ON = {"allow_extra_args": True, "ignore_unknown_options": True}
COMMAND = "the `cortexloc` command line to run with the variant, e.g. eval slam --data D --half tune"


def _runner(ctx: typer.Context) -> Callable[[list[str]], object]:
    """Run another `cortexloc` command line in this process (the variant installed stays in force)."""
    root = ctx.find_root().command
    return lambda argv: root.main(args=list(argv), prog_name="cortexloc", standalone_mode=False)


@app.command("echo", context_settings=PASS_ON)
def eval_echo(
    ctx: typer.Context,
    variant: Annotated[str, typer.Argument(help="adopted | off | kill | absolute | between | codes:N")],
    command: Annotated[list[str], typer.Argument(help=COMMAND + "; or `synthetic`")],
) -> None:
    """The echo and what was tried against it: a variant of the own-trail rule for one run of another
    command (docs/results.md §10.9; benchmarks/experiments/echo.py)."""
    from benchmarks.experiments import echo

    echo.main(variant=variant, command=command, run_command=_runner(ctx))


@app.command("null-entry", context_settings=PASS_ON)
def eval_null_entry(
    ctx: typer.Context,
    variant: Annotated[str, typer.Argument(help="adopted | rows | entry:K | first | level")],
    command: Annotated[list[str], typer.Argument(help=COMMAND)],
) -> None:
    """Where the localiser's new rows start (the jump level) for one run of another command
    (docs/results.md §10.8; benchmarks/experiments/null_entry.py)."""
    from benchmarks.experiments import null_entry

    null_entry.main(variant=variant, command=command, run_command=_runner(ctx))


@app.command("short-term")
def eval_short_term(
    routes: Annotated[str, typer.Argument(help="comma-separated routes (slow3, flat, shortloop, ...)")],
    seeds: Annotated[str, typer.Argument(help="comma-separated map seeds")],
    starts: Annotated[str, typer.Argument(help="comma-separated first files of the windows")] = "100",
    localiser: Annotated[str, typer.Argument(help="the maps' localiser options as JSON")] = "",
) -> None:
    """A stream's short-term memory on the stress routes, one JSON line per route, window and seed
    (docs/results.md §10.11; benchmarks/experiments/short_term.py)."""
    from benchmarks.experiments import short_term

    short_term.main(routes=_split(routes, "ROUTES"), seeds=_split(seeds, "SEEDS", int),
                    starts=_split(starts, "STARTS", int), localiser=_json_object(localiser, "LOCALISER"))


@app.command("short-term-poses")
def eval_short_term_poses(
    metres: Annotated[float, typer.Argument(help="metres per label (a frame's pose: its label x this)")],
    seconds: Annotated[float, typer.Argument(help="seconds per frame (a frame's stamp: its index x this)")],
    localiser: Annotated[str, typer.Argument(help="the maps' localiser options as JSON")],
    cases: Annotated[list[str], typer.Argument(help="stress cases (rate3, parked, flat, ...)")],
) -> None:
    """The stress routes given poses, one learning stream through the service's step (docs/results.md
    §10.11 "With poses"; benchmarks/experiments/short_term_poses.py)."""
    from benchmarks.experiments import short_term_poses

    short_term_poses.main(metres=metres, seconds=seconds,
                          localiser=_json_object(localiser, "LOCALISER") or {}, cases=cases)


@app.command("span")
def eval_span(
    kinds: Annotated[str, typer.Argument(help="comma-separated lap-2 kinds (winter, flat); `sum`: total the "
                                         "JSON lines read from stdin")],
    seeds: Annotated[str | None, typer.Argument(help="comma-separated map seeds")] = None,
    localiser: Annotated[str, typer.Argument(help="the maps' localiser options as JSON")] = "",
) -> None:
    """The span in the localise mode at several margins and caps, one JSON line per window and seed
    (docs/results.md §10.13; benchmarks/experiments/span.py)."""
    import json
    import sys

    from benchmarks.experiments import span

    if kinds == "sum":
        span.total([json.loads(line) for line in sys.stdin if line.strip()])
        return
    if seeds is None:
        raise typer.BadParameter("give the map seeds", param_hint="SEEDS")
    span.main(kinds=_split(kinds, "KINDS"), seeds=_split(seeds, "SEEDS", int),
              localiser=_json_object(localiser, "LOCALISER"))


@app.command("parked")
def eval_parked(
    seeds: Annotated[str, typer.Argument(help="comma-separated map seeds; `sum`: total the JSON lines read "
                                         "from stdin")],
) -> None:
    """A robot that parks, on new ground beside a map of other ground and on known ground, with poses and
    without, the standing-view rule on and off: revisits before, during and after the stop, one JSON
    line per window and seed (docs/results.md §10.24; benchmarks/experiments/parked.py)."""
    import json
    import sys

    from benchmarks.experiments import parked

    if seeds == "sum":
        parked.total([json.loads(line) for line in sys.stdin if line.strip()])
        return
    parked.main(seeds=_split(seeds, "SEEDS", int))


@app.command("join-level")
def eval_join_level(
    seeds: Annotated[str, typer.Argument(help="comma-separated map seeds; `sum`: total the JSON lines read "
                                         "from stdin")],
) -> None:
    """How alike a frame is to its own place's row seen otherwise and to the rows a wrong warm-up join
    would take, on `consolidate`'s scale, one JSON line per window and seed (docs/results.md §11;
    benchmarks/experiments/join_level.py)."""
    import json
    import sys

    from benchmarks.experiments import join_level

    if seeds == "sum":
        join_level.total([json.loads(line) for line in sys.stdin if line.strip()])
        return
    join_level.main(seeds=_split(seeds, "SEEDS", int))
