"""PR curve, AUC, recall@K, tolerance and grid scoring (docs/design/science.md §8)."""

from __future__ import annotations

import numpy as np
import pytest

from models.evaluation import metrics
from models.evaluation.datasets import GRID_PLACES_FILE, GRID_SDR_FILES, grid_dir
from models.evaluation.gridworld import generate, load_published
from models.evaluation.metrics import (
    apply_tolerance,
    auc,
    grid_evaluation,
    place_ground_truth,
    pr_curve,
    recall_at_100_precision,
    recall_at_k,
    soft_ground_truth,
)
from models.sdr import INDEX_DTYPE, dice_matrix

GRID_DIR = grid_dir()
PLACES_FILE = GRID_DIR / GRID_PLACES_FILE


def as_sdr(indices: list[int]) -> np.ndarray:
    """A sorted, unique int32 SDR of `indices`."""
    return np.unique(np.asarray(indices, dtype=np.int64)).astype(INDEX_DTYPE)


def _reference_create_pr(S: np.ndarray, GT: np.ndarray, n: int = 100) -> tuple[list[float], list[float]]:
    """[VPRT] createPR, "multi" matching, written out as the per-threshold loop."""
    gt = GT.astype(bool)
    P, R = [1.0], [0.0]
    for tau in np.linspace(S.max(), S.min(), n):
        selected = S >= tau  # noqa: SIM300 (S is the matrix, not a constant)
        TP = np.count_nonzero(gt & selected)
        FN = np.count_nonzero(gt & ~selected)
        FP = np.count_nonzero(~gt & selected)
        P.append(TP / (TP + FP))
        R.append(TP / (TP + FN))
    return P, R


# --- PR curve and AUC (§8.2) --------------------------------------------------------------------------


def test_pr_curve_hand_computed() -> None:
    S = np.array([[1.0, 0.0], [0.5, 0.75]])
    GT = np.eye(2, dtype=bool)
    P, R = pr_curve(S, GT, n_thresholds=3)  # τ = 1, 0.5, 0
    np.testing.assert_allclose(P, [1.0, 1.0, 2 / 3, 0.5])
    np.testing.assert_allclose(R, [0.0, 0.5, 1.0, 1.0])
    assert auc(P, R) == pytest.approx(0.5 * 1.0 + 0.5 * (1 + 2 / 3) / 2)
    assert recall_at_100_precision(P, R) == 0.5


def test_pr_curve_default_has_101_points_and_is_shape_agnostic() -> None:
    rng = np.random.default_rng(0)
    S = rng.random((6, 7))
    GT = rng.random((6, 7)) < 0.3
    P, R = pr_curve(S, GT)
    assert P.shape == R.shape == (101,)
    P_flat, R_flat = pr_curve(S.ravel(), GT.ravel())
    np.testing.assert_array_equal(P, P_flat)
    np.testing.assert_array_equal(R, R_flat)
    assert R[-1] == 1.0 and P[-1] == pytest.approx(GT.mean())


@pytest.mark.parametrize("seed", range(5))
def test_pr_curve_matches_the_reference_loop_with_ties(seed: int) -> None:
    rng = np.random.default_rng(seed)
    S = rng.integers(0, 12, size=(40, 40)).astype(float)  # many ties, thresholds hit values exactly
    GT = rng.random((40, 40)) < 0.1
    P, R = pr_curve(S, GT)
    P_ref, R_ref = _reference_create_pr(S, GT)
    np.testing.assert_allclose(P, P_ref, rtol=0, atol=1e-15)
    np.testing.assert_allclose(R, R_ref, rtol=0, atol=1e-15)


def test_pr_curve_errors() -> None:
    with pytest.raises(ValueError, match="no positive"):
        pr_curve(np.ones((3, 3)), np.zeros((3, 3), dtype=bool))
    with pytest.raises(ValueError, match="shapes"):
        pr_curve(np.ones((3, 3)), np.ones((3, 2), dtype=bool))
    with pytest.raises(ValueError, match="NaN"):
        pr_curve(np.array([np.nan, 1.0]), np.array([True, False]))


