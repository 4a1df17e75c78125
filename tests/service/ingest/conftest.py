"""Fixtures of the ingest tests: a real `cortexloc serve` (the clean CORTEXLOC_* environment and the tiny
default preset are every service test's: tests/service/conftest.py)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.e2e.conftest import Server


@pytest.fixture
def served(tmp_path) -> Iterator[Server]:
    """`cortexloc serve` in a subprocess (random weights); `.base` is its URL."""
    s = Server(tmp_path)
    try:
        s.start()
        yield s
    finally:
        s.stop()
