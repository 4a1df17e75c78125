"""Fixtures of the ingest tests: a real `cortexloc serve` (the clean CORTEXLOC_* environment and the tiny
default preset are every service test's: tests/service/conftest.py)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.e2e.conftest import Server


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """`cortexloc serve` in a subprocess (random weights); `.base` is its URL. One per module: a start
    exports the backbone (tens of seconds on two cores), and the tests' maps have ids of their own."""
    s = Server(tmp_path_factory.mktemp("served"))
    try:
        s.start()
        yield s
    finally:
        s.stop()