def test_perfect_separation_gives_auc_one_and_full_recall_at_100p() -> None:
    GT = np.eye(5, dtype=bool)
    S = np.where(GT, 0.9, 0.1)
    P, R = pr_curve(S, GT)
    assert auc(P, R) == pytest.approx(1.0)
    assert recall_at_100_precision(P, R) == 1.0


def test_recall_at_100_precision_is_zero_without_a_precise_point() -> None:
    assert recall_at_100_precision([1.0, 0.5, 0.4], [0.0, 0.5, 1.0]) == 0.0


# --- recall@K (§8.3) ----------------------------------------------------------------------------------


def test_recall_at_k_counts_only_queries_with_a_positive() -> None:
    S = np.array([[0.9, 0.2, 0.5],
                  [0.1, 0.8, 0.4],
                  [0.3, 0.7, 0.6]])
    GT = np.array([[1, 0, 0],
                   [0, 0, 0],
                   [0, 1, 0]], dtype=bool)  # query 2 has no positive
    assert recall_at_k(S, GT, 1) == 0.5  # query 0 hit, query 1 ranks db 1 first
    assert recall_at_k(S, GT, 2) == 1.0


def test_recall_at_k_ties_prefer_the_older_item() -> None:
    S = np.array([[0.5, 0.5], [0.5, 0.5]])
    GT_new = np.array([[0, 0], [1, 1]], dtype=bool)
    GT_old = np.array([[1, 1], [0, 0]], dtype=bool)
    assert recall_at_k(S, GT_new, 1) == 0.0
    assert recall_at_k(S, GT_old, 1) == 1.0
    assert recall_at_k(S, GT_new, 2) == 1.0


def test_recall_at_k_valid_mask_excludes_items() -> None:
    S = np.array([[0.1], [0.9], [0.5]])
    GT = np.array([[1], [0], [0]], dtype=bool)
    assert recall_at_k(S, GT, 1) == 0.0
    valid = np.array([[True], [False], [False]])
    assert recall_at_k(S, GT, 1, valid=valid) == 1.0
    # A positive outside the mask is no positive: the query does not count.
    with pytest.raises(ValueError, match="no query"):
        recall_at_k(S, GT, 1, valid=~valid)
    # Fewer eligible items than k: ineligible ones fill the list but never hit.
    assert recall_at_k(S, np.array([[0], [1], [1]], dtype=bool), 5,
                       valid=np.array([[True], [False], [True]])) == 1.0


def test_recall_at_k_errors() -> None:
    with pytest.raises(ValueError):
        recall_at_k(np.ones((2, 2)), np.eye(2, dtype=bool), 0)
    with pytest.raises(ValueError):
        recall_at_k(np.ones(4), np.ones(4, dtype=bool), 1)


# --- tolerance (§8.3) ---------------------------------------------------------------------------------


def test_soft_ground_truth_widens_along_the_database_axis() -> None:
    soft = soft_ground_truth(np.eye(5, dtype=bool), 1)
    expected = np.abs(np.subtract.outer(np.arange(5), np.arange(5))) <= 1
    np.testing.assert_array_equal(soft, expected)
    np.testing.assert_array_equal(soft_ground_truth(np.eye(5, dtype=bool), 0), np.eye(5, dtype=bool))
    np.testing.assert_array_equal(soft_ground_truth(np.eye(3, dtype=bool), 10), np.ones((3, 3), bool))


def test_apply_tolerance_ignores_near_misses_in_pr_and_counts_them_for_recall() -> None:
    # Query q's best match is db q+1 (a neighbour); the exact match is second.
    S = np.array([[0.6, 0.0, 0.1, 0.0],
                  [0.9, 0.6, 0.0, 0.1],
                  [0.0, 0.9, 0.6, 0.0],
                  [0.1, 0.0, 0.9, 0.6]])
    GT = np.eye(4, dtype=bool)
    S_pr, GT_soft = apply_tolerance(S, GT, 1)
    expected = np.where(np.abs(np.subtract.outer(np.arange(4), np.arange(4))) == 1, 0.0, S)
    np.testing.assert_array_equal(S_pr, expected)
    assert S[1, 0] == 0.9  # input untouched
    assert recall_at_k(S, GT, 1) == 0.25
    assert recall_at_k(S, GT_soft, 1) == 1.0
    P_hard, R_hard = pr_curve(S, GT)
    P_tol, R_tol = pr_curve(S_pr, GT)
    assert auc(P_tol, R_tol) > auc(P_hard, R_hard)
    # With the neighbours ignored the exact matches are the top scores: a perfect curve.
    assert auc(P_tol, R_tol) == pytest.approx(1.0)
    assert recall_at_100_precision(P_tol, R_tol) == 1.0
    # The `GT_soft` argument of pr_curve is the same operation.
    P_arg, R_arg = pr_curve(S, GT, GT_soft=GT_soft)
    np.testing.assert_array_equal(P_arg, P_tol)
    np.testing.assert_array_equal(R_arg, R_tol)


