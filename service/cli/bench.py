"""`cortexloc bench <name>`: speed and memory measurements, as medians (docs/benchmarks.md).

The design of record for where an experiment or a measurement lives is benchmarks/__init__.py's
docstring (and docs/benchmarks.md's opening): a table of docs/results.md comes from `cortexloc eval
<name>` (service/cli/evaluate.py, service/cli/experiments.py), a speed or memory figure from
`cortexloc bench <name>` (here). `tm` and `encoder` measure one configuration given by their options;
every other command runs the benchmark of `benchmarks/<module>.py` named in its help, whose `main(...)`
takes these options as keyword arguments. Each command imports its benchmark only when it runs, so
`--help` imports no torch or cv2. JSON results go under benchmarks/results/ unless `--out` says otherwise;
`--quick` (or CORTEXLOC_BENCH_QUICK=1) shrinks a run to a smoke test. `cortexloc bench all` runs them
all, each in its own process (`make bench`, `make bench-quick`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from models.frontend import backbones
from service.cli.common import check_backbone, check_presets, provenance, write_json

app = typer.Typer(no_args_is_help=True, help="Speed and memory measurements (medians; run on demand).")

QUICK = "smoke run (also CORTEXLOC_BENCH_QUICK=1)"
SERVER_CMD = "command that starts the CLI instead of `cortexloc` (e.g. another build); `serve ...` follows"


@app.command("tm")
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

    check_presets(preset)
    if active > columns:
        raise typer.BadParameter("--active must not exceed --columns")
    overrides = {k: v for k, v in (("maxSegmentsPerCell", max_segments),
                                   ("maxSynapsesPerSegment", max_synapses)) if v is not None}
    result = run(columns=columns, cells=cells, active=active, steps=steps, preset=preset, period=period,
                 overrides=overrides)
    result["provenance"] = provenance()
    write_json(json_out, result)
    typer.echo(f"TM {columns}x{cells}, {active} active, {steps} steps ({preset}): "
               f"median {result['ms_per_step_median']:.3f} ms/step, p90 {result['ms_per_step_p90']:.3f}, "
               f"RSS growth {result['rss_growth_mb']:.1f} MB, segments {result['segments']}, "
               f"synapses {result['synapses']}, bytes {result['bytes']}")


@app.command("encoder")
def bench_encoder(
    backbone: Annotated[str, typer.Option(help="a backbone registered in models.frontend.backbones")]
    = backbones.PAPER,
    repeats: Annotated[int, typer.Option(min=1)] = 15,
    threads: Annotated[int, typer.Option(min=1, help="the backbone's threads")] = 1,
    projection: Annotated[str, typer.Option(help="dense | sparse")] = "dense",
    runtime: Annotated[str | None, typer.Option(help="onnxruntime | torch (default: the encoder's)")] = None,
    json_out: Annotated[Path | None, typer.Option("--json")] = None,
) -> None:
    """Whole-encoder batch-1 latency and batch-16 throughput beside a bare backbone forward."""
    from models.evaluation.bench import bench_encoder as run
    from models.frontend.runtimes import RUNTIMES

    check_backbone(backbone)
    if projection not in ("dense", "sparse"):
        raise typer.BadParameter("must be dense or sparse", param_hint="--projection")
    if runtime is not None and runtime not in RUNTIMES:
        raise typer.BadParameter(f"must be one of {', '.join(RUNTIMES)}", param_hint="--runtime")
    result = run(backbone=backbone, repeats=repeats, threads=threads, projection=projection, runtime=runtime)
    result["provenance"] = provenance()
    write_json(json_out, result)
    st = result["batch16_stage_ms_median"]
    typer.echo(f"encoder {result['encoder']}: D = {result['feature_dim']:,} features, k = {result['k']:,}, "
               f"dense projection {result['dense_projection_bytes'] / 2**20:.1f} MiB")
    typer.echo(f"encoder {result['encoder']} on {result['runtime']} ({result['device']}, {projection} "
               f"projection, {threads} thread(s)): batch 1 "
               f"{result['batch1_ms_median']:.1f} ms; batch 16 {result['batch16_images_per_s']:.1f} img/s "
               f"vs bare backbone {result['bare_batch16_images_per_s']:.1f} img/s "
               f"(ratio {result['ratio_to_bare']:.2f}); stages at batch 16 (ms): "
               + ", ".join(f"{k} {v:.1f}" for k, v in st.items()))



@app.command("all")
def bench_all(
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
    only: Annotated[list[str] | None, typer.Option(help="a benchmark to run (repeat; default: all)")] = None,
) -> None:
    """Every benchmark below, each in its own process (benchmarks/run_all.py; `make bench`)."""
    from benchmarks.run_all import main

    main(quick=quick, only=only or [])


@app.command("tm-suite")
def bench_tm_suite(
    steps: Annotated[int, typer.Option(min=1)] = 5000,
    preset: Annotated[str, typer.Option(help="TM preset of the first two configurations")] = "cortexloc-grid",
    out: Annotated[Path | None, typer.Option(help="default benchmarks/results/tm.json")] = None,
) -> None:
    """The Temporal Memory's three configurations of docs/benchmarks.md (benchmarks/bench_tm.py)."""
    from benchmarks.bench_tm import main

    check_presets(preset)
    main(steps=steps, preset=preset, out=out)


