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
def _tiny_default_preset(tiny_default_preset):
    """Service tests run the service's real code paths on a small map (tests/conftest.py)."""
