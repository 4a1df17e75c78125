"""`cortexloc eval unknown` (service/evaluation/unknown.py): places never stored, on a slice of the route."""

from __future__ import annotations

import re

import pytest
from typer.testing import CliRunner

from service.cli import app
from tests.service.helpers import frame


@pytest.fixture
def route(tmp_path, monkeypatch):
    """Two traverses of 16 places (the second re-noised), named alike; features cached under tmp."""
    for folder, noise in (("db", 0.0), ("query", 6.0)):
        (tmp_path / folder).mkdir()
        for p in range(16):
            (tmp_path / folder / f"{p:04d}.png").write_bytes(frame(p, noise=noise))
    monkeypatch.setenv("CORTEXLOC_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path


def invoke(route, *args: str):
    return CliRunner().invoke(app, ["eval", "unknown", "--db", str(route / "db"), "--query",
                                    str(route / "query"), "--backbone", "alexnet", "--thresholds", "0.5",
                                    *args])


def test_a_slice_of_the_route_is_cut_at_split_counted_from_its_offset(route):
    r = invoke(route, "--offset", "2", "--limit", "14", "--split", "7")
    assert r.exit_code == 0, r.output
    assert "rows 2-9 learned, 9-16 driven" in r.output and "rows 9-16 learned, 2-9 driven" in r.output
    assert re.search(r"stored \(rows 2-9\) at 0\.5: precision", r.output)


def test_halves_too_short_for_the_warm_up_say_so(route):
    r = invoke(route, "--limit", "8", "--split", "4")
    assert r.exit_code == 0, r.output
    assert r.output.count("no answer (too few frames for the localiser's warm-up)") == 2


@pytest.mark.parametrize("args, says", [(("--split", "0"), "split"),
                                        (("--limit", "4", "--split", "4"), "split"),
                                        (("--offset", "16", "--split", "1"), "offset")])
def test_a_split_or_offset_that_leaves_a_half_empty_is_refused_before_any_work(route, args, says):
    r = invoke(route, *args)
    assert r.exit_code == 2 and says in r.output and "Traceback" not in r.output
    assert not (route / "cache").exists()  # refused before a feature was computed
