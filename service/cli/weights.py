"""`cortexloc weights download | import | export`: install AlexNet conv1..conv3 weights, checksummed, and
build the backbones' ONNX exports from the installed weights (docs/design/science.md §6.1)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

app = typer.Typer(no_args_is_help=True, help="Install AlexNet conv1..conv3 weights.")


@app.command("download")
def weights_download(
    dest: Annotated[Path | None, typer.Option(help="Cache directory (default: $CORTEXLOC_WEIGHTS_DIR "
                                                   "or ~/.cache/cortexloc/weights).")] = None,
    url: Annotated[str | None, typer.Option(help="Checkpoint URL (default: torchvision's).")] = None,
) -> None:
    """Fetch torchvision's AlexNet checkpoint, verify its SHA-256 (7be5be79...), keep conv1..conv3."""
    from models.frontend import weights

    _install(lambda: weights.download_alexnet(dest, **({"url": url} if url else {})))


@app.command("import")
def weights_import(
    path: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="alexnet-owt-7be5be79.pth")],
    dest: Annotated[Path | None, typer.Option(help="Cache directory.")] = None,
) -> None:
    """Install weights from a local copy of torchvision's checkpoint (verified the same way)."""
    from models.frontend import weights

    _install(lambda: weights.import_alexnet(path, dest))


@app.command("export")
def weights_export(
    dest: Annotated[Path | None, typer.Option(help="Export store (default: <weights cache>/onnx).")] = None,
) -> None:
    """Build the ONNX export of every registered backbone from its installed weights, as the encoder
    would on first use (an image build runs it, so a container starts without exporting)."""
    from models.frontend import backbones, runtimes, weights

    store = dest if dest is not None else weights.default_cache_dir() / "onnx"
    for name in backbones.names():
        backbone = backbones.get(name)({"weights_path": weights.find_alexnet(), "random_seed": 0})
        _, sha = runtimes.onnx_model(backbone, store)
        typer.echo(f"{name}: {backbone.arch}/{backbone.weights_id} -> {store / (sha + '.onnx')}")


def _install(run: Any) -> None:
    """Run a weights install; say where it went and how to point the service at it, or why not."""
    from models.frontend import weights

    try:
        path = run()
    except (weights.WeightsError, ValueError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from e
    typer.echo(f"installed {path}\nthe encoder finds it there; or set CORTEXLOC_WEIGHTS_PATH={path}")
