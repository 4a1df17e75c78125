"""`cortexloc serve --ray` and `cortexloc shards list | move`: the Ray Serve scale-out
(service.scaleout; docs/scaling.md). Needs the `ray` extra."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated

import typer

__all__ = ["app", "serve_ray"]

app = typer.Typer(no_args_is_help=True, help="The map shards of a Ray Serve deployment (`serve --ray`).")

AddressOpt = Annotated[str, typer.Option(help="The Ray cluster (`ray start --head` prints it; default: "
                                              "the running local one).")]


def _ray(address: str):
    try:
        import ray
    except ImportError as e:
        typer.echo("error: Ray is not installed: pip install 'cortexloc[ray]'", err=True)
        raise typer.Exit(2) from e
    ray.init(address=address, logging_level="WARNING", log_to_driver=False)
    return ray


def serve_ray(host: str, port: int, data_dir: Path, shards: int, encoder_replicas: int, autoscale: bool,
              address: str) -> None:
    """Deploy the application on the Ray cluster at `address` (a local one when `local`) and wait."""
    ray = _ray(None if address == "local" else address)
    from ray import serve

    from service.scaleout.deployments import APP_NAME, build_app

    serve.start(http_options={"host": host, "port": port})
    serve.run(build_app(data_dir, shards=shards, encoder_replicas=encoder_replicas, autoscale=autoscale),
              name=APP_NAME, route_prefix="/")
    typer.echo(f"cortexloc on Ray Serve: http://{host}:{port} ({shards} shards, data in {data_dir})")
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        serve.shutdown()
        ray.shutdown()


def _ingress(address: str):
    _ray(address)
    from ray import serve

    from service.scaleout.deployments import APP_NAME

    return serve.get_deployment_handle("Ingress", app_name=APP_NAME)


@app.command("list")
def list_routes(address: AddressOpt = "auto") -> None:
    """The map -> shard table: map, shard, state (serving | moving), tab-separated."""
    for map_id, shard, state in _ingress(address).routes.remote().result():
        typer.echo(f"{map_id}\t{shard}\t{state}")


@app.command("move")
def move(map_id: Annotated[str, typer.Argument(help="The map to move.")],
         to: Annotated[str, typer.Option("--to", help="The shard that will own it (shard-<i>).")],
         address: AddressOpt = "auto") -> None:
    """Move a map to another shard: drain it (503 + Retry-After meanwhile), snapshot, import there,
    switch the table, delete the old copy. Prints the result as JSON; exit 1 when it stays where it was."""
    try:
        out = _ingress(address).move.remote(map_id, to).result()
    except typer.Exit:  # no Ray (`_ray`): click's Exit is an Exception too, and it said why already
        raise
    except Exception as e:  # no cluster, or the deployment's error (MoveFailed, MapNotFound), wrapped by Ray
        typer.echo(f"error: {getattr(e, 'cause', None) or e}", err=True)
        raise typer.Exit(1) from e
    typer.echo(json.dumps(out))
