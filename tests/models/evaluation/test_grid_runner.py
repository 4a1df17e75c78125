"""The grid protocol end to end: runner, the `cortexloc` CLI contract and the paper's acceptance band."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from models import presets
from models.evaluation import gridworld, runner
from models.evaluation.datasets import GRID_PLACES_FILE, GRID_SDR_FILES, grid_dir
from service.cli import app

GRID = grid_dir()
needs_data = pytest.mark.skipif(
    not (GRID / GRID_PLACES_FILE).is_file(),
    reason=f"published grid-world data not found in {GRID} (set CORTEXLOC_SHARED_DATA)")
cli = CliRunner()


def published(key: str) -> gridworld.GridData:
    return gridworld.load_published(GRID / GRID_SDR_FILES[key], GRID / GRID_PLACES_FILE)


def test_presets_command_lists_every_preset_with_description():
    result = cli.invoke(app, ["presets"])
    assert result.exit_code == 0
    lines = result.stdout.strip().splitlines()
    assert [line.split("\t")[0] for line in lines] == presets.names()
    assert all(len(line.split("\t")) == 2 and line.split("\t")[1] for line in lines)
    for required in ("cba2020-grid", "cba2020-nordland", "numenta-defaults"):
        assert required in presets.names()


def test_eval_grid_generate_writes_json_table_and_plots(tmp_path):
    out = tmp_path / "r.json"
    result = cli.invoke(app, ["eval", "grid", "--generate", "--aliasing", "5", "--noise", "0.5",
                              "--loops", "3", "--seeds", "2", "--scoring", "clean", "--json", str(out),
                              "--plots", str(tmp_path / "plots"), "--preset", "cortexloc-grid"])
    assert result.exit_code == 0, result.output
    payload = json.loads(out.read_text())
    assert payload["scoring"] == "clean"
    assert list(payload["methods"]) == ["pairwise", "pairwise-seq", "mcn", "htm"]
    for entry in payload["methods"].values():
        assert entry["auc_min"] <= entry["auc_mean"] <= entry["auc_max"] <= 1.0
        assert 0.0 <= entry["recall_at_1_mean"] <= 1.0
        assert len(entry["per_seed"]) == 2
    assert payload["methods"]["htm"]["preset"] == "cortexloc-grid"
    assert payload["methods"]["htm"]["predicted_column_fraction_mean"] > 0
    assert "pairwise" in result.stdout and "htm" in result.stdout  # the table
    pngs = sorted(p.name for p in (tmp_path / "plots").glob("*.png"))
    assert "pr_clean.png" in pngs and len(pngs) == 5


def test_eval_grid_rejects_bad_arguments(tmp_path):
    assert cli.invoke(app, ["eval", "grid", "--generate", "--scoring", "nope"]).exit_code == 2
    assert cli.invoke(app, ["eval", "grid", "--generate", "--preset", "nope"]).exit_code == 2
    assert cli.invoke(app, ["eval", "grid"]).exit_code == 2  # neither files nor --generate
    assert cli.invoke(app, ["eval", "grid", "--generate", "--aliasing", "9"]).exit_code == 2
    bad = tmp_path / "bad.txt"
    bad.write_text("0,1\n")
    places = tmp_path / "p.txt"
    places.write_text("# x y\n8,3\n")
    r = cli.invoke(app, ["eval", "grid", "--sdr", str(bad), "--places", str(places)])
    assert r.exit_code == 2 and "bad.txt" in r.output


def test_bench_tm_command_reports_json(tmp_path):
    out = tmp_path / "b.json"
    r = cli.invoke(app, ["bench", "tm", "--columns", "256", "--cells", "4", "--active", "8", "--steps", "50",
                         "--json", str(out)])
    assert r.exit_code == 0, r.output
    payload = json.loads(out.read_text())
    assert {"ms_per_step_median", "rss_growth_mb", "segments", "synapses"} <= set(payload)
    assert payload["segments"] > 0


def test_seeds_make_runs_reproducible_and_distinct():
    def data(s: int) -> gridworld.GridData:
        return gridworld.generate(1, 0.25, loops=3, seed=s)

    a = runner.grid_experiment(data, scoring="clean", seeds=2, seed=5)
    b = runner.grid_experiment(data, scoring="clean", seeds=2, seed=5)
    c = runner.grid_experiment(data, scoring="clean", seeds=2, seed=6)
    assert a["methods"]["htm"]["per_seed"] == b["methods"]["htm"]["per_seed"]
    assert a["methods"]["htm"]["per_seed"] != c["methods"]["htm"]["per_seed"]


@needs_data
def test_paper_scoring_reproduces_the_published_numbers():
    """docs/design/science.md §9.3 acceptance: 10 seeds, published files, paper scoring."""
    a1 = runner.grid_experiment(lambda s: published("a1n0"), scoring="paper", seeds=10)["methods"]
    a5 = runner.grid_experiment(lambda s: published("a5n05"), scoring="paper", seeds=10)["methods"]
    assert a1["pairwise"]["auc_mean"] == pytest.approx(0.911734, abs=1e-6)
    assert a5["pairwise"]["auc_mean"] == pytest.approx(0.738555, abs=1e-6)
    assert a1["htm"]["auc_min"] == pytest.approx(1.0, abs=5e-4)
    assert 0.947 <= a5["htm"]["auc_mean"] <= 0.959
    assert 0.95 <= a1["mcn"]["auc_mean"] <= 0.995
    assert 0.79 <= a5["mcn"]["auc_mean"] <= 0.86
    # docs/design/science.md §3.8: it never predicts
    assert a5["htm"]["predicted_column_fraction_mean"] == 0.0


@needs_data
def test_predicting_preset_beats_the_paper_on_clean_scoring():
    res = runner.grid_experiment(lambda s: published("a5n05"), scoring="clean", seeds=3,
                                 preset="cortexloc-grid", methods=["htm"])["methods"]["htm"]
    assert res["auc_mean"] >= 0.99
    assert res["predicted_column_fraction_mean"] > 0.2


def test_predicting_preset_on_generated_world():
    data = gridworld.generate(5, 0.5, seed=11)
    winners, info = runner.run_htm(data, "cortexloc-grid", seed=1)
    clean = runner.metrics.grid_evaluation(winners, data.places, "clean")
    pairwise = runner.metrics.grid_evaluation(data.sdrs, data.places, "clean")
    assert info["predicted_column_fraction"] > 0.2
    assert clean["auc"] > pairwise["auc"] + 0.2
    assert np.isfinite(clean["recall_at_1"])


def test_the_memory_always_runs_beside_a_sequence_filter_on_its_input_codes():
    data = gridworld.generate(5, 0.5, loops=4, seed=2)
    res = runner.grid_experiment(lambda s: data, scoring="clean", seeds=1, preset="cortexloc-grid",
                                 methods=["htm"])["methods"]
    assert list(res) == ["pairwise", "pairwise-seq", "htm"]
    # With aliased twins the filter over the input codes alone beats one code against one.
    assert res["pairwise-seq"]["auc_mean"] > res["pairwise"]["auc_mean"]
    assert res["pairwise-seq"]["per_seed"][0]["ds"] == 10
