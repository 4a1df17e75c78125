"""Fixtures of the ingest tests: a clean CORTEXLOC_* environment, a real `cortexloc serve`."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest

from tests.e2e.conftest import Server


@pytest.fixture
def clean_env(monkeypatch, tmp_path):
    """No CORTEXLOC_* from the caller's shell; no installed weights (random, seeded)."""
    for var in list(os.environ):
        if var.startswith("CORTEXLOC_"):
            monkeypatch.delenv(var)
    monkeypatch.setenv("CORTEXLOC_WEIGHTS_DIR", str(tmp_path / "no-weights"))


@pytest.fixture
def served(tmp_path, clean_env) -> Iterator[Server]:
    """`cortexloc serve` in a subprocess (random weights); `.base` is its URL."""
    s = Server(tmp_path)
    try:
        s.start()
        yield s
    finally:
        s.stop()