def test_apply_tolerance_zero_is_identity() -> None:
    S = np.arange(9.0).reshape(3, 3)
    S_pr, soft = apply_tolerance(S, np.eye(3, dtype=bool), 0)
    np.testing.assert_array_equal(S_pr, S)
    np.testing.assert_array_equal(soft, np.eye(3, dtype=bool))
    with pytest.raises(ValueError):
        apply_tolerance(S, np.eye(3, dtype=bool), -1)


# --- grid scoring (§8.4) ------------------------------------------------------------------------------


def test_place_ground_truth() -> None:
    gt = place_ground_truth(np.array([[8, 6], [12, 6], [8, 6]]))
    np.testing.assert_array_equal(gt, [[1, 0, 1], [0, 1, 0], [1, 0, 1]])


def _tiny_grid() -> tuple[list[np.ndarray], np.ndarray]:
    descriptors = [as_sdr([0, 1, 2, 3]), as_sdr([4, 5]), as_sdr([0, 1, 2, 9]), as_sdr([4, 5, 6, 7])]
    places = np.array([[0, 0], [1, 0], [0, 0], [1, 0]])
    return descriptors, places


def test_paper_scoring_builds_the_published_matrix() -> None:
    descriptors, places = _tiny_grid()
    result = grid_evaluation(descriptors, places, "paper")
    expected_S = np.array([[4, 0, 3, 0],
                           [1, 2, 0, 2],
                           [1, 1, 4, 0],
                           [1, 1, 1, 4]], dtype=float)
    np.testing.assert_array_equal(result["S"], expected_S)
    expected_GT = np.array([[1, 0, 1, 0],
                            [0, 1, 0, 1],
                            [0, 0, 1, 0],
                            [0, 0, 0, 1]], dtype=bool)
    P, R = pr_curve(expected_S, expected_GT)
    assert result["scoring"] == "paper"
    assert result["P"] == P.tolist() and result["R"] == R.tolist()
    assert result["auc"] == auc(P, R)
    assert result["recall_at_100p"] == recall_at_100_precision(P, R)


def test_clean_scoring_uses_the_strict_upper_triangle_with_dice() -> None:
    descriptors, places = _tiny_grid()
    result = grid_evaluation(descriptors, places, "clean")
    D = dice_matrix(descriptors)
    np.testing.assert_array_equal(result["S"], D)
    iu = np.triu_indices(4, k=1)
    P, R = pr_curve(D[iu], place_ground_truth(places)[iu])
    assert result["P"] == P.tolist() and result["R"] == R.tolist()
    # Pairs (0,2) Dice 0.75 and (1,3) Dice 2/3 are the only positives and the top two scores.
    assert result["auc"] == pytest.approx(1.0)
    assert result["recall_at_100p"] == 1.0


def test_grid_recall_is_online_loop_closure() -> None:
    # Step 2 revisits step 0, but a newer item (step 3) would win if it were eligible.
    descriptors = [as_sdr([0, 1, 2, 3]), as_sdr([10, 11]), as_sdr([0, 1, 20, 21]), as_sdr([0, 1, 20, 21])]
    places = np.array([[0, 0], [1, 0], [0, 0], [2, 0]])
    for scoring in ("paper", "clean"):
        result = grid_evaluation(descriptors, places, scoring)
        assert result["recall_at_1"] == 1.0  # only query 2 has an older positive
    # Query 3 now revisits step 1 but is closest to step 2: a miss at K = 1, a hit at K = 5.
    places = np.array([[0, 0], [1, 0], [0, 0], [1, 0]])
    result = grid_evaluation(descriptors, places, "clean")
    assert result["recall_at_1"] == 0.5 and result["recall_at_5"] == 1.0


