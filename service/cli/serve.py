"""`cortexloc serve`, and the settings of a service that this process runs (`serve`, in-process
`ingest`)."""

from __future__ import annotations

import socket
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:
    from service.settings import Settings


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


def command_settings(data_dir: Path | None) -> Settings:
    """The settings of the app a one-shot command runs in this process (in-process `ingest`, `repair`,
    `import`): `process_settings`, its log quiet (WARNING) and no wait for the data directory's lock
    (`CORTEXLOC_LOCK_WAIT_S` 0: a server that holds it will not let it go, and a command run beside one
    sat 30 s on a frozen progress bar before it said so), unless configured."""
    import os

    env = {name: value for name, value in (("CORTEXLOC_LOG_LEVEL", "WARNING"), ("CORTEXLOC_LOCK_WAIT_S", "0"))
           if not os.environ.get(name)}
    return process_settings(data_dir=data_dir, **env)


def _can_listen(host: str, port: int) -> None:
    """Exit 3 (uvicorn's start-up failure) with one line where `host:port` cannot be bound, before the
    encoder loads and the data directory is made: uvicorn binds only after the app has started, so a port
    in use failed a start that had already made a fresh data directory and its `default` map."""
    if port == 0:
        return
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError as e:
        typer.echo(f"error: cannot listen on {host}:{port}: {e}", err=True)
        raise typer.Exit(3) from e
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
        try:
            probe.bind(address)
        except OSError as e:
            typer.echo(f"error: cannot listen on {host}:{port}: {e.strerror or e}", err=True)
            raise typer.Exit(3) from e


def _file_limit(connections: int) -> int:
    """Raise the soft file-descriptor limit to fit `connections` and the service's own files
    (`service.server.FD_RESERVE`), up to the hard limit (a systemd unit's soft 1,024 is common, while
    idle connections each hold one); warn where it cannot. Returns the connections that fit
    (`service.server.connection_cap`)."""
    import resource

    from service.server import FD_RESERVE, connection_cap

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = connections + FD_RESERVE
    if soft != resource.RLIM_INFINITY and soft < want:
        raised = want if hard == resource.RLIM_INFINITY else min(hard, want)
        if raised > soft:
            resource.setrlimit(resource.RLIMIT_NOFILE, (raised, hard))
    connection_cap.cache_clear()
    cap = connection_cap(connections)
    if cap < connections:
        typer.echo(f"warning: the file-descriptor limit ({hard} at most) leaves room for {cap} connections, "
                   f"not CORTEXLOC_MAX_CONNECTIONS={connections}", err=True)
    return cap


def serve(
    host: Annotated[str | None, typer.Option(help="Bind address (default: $CORTEXLOC_HOST or 127.0.0.1).")]
    = None,
    port: Annotated[int | None, typer.Option(min=0, max=65535,
                                             help="Bind port (default: $CORTEXLOC_PORT or 8000).")] = None,
    data_dir: Annotated[Path | None, typer.Option(help="Root of all state (default: $CORTEXLOC_DATA_DIR "
                                                       "or ./var).")] = None,
    ray: Annotated[bool, typer.Option("--ray", help="Run on Ray Serve instead (the `ray` extra): an "
                                                    "encoder deployment, map shards and an ingress; "
                                                    "docs/scaling.md.")]
    = False,
    shards: Annotated[int, typer.Option(min=1, help="--ray: map shards (one replica each).")] = 2,
    encoder_replicas: Annotated[int, typer.Option(min=1, help="--ray: encoder replicas (the most, with "
                                                               "--autoscale).")] = 1,
    autoscale: Annotated[bool, typer.Option(help="--ray: scale the encoder on its queue.")] = False,
    ray_address: Annotated[str, typer.Option(help="--ray: the cluster's address, or `local` to start one.")]
    = "local",
) -> None:
    """Run the HTTP service (one uvicorn worker: maps live in process memory). Other settings: CORTEXLOC_*.

    With --ray the same API runs on Ray Serve (service.scaleout), each shard in `DATA_DIR/shard-<i>`."""
    settings = process_settings(host=host, port=port, data_dir=data_dir)
    if ray:
        from service.cli.shards import serve_ray

        serve_ray(settings.host, settings.port, settings.data_dir, shards, encoder_replicas, autoscale,
                  ray_address)
        return

    _can_listen(settings.host, settings.port)
    _file_limit(settings.max_connections)
    import uvicorn

    from service.app import create_app
    from service.server import BACKLOG, ProblemHttpToolsProtocol

    # loop="asyncio": the `ray` extra installs uvloop, which uvicorn would otherwise pick; the single
    # process keeps the loop it is tested and measured with, whatever extras are installed.
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, workers=1, lifespan="on",
                log_level=settings.log_level.lower(), http=ProblemHttpToolsProtocol, loop="asyncio",
                backlog=BACKLOG)

