"""The `cortexloc` command line: a stable contract that scripts and acceptance checks call.

    cortexloc presets
    cortexloc eval grid | images | slam | ...   service.cli.evaluate, service.cli.experiments
    cortexloc bench tm | encoder | http | ...   service.cli.bench
    cortexloc weights download | import ...     service.cli.weights
    cortexloc serve [--host H] [--port P] [--data-dir DIR] [--ray [--shards N] [--encoder-replicas N]]
                                                                      service.cli.serve
    cortexloc shards list | move MAP --to SHARD [--address A]         service.cli.shards
    cortexloc import FILE.tar [--data-dir DIR]                        service.cli.maps
    cortexloc verify [--map M] [--data-dir DIR]                       service.cli.maps
    cortexloc repair --map M [--dry-run] [--url URL | --data-dir DIR] [--api-key KEY] [--json]
                                                                      service.cli.maps
    cortexloc ingest SOURCE --map M [--stream S] [--learn | --localise] [--url URL | --data-dir DIR]
                     [--topic T] [--every N] [--json] [--prefetch K] [--label-stamp] [--api-key KEY]
                                                                      service.cli.ingest

Tables go to stdout, progress and warnings to stderr, machine-readable results to --json. Importing this
package imports no heavy library (torch, cv2, rosbags): each command imports what it needs when it runs,
so `serve` can set OpenCV's pixel guard before cv2 is first imported. Where an experiment or a
benchmark goes (`eval` or `bench`) is benchmarks/__init__.py's rule.
"""

from __future__ import annotations

import typer

from models import presets
from service.cli import bench, experiments, maps, shards, weights
from service.cli.ingest import ingest_command
from service.cli.serve import process_settings, serve

__all__ = ["app", "main", "process_settings", "serve"]

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="cortexloc: visual place recognition with a Hierarchical Temporal Memory.")
# experiments.app is service.cli.evaluate.app with the searches and experiments registered on it
app.add_typer(experiments.app, name="eval")
app.add_typer(bench.app, name="bench")
app.add_typer(weights.app, name="weights")
app.add_typer(shards.app, name="shards")


@app.command("presets")
def list_presets() -> None:
    """Print every preset name, a tab, and its one-line description."""
    for name in presets.names():
        typer.echo(f"{name}\t{presets.describe(name)}")


app.command("serve")(serve)
app.command("import")(maps.import_map)
app.command("verify")(maps.verify)
app.command("repair")(maps.repair)
app.command("ingest")(ingest_command)


def main() -> None:  # pragma: no cover - console entry point
    app()