@app.command("encoder-suite")
def bench_encoder_suite(
    repeats: Annotated[int, typer.Option(min=1)] = 15,
    out: Annotated[Path | None, typer.Option(help="default benchmarks/results/encoder.json")] = None,
) -> None:
    """The encoder's three configurations against issue 24's targets (benchmarks/bench_encoder.py)."""
    from benchmarks.bench_encoder import main

    main(repeats=repeats, out=out)


@app.command("runtimes")
def bench_runtimes(
    threads: Annotated[int, typer.Option(min=1, help="intra-op threads of every runtime")] = 1,
    repeats: Annotated[int, typer.Option(min=1)] = 7,
    backbones: Annotated[list[str] | None, typer.Option(help="a backbone (repeat; default: all)")] = None,
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
) -> None:
    """Backbone runtimes side by side: torch against its ONNX export (benchmarks/bench_runtimes.py)."""
    from benchmarks.bench_runtimes import main

    main(threads=threads, repeats=repeats, backbones=backbones, quick=quick)


@app.command("tm-peer")
def bench_tm_peer(
    steps: Annotated[int, typer.Option(min=1)] = 5000,
    rounds: Annotated[int, typer.Option(min=1)] = 3,
    before: Annotated[list[str] | None, typer.Option(help="also time this commit's memory (repeat)")] = None,
    peer_python: Annotated[Path | None, typer.Option(help="default .venv-peer/bin/python")] = None,
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
    out: Annotated[Path | None, typer.Option(help="default benchmarks/results/tm_peer.json")] = None,
) -> None:
    """The Temporal Memory against BrainBlocks 0.7.1, like for like (benchmarks/bench_tm_peer.py)."""
    from benchmarks.bench_tm_peer import main

    main(steps=steps, rounds=rounds, before=before or [], peer_python=peer_python, quick=quick, out=out)


@app.command("tm-profile")
def bench_tm_profile(
    warm: Annotated[int, typer.Option(min=1)] = 300,
    steps: Annotated[int, typer.Option(min=1)] = 30,
    repeats: Annotated[int, typer.Option(min=1)] = 3,
    before: Annotated[list[str] | None, typer.Option(help="also time this commit's kernels (repeat)")] = None,
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
) -> None:
    """Where the service preset's learning step goes, by ablation (benchmarks/bench_tm_profile.py)."""
    from benchmarks.bench_tm_profile import main

    main(warm=warm, steps=steps, repeats=repeats, before=before or [], quick=quick)


