"""Fixtures shared by the service tests and the benchmark smoke tests."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _wide_cli_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    # Typer's error boxes (Rich) wrap at 80 columns off a terminal, so a test that looks for a file's name in
    # one fails when its tmp path is long (an xdist worker's, `make test`, is 11 characters longer).
    monkeypatch.setenv("COLUMNS", "250")


@pytest.fixture
def tiny_default_preset(monkeypatch):
    """`cortexloc-default` shrunk to 128 columns and k = 64: the real code paths on a small map (the
    real TM and 64,896 x 1,024 projection would cost seconds and 266 MB per map)."""
    from models import presets

    tiny = {"description": "tiny default for tests",
            "tm": {**presets.confs["cortexloc-default"]["tm"], "columnDimensions": 128,
                   "maxSegmentsPerCell": 8, "maxSynapsesPerSegment": 16, "maxNewSynapseCount": 8,
                   "activationThreshold": 4, "minThreshold": 2},
            "slsbh": {**presets.confs["cortexloc-default"]["slsbh"], "k": 64}}
    monkeypatch.setitem(presets.confs, "cortexloc-default", tiny)



@pytest.fixture
def png_bomb():
    """`png_bomb(width, height, inflated_bytes, idat_chunks=1) -> bytes`
    (models.evaluation.bench.png_bomb): an 8-bit RGB PNG whose image data is `inflated_bytes` deflated
    zeros, whatever its raster needs."""
    from models.evaluation.bench import png_bomb

    return png_bomb


@pytest.fixture
def make_png():
    """`make_png(width, height, zlib_data, colour=2, depth=8, interlace=0, idat_chunks=1) -> bytes`."""
    from models.evaluation.bench import make_png

    return make_png
