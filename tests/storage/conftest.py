"""Fixtures shared by the storage tests: a map meta, deterministic observation rows, an open store."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from storage.mapstore import MapMeta, MapStore, NewObservation

PARAMS = {"tm": {"columnDimensions": 2048, "cellsPerColumn": 32}, "slsbh": {"k": 2048, "s": 0.25},
          "encoder": {"resize": "crop"}, "seed": 7, "exclude_recent": 0}
N_COLUMNS = 2048
N_CELLS = 2048 * 32


def make_row(i: int, *, stream: str = "default", n_cells: int = N_CELLS, prev: int | None = None,
             label: str | None = None) -> NewObservation:
    """Observation number `i`, a pure function of `i` (so a crashed writer's rows can be recomputed)."""
    rng = np.random.default_rng(i)
    cols = np.sort(rng.choice(N_COLUMNS, size=40, replace=False))
    cells = np.sort(rng.choice(n_cells, size=44, replace=False))
    return NewObservation(stream=stream, image_sha256=f"{i:064x}", input_sdr=cols, winner_cells=cells,
                          context_prev_seq=prev, label=label, observation_id=f"obs-{i:08d}",
                          created_at=f"2025-01-01T00:00:{i % 60:02d}.000000Z")


@pytest.fixture
def meta() -> MapMeta:
    return MapMeta(map_id="lab", params=PARAMS, projection_sha256="ab" * 32,
                   encoder_id="alexnet-conv3:random-0:crop", cell_dtype="uint16")


@pytest.fixture
def store(tmp_path: Path, meta: MapMeta) -> Iterator[MapStore]:
    s = MapStore.create(tmp_path / "map.sqlite", meta)
    yield s
    s.close()


@pytest.fixture
def row_factory() -> Callable[..., NewObservation]:
    return make_row
