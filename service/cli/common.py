"""What several `cortexloc` commands share: the progress bar, the --json writer, provenance, checks of
names (presets, backbones).

Tables go to stdout, progress and warnings to stderr, machine-readable results to --json.
"""

from __future__ import annotations

import json
import platform
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import typer

from models import presets

#: What a long computation calls as it goes: (done, total).
Tick = Callable[[int, int], None]


@contextmanager
def progress(label: str, *, show: bool = True) -> Iterator[Tick | None]:
    """A progress bar on stderr (stdout stays a clean table) for the `with` block; yields the callback
    to hand to the computation, or None when `show` is False (e.g. a single run).

    rich redraws at a bounded rate however often the callback is called, so callers need not throttle.
    """
    if not show:
        yield None
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  console=Console(stderr=True)) as bar:
        task = bar.add_task(label, total=None)

        def tick(done: int, total: int) -> None:
            # a total read before the work (a live map's rows) may be passed: never show 149/138
            bar.update(task, completed=done, total=max(total, done))

        yield tick


def write_json(path: Path | None, payload: dict[str, Any]) -> None:
    """Write `payload` to `path` atomically (nothing when `path` is None); NumPy values as plain JSON."""
    if path is None:
        return
    from storage.base.files import atomic_write

    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(payload, indent=2, default=_jsonable).encode()
    atomic_write(path, lambda f: f.write(text))


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def provenance() -> dict[str, Any]:
    """The command line and versions a --json result was made with."""
    return {"command": " ".join(["cortexloc", *sys.argv[1:]]), "python": platform.python_version(),
            "numpy": np.__version__}


def check_presets(*names: str) -> None:
    """Each name must be a preset of `models.presets`."""
    for name in names:
        if name not in presets.confs:
            raise typer.BadParameter(f"unknown preset {name!r}; see `cortexloc presets`")


def check_backbone(name: str) -> None:
    """--backbone must name a backbone of the registry (models.frontend.backbones)."""
    from models.frontend import backbones

    if name not in backbones.names():
        raise typer.BadParameter(f"must be one of {', '.join(backbones.names())}", param_hint="--backbone")


def check_map_id(map_id: str) -> None:
    """--map must be a map id: a command that puts it into a URL path as it is would otherwise reach
    another resource (`m/x/..` is map m, `m/snapshots` a collection)."""
    from service.maps.ids import MAP_ID_RE

    if not MAP_ID_RE.fullmatch(map_id):  # fullmatch: the pattern's `$` also matches before a last newline
        raise typer.BadParameter(f"{map_id!r} is not a map id ({MAP_ID_RE.pattern})", param_hint="--map")