def test_grid_evaluation_rejects_bad_input() -> None:
    descriptors, places = _tiny_grid()
    with pytest.raises(ValueError, match="scoring"):
        grid_evaluation(descriptors, places, "fancy")
    with pytest.raises(ValueError):
        grid_evaluation(descriptors[:3], places, "paper")


def test_generated_grid_scores_are_sane() -> None:
    data = generate(0, 0.0, seed=0)
    for scoring in ("paper", "clean"):
        result = grid_evaluation(data.sdrs, data.places, scoring)
        assert 0.0 <= result["auc"] <= 1.0
        assert result["recall_at_1"] == 1.0  # noise-free and unaliased: every revisit is exact
        assert result["S"].shape == (212, 212)
    assert grid_evaluation(data.sdrs, data.places, "clean")["auc"] == pytest.approx(1.0)


@pytest.mark.skipif(not all((GRID_DIR / n).is_file() for n in (GRID_PLACES_FILE, *GRID_SDR_FILES.values())),
                    reason=f"published grid-world data not found in {GRID_DIR} (set CORTEXLOC_SHARED_DATA)")
@pytest.mark.parametrize(("key", "paper", "clean"), [
    ("a1n0", 0.911734, 0.944444),
    ("a5n05", 0.738555, 0.596987),
])
def test_input_sdr_check_values(key: str, paper: float, clean: float) -> None:
    """§8.4 check values: InputSDR on the published files, to 6 decimals."""
    data = load_published(GRID_DIR / GRID_SDR_FILES[key], PLACES_FILE)
    paper_result = grid_evaluation(data.sdrs, data.places, "paper")
    clean_result = grid_evaluation(data.sdrs, data.places, "clean")
    assert round(paper_result["auc"], 6) == paper
    assert round(clean_result["auc"], 6) == clean
    for result in (paper_result, clean_result):
        assert len(result["P"]) == len(result["R"]) == 101
        assert 0.0 <= result["recall_at_1"] <= result["recall_at_5"] <= 1.0


# ---- per-query metrics (one answer per query, with a confidence) ----------------------------------


def test_query_pr_curve_counts_answers_over_confidence_thresholds():
    conf = np.array([0.9, 0.8, 0.8, 0.3])
    correct = np.array([True, False, True, True])
    has_pos = np.array([True, True, True, False])  # the last query has no match: its answer is wrong
    P, R = metrics.query_pr_curve(conf, correct, has_pos)
    # Thresholds 0.9, 0.8 (both tied answers at once), 0.3; recall over the 3 queries with a match.
    np.testing.assert_allclose(P, [1.0, 1.0, 2 / 3, 2 / 4])
    np.testing.assert_allclose(R, [0.0, 1 / 3, 2 / 3, 2 / 3])
    with pytest.raises(ValueError, match="no query has a positive"):
        metrics.query_pr_curve(conf, correct, np.zeros(4, bool))


def test_query_metrics_reward_confident_right_answers():
    gt = np.eye(4, dtype=bool)
    S = np.array([[0.9, 0.0, 0.0, 0.0],
                  [0.0, 0.2, 0.7, 0.0],  # query 2 answers row 1: wrong, but confidently
                  [0.0, 0.1, 0.1, 0.0],
                  [0.0, 0.0, 0.0, 0.8]])
    q = metrics.query_metrics(S, gt)
    assert q["best"].tolist() == [0, 1, 1, 3] and q["correct"].tolist() == [True, True, False, True]
    assert q["recall_at_1"] == 0.75
    assert q["query_recall_at_100p"] == 0.5  # the two most confident answers are right, then a wrong one
    assert 0.0 < q["query_auc"] < 1.0
    # The same answers, the wrong one least confident: precision stays 1 up to recall 0.75.
    S2 = S.copy()
    S2[1, 2] = 0.15
    S2[2, 2] = 0.1
    q2 = metrics.query_metrics(S2, gt)
    assert q2["query_recall_at_100p"] == 0.75 and q2["query_auc"] > q["query_auc"]