@app.command("index")
def bench_index(
    sizes: Annotated[list[int] | None, typer.Option(help="descriptors (repeat; default 10^3 10^5 "
                                                         "10^6)")] = None,
    queries: Annotated[int | None, typer.Option(min=1, help="queries per size (default 50; quick "
                                                            "10)")] = None,
    keep: Annotated[int, typer.Option(min=0, help="cells of the stored descriptor kept in a query")] = 30,
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
    out: Annotated[Path | None, typer.Option(help="default benchmarks/results/index.json")] = None,
) -> None:
    """Retrieval as a map grows: the inverted index against a popcount scan (benchmarks/bench_index.py)."""
    from benchmarks.bench_index import main

    main(sizes=sizes, queries=queries, keep=keep, quick=quick, out=out)


@app.command("localiser")
def bench_localiser(
    sizes: Annotated[list[int], typer.Option(help="map sizes "
                                                  "(repeat)")] = [1_000, 100_000, 1_000_000],  # noqa: B006
    frames: Annotated[int, typer.Option(min=1)] = 400,
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
) -> None:
    """The online localiser's step as the map grows: cost and state size (benchmarks/bench_localiser.py)."""
    from benchmarks.bench_localiser import main

    main(sizes=sizes, frames=frames, quick=quick)


@app.command("place")
def bench_place(
    sizes: Annotated[list[int] | None, typer.Option(help="map sizes (repeat; default 10^3 10^5 "
                                                         "10^6)")] = None,
    frames: Annotated[int | None, typer.Option(min=1, help="frames per size (default 300; quick 40)")] = None,
    keep: Annotated[int, typer.Option(min=0, help="cells of the stored row kept in a frame")] = 30,
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
) -> None:
    """The per-frame `place` as the map grows: index pass plus localiser step (benchmarks/bench_place.py)."""
    from benchmarks.bench_place import main

    main(sizes=sizes, frames=frames, keep=keep, quick=quick)


@app.command("http")
def bench_http(
    clients: Annotated[list[int], typer.Option(help="client counts (repeat)")] = [1, 4, 16],  # noqa: B006
    requests: Annotated[int | None, typer.Option(min=1, help="replies per client count (default "
                                                             "160)")] = None,
    max_seconds: Annotated[float, typer.Option(help="wall-clock cap per client count")] = 120.0,
    repeats: Annotated[int | None, typer.Option(min=1, help="encoder-alone repeats (default 15)")] = None,
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
    keep: Annotated[bool, typer.Option("--keep", help="keep the temporary data directory")] = False,
    server_cmd: Annotated[str | None, typer.Option(help=SERVER_CMD)] = None,
    out: Annotated[Path | None, typer.Option(help="default benchmarks/results/http.json")] = None,
) -> None:
    """End to end over HTTP on loopback: images/s and latency by client count (benchmarks/bench_http.py)."""
    from benchmarks.bench_http import main

    main(clients=clients, requests=requests, max_seconds=max_seconds, repeats=repeats, quick=quick, keep=keep,
         server_cmd=server_cmd, out=out)


@app.command("scaleout")
def bench_scaleout(
    requests: Annotated[int, typer.Option(min=1, help="sequential requests per path (each kind)")] = 60,
    clients: Annotated[int, typer.Option(min=1)] = 8,
    rounds: Annotated[int, typer.Option(min=1)] = 3,
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
) -> None:
    """The Ray Serve scale-out's per-request cost against one process (benchmarks/bench_scaleout.py)."""
    from benchmarks.bench_scaleout import main

    main(requests=requests, clients=clients, rounds=rounds, quick=quick)


@app.command("hostile")
def bench_hostile(
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
    repeats: Annotated[int | None, typer.Option(min=1, help="posts per hostile image (default 3)")] = None,
    server_cmd: Annotated[str | None, typer.Option(help=SERVER_CMD)] = None,
    skip: Annotated[list[str] | None, typer.Option(help="a hostile image to leave out (repeat)")] = None,
    frames_during: Annotated[int | None, typer.Option(min=1, help="normal frames timed while bombs are "
                                                               "posted (default 10)")] = None,
    out: Annotated[Path | None, typer.Option(help="default benchmarks/results/hostile.json")] = None,
) -> None:
    """Hostile inputs against the real service: how fast bombs are refused, what a frame waits beside
    them and beside repair listings (benchmarks/bench_hostile.py)."""
    from benchmarks.bench_hostile import main

    main(quick=quick, repeats=repeats, server_cmd=server_cmd, skip=skip or [], frames_during=frames_during,
         out=out)


