"""`cortexloc bench tm | encoder`: speed and memory, as medians (run on demand; benchmarks/ keeps the
tables)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from models.frontend import backbones
from service.cli.common import check_backbone, check_presets, provenance, write_json

app = typer.Typer(no_args_is_help=True, help="Benchmarks (medians; run on demand).")


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

