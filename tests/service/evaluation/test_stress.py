"""The loop-closure stress suite (service/evaluation/stress.py, issue 35): its `--quick` part on a real
Nordland window, through the service's path at the service's defaults and a new map's seed (42) beside
the evaluations' (1). Skips without ../shared/data."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from models.evaluation import datasets
from service.cli import app
from service.evaluation import stress

NORDLAND = datasets.nordland_dir()


@pytest.fixture(autouse=True)
def _tiny_default_preset():
    """The suite measures the service's defaults: the map preset too, not the tiny one of the other
    service tests (tests/service/conftest.py)."""
needs_data = pytest.mark.skipif(not (NORDLAND / "summer").is_dir(), reason=f"no Nordland data at {NORDLAND}")


def test_merges_count_places_whose_rows_show_other_labels_and_frames_consolidated_elsewhere() -> None:
    labels = np.array([0, 1, 2, 30, 31, 3])
    trace = {"row_frame": np.array([0, 1, 2, 3, 4]), "row_place": np.array([1, 1, 3, 1, 5]),
             "visit": np.array([-1, -1, -1, -1, -1, 3])}  # rows 1, 2 and 4 one place; frame 5 into row 3
    assert stress.merges(labels, trace) == {"merged_places": 1, "wrong_consolidations": 0}
    trace["visit"][5] = 1  # frame 5 (label 3) into row 1 (label 0): another place
    assert stress.merges(labels, trace)["wrong_consolidations"] == 1


def test_every_case_builds_its_route_and_the_windows_cover_both_halves(tmp_path) -> None:
    assert list(stress.windows(True)) == [("tune", 100)]
    full = list(stress.windows(False))
    assert len(full) == 14 and full[0] == ("tune", 0) and full[-1] == ("test", 1494)
    with pytest.raises(ValueError, match="unknown case"):
        stress.route(None, "nope", 0)  # type: ignore[arg-type]


def test_the_faster_case_drives_lap_2_in_winter_at_twice_the_pace() -> None:
    """`faster` (docs/results.md §10.28): the window in summer, then every other file of it in winter."""
    class Seen:
        def image(self, season: str, i: int) -> np.ndarray:
            return np.full((4, 6, 3), (i % 100) + (100 if season == "winter" else 0), np.uint8)

    r = stress.route(Seen(), "faster", 300)  # type: ignore[arg-type]
    w = stress.WINDOW
    assert list(r.labels) == [*range(300, 300 + w), *range(300, 300 + w, 2)]
    assert list(r.laps) == [0] * w + [1] * (w // 2) and r.streams is None
    assert r.pngs[w] == stress.png(Seen().image("winter", 300)) and r.pngs[w + 1] == stress.png(
        Seen().image("winter", 302))
    assert "faster" in stress.CASES and "faster" not in stress.QUICK_CASES


@needs_data
def test_the_quick_suite_maps_without_a_false_revisit_or_a_merged_place_and_closes_real_loops(tmp_path):
    """One robot mapping while it drives: a slower robot (each frame 3 times), a low-texture stretch and a
    robot's two cameras naming one trail (before a path had to keep pace with its stream, 3 false
    revisits and a merged place at the new map's seed, docs/design/science.md §11.13) make no false
    revisit and merge no places (before the short-term memory: 2-19 false revisits and
    5-53 merged places per such run at these seeds, docs/results.md §10.11); a short loop and a noisy
    second lap still close, at precision 1. (The two cameras' second lap closes 0.25-0.32 of its loops
    here: one view stored twice, docs/results.md §10.23, not solved.)"""
    out = tmp_path / "quick.json"
    r = CliRunner().invoke(app, ["eval", "slam", "--suite", "--quick", "--data", str(NORDLAND),
                                 "--json", str(out)])
    assert r.exit_code == 0, r.output
    summary = json.loads(out.read_text())["summary"]
    assert set(summary) == set(stress.QUICK_CASES)
    for case, per_method in summary.items():
        s = per_method["service-slam"]
        assert s["runs"] == len(stress.QUICK_SEEDS)
        assert s["false_revisits"] == 0 and s["merged_places"] == 0, (case, s)
    # The span gate (docs/design/science.md §11.11) calls no revisit where 4 or more places score near
    # the best: this window's slow stretches give right answers such spans, so lap-2 recall is 0.45
    # (short loop) and 0.525 (noise) at worst, 0.65 and 0.695 without the gate (docs/results.md §10.13).
    for case in ("short-loop", "noise"):
        s = summary[case]["service-slam"]
        assert s["precision_worst"] >= 0.99 and s["recall_worst"] >= 0.4, (case, s)


@needs_data
def test_the_suite_runs_at_another_threshold_and_the_default_keeps_its_margin(tmp_path):
    """`--threshold`: the maps made at that revisit threshold. Under the margin the default keeps
    (docs/results.md §10.20: the lowest threshold the quick suite passes is 0.83; 0.88 before the
    departure level read one code a move and a path back along the stream's own trail needed odometry's
    word), at 0.82, the slower robot calls a false revisit and merges a place; the default passes (the
    test above)."""
    out = tmp_path / "quick.json"
    r = CliRunner().invoke(app, ["eval", "slam", "--suite", "--quick", "--data", str(NORDLAND),
                                 "--threshold", "0.82", "--json", str(out)])
    assert r.exit_code == 0, r.output
    slow = json.loads(out.read_text())["summary"]["rate3"]["service-slam"]
    assert slow["false_revisits"] >= 1 and slow["merged_places"] >= 1


def test_the_suite_runs_only_the_cases_asked_for_and_refuses_an_unknown_one(tmp_path, monkeypatch) -> None:
    """`--cases`: only those (`cortexloc eval slam --suite --quick --cases cameras`: a robot's two cameras
    naming one trail); a case the suite does not know is a usage error, before any data is read."""
    asked = {}
    monkeypatch.setattr(stress, "suite_runs", lambda **kw: asked.update(kw))
    r = CliRunner().invoke(app, ["eval", "slam", "--suite", "--quick", "--cases", "cameras,flat",
                                 "--data", str(tmp_path)])
    assert r.exit_code == 0, r.output
    assert asked["cases"] == ("cameras", "flat") and asked["quick"] is True
    r = CliRunner().invoke(app, ["eval", "slam", "--suite", "--cases", "nope", "--data", str(tmp_path)])
    assert r.exit_code == 2 and "unknown case" in r.output
    assert "cameras" in stress.QUICK_CASES and set(stress.QUICK_CASES) <= set(stress.CASES)
