"""The grid world through the service's localiser: online loop closure (science.md §2.4, §11.4)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from models.evaluation import gridworld, metrics, online, runner
from models.sdr import dice_matrix
from service.cli import app


def test_loop_closure_is_causal_and_never_answers_the_streams_own_recent_rows() -> None:
    rng = np.random.default_rng(0)
    S = rng.random((60, 60))
    S = S + S.T
    codes = [np.sort(rng.choice(2048, 300, replace=False)) for _ in range(60)]  # every step unlike the others
    found = online.loop_closure(S, codes)
    # Each step leaves the row before it at once; the `exclusion` rows behind that are still its own.
    own = online.SequenceLocaliser().options.exclusion + 1
    answered = np.flatnonzero(found.best >= 0)
    assert answered.size and np.all(found.best[answered] < answered - own)
    assert np.all(np.isneginf(found.S[np.tril_indices(60)]))  # only older steps are ever scored
    # Changing what is not yet stored (later rows and columns) changes no earlier answer.
    later = S.copy()
    later[40:, :] = rng.random((20, 60))
    later[:, 40:] = rng.random((60, 20))
    again = online.loop_closure(later, codes)
    np.testing.assert_array_equal(again.best[:40], found.best[:40])
    np.testing.assert_array_equal(again.confidence[:40], found.confidence[:40])


@pytest.mark.parametrize("aliasing", [0, 5])
def test_loop_closure_holds_every_revisit_once_it_has_closed_the_loop(aliasing: int) -> None:
    data = gridworld.generate(aliasing, 0.0, loops=3, seed=1)
    found = online.loop_closure(dice_matrix(data.sdrs), data.sdrs)
    gt = metrics.place_ground_truth(data.places) & np.triu(np.ones((len(data),) * 2, bool), k=1)
    revisits = np.flatnonzero(gt.any(axis=0))
    assert revisits.size > 30
    # The first revisits pay the jump (a new hypothesis must overtake), aliased twins a few more.
    assert np.all(gt[found.best[revisits[6:]], revisits[6:]])


@pytest.mark.parametrize("scoring", ["clean", "paper"])
def test_online_htm_brings_its_ablation_and_scores_per_query(scoring: str) -> None:
    result = runner.grid_experiment(lambda s: gridworld.generate(5, 0.25, loops=3, seed=s), scoring=scoring,
                                    preset="cortexloc-grid", seeds=2, methods=["online-htm"])
    assert list(result["methods"]) == ["online-pairwise", "online-htm"]
    for entry in result["methods"].values():
        assert len(entry["per_seed"]) == 2
        for k in ("auc", "recall_at_1", "query_auc", "query_recall_at_100p"):
            assert 0.0 <= entry[f"{k}_min"] <= entry[f"{k}_mean"] <= entry[f"{k}_max"] <= 1.0
    # The localiser over the input codes already resolves most aliased revisits (one code alone cannot).
    alone = runner.grid_experiment(lambda s: gridworld.generate(5, 0.25, loops=3, seed=s), scoring=scoring,
                                   seeds=2, methods=["pairwise"])["methods"]["pairwise"]
    assert result["methods"]["online-pairwise"]["recall_at_1_mean"] > alone["recall_at_1_mean"] + 0.1


def test_htm_and_online_htm_share_one_temporal_memory_run() -> None:
    data = gridworld.generate(1, 0.0, loops=2, seed=3)
    both = runner.run_grid_once(data, "clean", "cortexloc-grid", "mcn-grid", 7, 7, ["htm", "online-htm"])
    assert both["htm"]["info"] is both["online-htm"]["info"]
    with pytest.raises(ValueError, match="unknown method"):
        runner.run_grid_once(data, "clean", "cortexloc-grid", "mcn-grid", 7, 7, ["online-nope"])


def test_eval_grid_cli_runs_online_htm_with_its_ablation(tmp_path) -> None:
    out = tmp_path / "r.json"
    result = CliRunner().invoke(app, ["eval", "grid", "--generate", "--aliasing", "1", "--loops", "2",
                                      "--seeds", "1", "--scoring", "clean", "--methods", "online-htm",
                                      "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert list(json.loads(out.read_text())["methods"]) == ["online-pairwise", "online-htm"]
    assert "online-pairwise" in result.stdout and "qAUC" in result.stdout
