"""What a snapshot costs, by step, as a map's store grows (issue 19 item 10): is the copy of map.sqlite
the dominant part?

Run: `cortexloc bench snapshot [--quick] [--rows 0,20000,60000] [--repeats 3]`. Writes
benchmarks/results/snapshot.json.

In process, on a temporary directory: a default map's Temporal Memory (`cortexloc-default`, 62 MiB
of preallocated arrays; a snapshot saves them whole whatever was learned) and a store of N synthetic
rows shaped like the default map's (308 active columns, 308 winner cells, a pose in the metadata).
For each N, medians over repeats of the steps `storage.snapshots.create_snapshot` takes: the online
backup of map.sqlite (`db_copy`), `np.savez` of the memory (`memory_save`), the SHA-256 of both files
(`checksums`), and the whole call (`total`, with the fsyncs and the manifest), plus the files' sizes.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks._common import quick_mode, write_json
from models.memory.temporal_memory import TemporalMemory
from models.pipeline import memory_state
from models.presets import TmOptions
from service.maps.config import MapOptions, resolve
from storage import snapshots
from storage.base.files import sha256_file
from storage.mapstore import MapMeta, MapStore, NewObservation, cell_dtype_for


def fill(store: MapStore, n: int, rng: np.random.Generator, params: dict[str, Any]) -> None:
    columns = int(params["tm"]["columnDimensions"])
    cells = columns * int(params["tm"]["cellsPerColumn"])
    batch = []
    for i in range(n):
        cols = np.sort(rng.choice(columns, 308, replace=False))
        batch.append(NewObservation(
            stream="robot1", image_sha256=f"{i:064x}", input_sdr=cols,
            winner_cells=np.sort(rng.choice(cells, 308, replace=False)),
            context_prev_seq=store.last_seq() + len(batch) if i else None,
            metadata={"stamp": float(i), "pose": {"x": float(i), "y": 0.0}}))
        if len(batch) == 1000:
            store.append_many(batch)
            batch = []
    if batch:
        store.append_many(batch)


def timed(fn: Any) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def measure(root: Path, rows: int, repeats: int) -> dict[str, Any]:
    params = resolve(MapOptions(preset="cortexloc-default", backbone="efficientnet-lite0-s5"),
                     default_preset="cortexloc-default", default_backbone="efficientnet-lite0-s5").stored()
    cells = int(params["tm"]["columnDimensions"]) * int(params["tm"]["cellsPerColumn"])
    store = MapStore.create(root / "map.sqlite", MapMeta(map_id="bench", params=params,
                                                         projection_sha256="0" * 64, encoder_id="bench",
                                                         cell_dtype=cell_dtype_for(cells)))
    fill(store, rows, np.random.default_rng(0), params)
    memory = memory_state(TemporalMemory(TmOptions.of(params["tm"])), {})
    steps: dict[str, list[float]] = {"db_copy": [], "memory_save": [], "checksums": [], "total": []}
    sizes: dict[str, int] = {}
    for r in range(repeats):
        work = root / f"r{r}"
        work.mkdir()
        steps["db_copy"].append(timed(lambda w=work: store.backup_to(w / "copy.sqlite")))
        steps["memory_save"].append(timed(lambda w=work: np.savez(w / "memory.npz", allow_pickle=False,
                                                                   **memory)))
        steps["checksums"].append(timed(lambda w=work: [sha256_file(w / f) for f in ("copy.sqlite",
                                                                                     "memory.npz")]))
        sizes = {"db_bytes": (work / "copy.sqlite").stat().st_size,
                 "memory_bytes": (work / "memory.npz").stat().st_size}
        steps["total"].append(timed(lambda w=work: snapshots.create_snapshot(store, memory, w / "snap",
                                                                             kind="manual")))
    store.close()
    out: dict[str, Any] = {"rows": rows, **sizes}
    out.update({f"{k}_s": round(statistics.median(v), 3) for k, v in steps.items()})
    return out


def main(*, quick: bool, rows: str, repeats: int) -> None:
    quick = quick_mode(quick)
    sizes = [0, 1000] if quick else [int(n) for n in rows.split(",")]
    results = []
    for n in sizes:
        with tempfile.TemporaryDirectory() as d:
            results.append(measure(Path(d), n, 1 if quick else repeats))
            print(results[-1], flush=True)
    write_json("snapshot.json", {"results": results})