@app.command("startup")
def bench_startup(
    observations: Annotated[int | None, typer.Option(min=1, help="map size (default 100,000; quick 2,000)")]
    = None,
    short_tail: Annotated[int | None, typer.Option(min=0, help="replay after the newest snapshot "
                                                               "(100)")] = None,
    long_tail: Annotated[int | None, typer.Option(min=0, help="replay after the older snapshot "
                                                              "(10,000)")] = None,
    full_replay: Annotated[bool, typer.Option("--full-replay", help="also open with no snapshot at "
                                                                    "all")] = False,
    data_dir: Annotated[Path | None, typer.Option(help="reuse (or build once into) this directory instead of "
                                                       "a temporary one")] = None,
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
    out: Annotated[Path | None, typer.Option(help="default benchmarks/results/startup.json")] = None,
) -> None:
    """Start-up of a map of 10^5 observations: snapshot load, replay, index (benchmarks/bench_startup.py)."""
    from benchmarks.bench_startup import main

    main(observations=observations, short_tail=short_tail, long_tail=long_tail, full_replay=full_replay,
         data_dir=data_dir, quick=quick, out=out)


@app.command("forgetting")
def bench_forgetting(
    novel: Annotated[int, typer.Option(min=1, help="novel steps learned after the first route")] = 3000,
    every: Annotated[int, typer.Option(min=1, help="measure recall every this many steps")] = 300,
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
) -> None:
    """Forgetting shown: a first route's recall against novel input learned after it
    (benchmarks/bench_forgetting.py)."""
    from benchmarks.bench_forgetting import main

    main(novel=novel, every=every, quick=quick)


@app.command("longrun")
def bench_longrun(
    steps: Annotated[int | None, typer.Option(min=1, help="total TM steps (default 1,000,000; quick 20,000)")]
    = None,
    checkpoints: Annotated[int, typer.Option(min=1, help="RSS/recall measurements (every steps/N)")] = 10,
    preset: Annotated[str, typer.Option(help="TM preset")] = "cortexloc-default",
    places: Annotated[int, typer.Option(min=1, help="places per route")] = 100,
    laps: Annotated[int, typer.Option(min=1, help="learning laps of the early loop")] = 3,
    noise: Annotated[float, typer.Option(min=0.0, max=1.0, help="fraction of columns replaced per "
                                                                "visit")] = 0.1,
    novel: Annotated[str, typer.Option(help="routes | random")] = "routes",
    seed: Annotated[int, typer.Option()] = 0,
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
    out: Annotated[Path | None, typer.Option(help="default benchmarks/results/longrun.json")] = None,
) -> None:
    """10^6 Temporal Memory steps: RSS, caps and the forgetting curve (benchmarks/bench_longrun.py)."""
    from benchmarks.bench_longrun import main

    check_presets(preset)
    if novel not in ("routes", "random"):
        raise typer.BadParameter("must be routes or random", param_hint="--novel")
    main(steps=steps, checkpoints=checkpoints, preset=preset, places=places, laps=laps, noise=noise,
         novel=novel, seed=seed, quick=quick, out=out)


@app.command("gpu")
def bench_gpu(
    repeats: Annotated[int, typer.Option(min=1)] = 20,
    cpu_threads: Annotated[list[int] | None, typer.Option(help="CPU threads to compare (repeat; default 2 "
                                                                 "and all cores)")] = None,
    backbones: Annotated[list[str] | None, typer.Option(help="a backbone (repeat; default: all)")] = None,
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
) -> None:
    """The backbone's forward on a GPU beside the CPU; stops where there is none (benchmarks/bench_gpu.py)."""
    from benchmarks.bench_gpu import main

    main(repeats=repeats, cpu_threads=cpu_threads, backbones=backbones, quick=quick)


