"""Every service test runs with a clean CORTEXLOC_* environment and no installed AlexNet weights."""

from __future__ import annotations

import os

import pytest


@pytest.fixture(autouse=True)
def _isolated_env(monkeypatch, tmp_path):
    for var in list(os.environ):
        if var.startswith("CORTEXLOC_"):
            monkeypatch.delenv(var)
    monkeypatch.setenv("CORTEXLOC_WEIGHTS_DIR", str(tmp_path / "no-weights"))


@pytest.fixture(autouse=True)
def _tiny_default_preset(monkeypatch):
    """Service tests run the service's real code paths on a small map: the default preset's TM and
    projection (64,896 x 1,024 floats) would cost seconds and 266 MB per app otherwise."""
    from models import presets

    tiny = {"description": "tiny default for service tests",
            "tm": {**presets.confs["cortexloc-default"]["tm"], "columnDimensions": 128,
                   "maxSegmentsPerCell": 8, "maxSynapsesPerSegment": 16, "maxNewSynapseCount": 8,
                   "activationThreshold": 4, "minThreshold": 2},
            "slsbh": {**presets.confs["cortexloc-default"]["slsbh"], "k": 64}}
    monkeypatch.setitem(presets.confs, "cortexloc-default", tiny)
