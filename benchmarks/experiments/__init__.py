"""The variants behind docs/results.md §10.6-§10.11 (`cortexloc eval echo | null-entry | short-term |
short-term-poses | span | slam-seasons`): each replaces one rule of the service for the run only, so the rest
of the path is the service's. Also the measurements of §10.24 and §11 (`parked`, `join-level`), which run
per window and seed (`per_window`)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from typing import Any


def per_window(run: Callable[..., dict[str, Any]], seeds: list[int]) -> None:
    """`run(frames, half, lo, seed, map_conf)` on every window of both halves (`stress.windows`) at each
    map seed, with the service's encoder and map keywords (`encoder_setup`): one JSON line each, printed
    as it is done, with the seconds it took."""
    from models.evaluation import datasets
    from service.evaluation import stress
    from service.evaluation.slam import encoder_setup

    enc, cache, conf = encoder_setup(None, None)
    frames = stress.Frames(datasets.nordland_dir(), enc, cache)
    for half, lo in stress.windows(quick=False):
        for seed in seeds:
            t0 = time.perf_counter()
            line = run(frames, half, lo, seed, conf)
            line["seconds"] = round(time.perf_counter() - t0, 1)
            print(json.dumps(line), flush=True)