@app.command("ingest")
def bench_ingest(
    frames: Annotated[int, typer.Option(min=1)] = 50,
    repeats: Annotated[int, typer.Option(min=1)] = 3,
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
) -> None:
    """`cortexloc ingest`: frames/s and latency in process against HTTP (benchmarks/bench_ingest.py)."""
    from benchmarks.bench_ingest import main

    main(frames=frames, repeats=repeats, quick=quick)


@app.command("keyframes")
def bench_keyframes(
    out: Annotated[Path | None, typer.Option(help="JSON out (default: benchmarks/results/keyframes.json)")]
    = None,
) -> None:
    """Keyframe extraction of large frames: wall time and peak RSS growth (benchmarks/bench_keyframes.py)."""
    from benchmarks.bench_keyframes import main

    main(out=out)


@app.command("memory")
def bench_memory(
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
    budget: Annotated[int | None, typer.Option(min=1, help="CORTEXLOC_MEMORY_BUDGET_BYTES (default: unset)")]
    = None,
    big: Annotated[int, typer.Option(min=1, help="big maps to try")] = 3,
    many: Annotated[int, typer.Option(min=1, help="default maps to try")] = 63,
    restart_budget: Annotated[int | None, typer.Option(min=1, help="CORTEXLOC_MEMORY_BUDGET_BYTES at the "
                                                               "restart (default: as --budget)")] = None,
    server_cmd: Annotated[str | None, typer.Option(help=SERVER_CMD)] = None,
    out: Annotated[str, typer.Option(help="name of the JSON under benchmarks/results/ (.json added)")]
    = "memory",
) -> None:
    """The process-wide memory budget against the real service (benchmarks/bench_memory.py)."""
    from benchmarks.bench_memory import main

    main(quick=quick, budget=budget, big=big, many=many, restart_budget=restart_budget, server_cmd=server_cmd,
         out=out)


@app.command("snapshot")
def bench_snapshot(
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
    rows: Annotated[str, typer.Option(help="comma-separated store sizes")] = "0,20000,60000",
    repeats: Annotated[int, typer.Option(min=1)] = 3,
) -> None:
    """What a snapshot costs, by step, as a map's store grows (benchmarks/bench_snapshot.py)."""
    from benchmarks.bench_snapshot import main

    main(quick=quick, rows=rows, repeats=repeats)


@app.command("uploads")
def bench_uploads(
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
    server_cmd: Annotated[str | None, typer.Option(help=SERVER_CMD)] = None,
    env: Annotated[list[str] | None, typer.Option(help="NAME=VALUE for the server (repeat)")] = None,
    uploads: Annotated[int, typer.Option(min=1)] = 50,
    declared: Annotated[int, typer.Option(min=1)] = 10_000_000,
    sent: Annotated[int, typer.Option(min=0)] = 9_000_000,
    watch: Annotated[float | None, typer.Option(help="seconds to wait before the last look")] = None,
    out: Annotated[Path | None, typer.Option(help="default benchmarks/results/uploads.json")] = None,
) -> None:
    """Half-sent uploads against the real service: what they hold, how long (benchmarks/bench_uploads.py)."""
    from benchmarks.bench_uploads import main

    main(quick=quick, server_cmd=server_cmd, env=env or [], uploads=uploads, declared=declared, sent=sent,
         watch=watch, out=out)


