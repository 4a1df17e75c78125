"""`cortexloc ingest SOURCE --map M [--stream S] [--learn | --localise] [--url URL | --data-dir DIR] ...`

Progress (rate, ETA) and the summary's warnings go to stderr; the summary to stdout, or with `--json` one
JSON object per frame to stdout (`{"frame", "name", "stamp_ns", "status", "latency_ms", "answer"}`) and the
summary to stderr; a file that could not be read is status 0 (not sent), counted as an error, and the
ingest goes on. Exit status: 0 all frames answered 200; 1 some frame refused or unread, or the ingest stopped;
2 the source or the options cannot be used (a damaged bag included: one `error:` line, no traceback).
"""

from __future__ import annotations

import json
import sys
import urllib.parse
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:
    from rich.progress import Task
    from rich.text import Text

    from service.ingest.poster import Record
    from service.settings import Settings

__all__ = ["ingest_command"]


def ingest_command(
    source: Annotated[Path, typer.Argument(help="A folder of images (name order), a ROS 1 .bag, or a ROS 2 "
                                                "bag (its folder with metadata.yaml, .db3 or .mcap).")],
    map_id: Annotated[str, typer.Option("--map", help="Map to post to (created when learning and missing).")],
    stream: Annotated[str, typer.Option(help="Stream name: one robot or camera sequence.")] = "default",
    learn: Annotated[bool, typer.Option("--learn/--localise",
                                        help="Learn the frames (mapping) or only localise them.")] = True,
    url: Annotated[str | None, typer.Option(help="A running service, e.g. http://127.0.0.1:8000 (default: "
                                                 "run the service in this process).")] = None,
    data_dir: Annotated[Path | None, typer.Option(help="In process: the data directory (default: "
                                                       "$CORTEXLOC_DATA_DIR or ./var).")] = None,
    topic: Annotated[str | None, typer.Option(help="Bag topic of sensor_msgs/Image or CompressedImage "
                                                   "(default: the bag's only image topic).")] = None,
    every: Annotated[int, typer.Option(min=1, help="Post the first frame and every N-th after it.")] = 1,
    json_lines: Annotated[bool, typer.Option("--json", help="One JSON answer per frame on stdout.")] = False,
    prefetch: Annotated[int, typer.Option(min=0, max=64, help="Frames read and converted ahead of the post "
                                                              "in flight. Posts stay one at a time, in "
                                                              "source order: the map's memory depends on "
                                                              "the order.")] = 2,
    label_stamp: Annotated[bool, typer.Option("--label-stamp", help="Send each bag message's stamp "
                                                                    "(sec.nanosec) as the observation's "
                                                                    "label.")] = False,
    api_key: Annotated[str | None, typer.Option(help="API key of the service (X-API-Key); in process "
                                                     "the configured CORTEXLOC_API_KEY is used.")] = None,
    max_bytes: Annotated[int | None, typer.Option(min=1, help="Frames larger than this are not read or "
                                                  "sent, and counted as refused (413). Default: the "
                                                  "service's CORTEXLOC_MAX_UPLOAD_BYTES; with --url, its "
                                                  "default (10 MiB): give the server's if it differs.")]
    = None,
) -> None:
    """Post a folder of images or a ROS bag to a map in source order, with progress and a summary."""
    from service.cli.common import check_map_id

    check_map_id(map_id)  # before the in-process service starts (its maps replayed, its lock taken)
    # Before anything imports cv2 (the readers do): the settings set OpenCV's pixel guard for the app.
    settings, api_key = target(url, data_dir, api_key)

    import anyio

    from models.frontend.limits import DEFAULT_MAX_BYTES
    from service.ingest import poster
    from service.ingest.sources import SourceError, open_source
    from service.maps.errors import DataDirectoryInUse
    from service.settings import ConfigError

    if max_bytes is None:
        max_bytes = settings.max_upload_bytes if settings is not None else DEFAULT_MAX_BYTES
    try:
        src = open_source(source, topic=topic, every=every, max_bytes=max_bytes)
    except SourceError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from e
    opts = poster.Options(map_id=map_id, stream=stream, learn=learn, label_stamp=label_stamp,
                          api_key=api_key, prefetch=prefetch)
    progress = _progress(src.total, src.describe())

    def on_record(rec: Record) -> None:
        if json_lines:
            sys.stdout.write(json.dumps({"frame": rec.frame, "name": rec.name, "stamp_ns": rec.stamp_ns,
                                         "status": rec.status, "latency_ms": rec.latency_ms,
                                         "answer": rec.answer}) + "\n")
            sys.stdout.flush()
        elif rec.status != 200:
            progress.console.print(f"frame {rec.name}: {rec.status} {rec.answer.get('detail', '')}")
        task = progress.tasks[0]
        progress.update(task.id, advance=1, revisits=task.fields["revisits"] + rec.is_revisit(),
                        errors=task.fields["errors"] + (rec.status != 200))

    async def run() -> poster.Summary:
        client = poster.remote_client(url) if settings is None else poster.in_process_client(settings)
        async with client as c:
            return await poster.ingest(c, src, opts, on_record=on_record)

    out = sys.stderr if json_lines else sys.stdout
    try:
        with progress:
            summary = anyio.run(run)
    except poster.IngestError as e:
        print(e.summary.text(), file=out)
        typer.echo(f"error: stopped: {e}", err=True)
        raise typer.Exit(1) from e
    except (SourceError, ConfigError) as e:  # a bag message that cannot be read; the app's configuration
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from e
    except DataDirectoryInUse as e:  # in process, beside a server on the same data directory
        typer.echo(f"error: {e}; post to it with --url instead", err=True)
        raise typer.Exit(1) from e
    print(summary.text(), file=out)
    if summary.errors:
        raise typer.Exit(1)


def target(url: str | None, data_dir: Path | None, api_key: str | None) -> tuple[Settings | None, str | None]:
    """(the in-process app's settings, None with `--url`; the API key to send: the given one, else the
    in-process service's). `--url` and `--data-dir` together are a usage error."""
    if url is not None and data_dir is not None:
        raise typer.BadParameter("--data-dir is for the in-process service; with --url the server has its "
                                 "own", param_hint="--data-dir")
    if url is not None:
        parts = urllib.parse.urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise typer.BadParameter(f"{url!r} is no http:// or https:// URL (e.g. http://127.0.0.1:8000)",
                                     param_hint="--url")
    from service.cli.serve import command_settings

    settings = None if url is not None else command_settings(data_dir)
    return settings, settings.api_key if settings is not None and api_key is None else api_key


def _progress(total: int, what: str):
    """A progress bar on stderr: done/total, frames/s, ETA, revisits and errors so far."""
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        ProgressColumn,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )
    from rich.text import Text

    class Rate(ProgressColumn):
        def render(self, task: Task) -> Text:
            return Text("-- frames/s" if task.speed is None else f"{task.speed:.1f} frames/s")

    progress = Progress(TextColumn("ingest"), BarColumn(), MofNCompleteColumn(), Rate(), TimeElapsedColumn(),
                        TextColumn("ETA"), TimeRemainingColumn(),
                        TextColumn("revisits {task.fields[revisits]} errors {task.fields[errors]}"),
                        console=Console(stderr=True), transient=False)
    progress.console.print(f"ingest {what}: {total} frames")
    progress.add_task("ingest", total=total, revisits=0, errors=0)
    return progress