@app.command("fairness")
def bench_fairness(
    quick: Annotated[bool, typer.Option("--quick", help=QUICK)] = False,
    server_cmd: Annotated[str | None, typer.Option(help=SERVER_CMD)] = None,
    env: Annotated[list[str] | None, typer.Option(help="NAME=VALUE for the server (repeat)")] = None,
    frames: Annotated[int, typer.Option(min=1, help="the robot's frames per phase")] = 20,
    gap: Annotated[float, typer.Option(min=0.0, help="seconds between the robot's frames")] = 0.25,
    clients: Annotated[int, typer.Option(min=1, help="the flood's connections")] = 40,
    side: Annotated[int, typer.Option(min=16, help="the flood's PNG side in pixels")] = 5000,
    noise: Annotated[bool, typer.Option("--noise", help="the flood's PNG of noise (side² x 3 bytes) "
                                                        "instead of a pattern")] = False,
    keyframes: Annotated[str | None, typer.Option(help="both maps take local features (orb or sift), so the "
                                                       "flood fills the keyframe extractions too")] = None,
    out: Annotated[Path | None, typer.Option(help="default benchmarks/results/fairness.json")] = None,
) -> None:
    """One map's flood against another map's robot: does the robot wait (benchmarks/bench_fairness.py)."""
    from benchmarks.bench_fairness import main

    if keyframes not in (None, "orb", "sift"):
        raise typer.BadParameter("orb or sift", param_hint="--keyframes")
    main(quick=quick, server_cmd=server_cmd, env=env or [], frames=frames, gap=gap, clients=clients,
         side=side, noise=noise, keyframes=keyframes, out=out)


@app.command("profile-encoder")
def bench_profile_encoder(
    repeats: Annotated[int, typer.Option(min=1)] = 9,
    backbone: Annotated[str, typer.Option(help="a backbone registered in models.frontend.backbones")]
    = "efficientnet-lite0-s5",
    out: Annotated[Path | None, typer.Option(help="default benchmarks/results/profile_encoder.json")] = None,
) -> None:
    """The encoder's stages one by one, and its ratio to the bare forward (benchmarks/profile_encoder.py)."""
    from benchmarks.profile_encoder import main

    check_backbone(backbone)
    main(repeats=repeats, backbone=backbone, out=out)


@app.command("profile-service")
def bench_profile_service(
    clients: Annotated[int, typer.Option(min=1)] = 16,
    seconds: Annotated[float, typer.Option(min=0.0)] = 30.0,
    server_cmd: Annotated[str | None, typer.Option(help=SERVER_CMD)] = None,
    out: Annotated[Path | None, typer.Option(help="default benchmarks/results/profile.json")] = None,
) -> None:
    """Where the service's CPU goes per image, 16 loopback clients (benchmarks/profile_service.py)."""
    from benchmarks.profile_service import main

    main(clients=clients, seconds=seconds, server_cmd=server_cmd, out=out)


@app.command("growth")
def bench_growth(
    passes: Annotated[int, typer.Option(min=1)] = 10,
    lo: Annotated[int, typer.Option(min=0, help="first file of the route (test half: 894-1787)")] = 894,
    frames: Annotated[int, typer.Option(min=1)] = 400,
    seed: Annotated[int, typer.Option(help="the map's seed (42: a new map's)")] = 42,
    quick: Annotated[bool, typer.Option("--quick", help="3 passes of 100 frames (a smoke run)")] = False,
    http: Annotated[bool, typer.Option("--http", help="through HTTP: the service at its defaults")] = False,
    anywhere: Annotated[bool, typer.Option("--anywhere", help="passes after the first start part-way along "
                                           "the route")] = False,
    routes: Annotated[str, typer.Option(help="comma-separated: exact, noise8, winter (every pass after the "
                                        "first in winter)")] = "exact,noise8",
    localiser: Annotated[str | None, typer.Option(help="the map's localiser options as JSON, over the "
                                                  "defaults (an ablation), e.g. '{\"unsure_fraction\": 0}'")]
    = None,
) -> None:
    """A map's growth pass after pass over one held-out route while it learns (docs/results.md §11;
    benchmarks/bench_growth.py)."""
    from benchmarks.bench_growth import ROUTES, main
    from service.cli.evaluate import _json_object

    chosen = tuple(r.strip() for r in routes.split(",") if r.strip())
    unknown = sorted(set(chosen) - set(ROUTES))
    if unknown or not chosen:
        raise typer.BadParameter(f"unknown route(s) {', '.join(unknown) or '(none given)'}; "
                                 f"choose among {', '.join(ROUTES)}", param_hint="--routes")

    main(passes=passes, lo=lo, frames=frames, seed=seed, quick=quick, http=http, anywhere=anywhere,
         routes=chosen, localiser=_json_object(localiser or "", "--localiser"))
