"""Place-recognition metrics (docs/design/science.md §8).

Conventions follow [VPRT] `evaluation/metrics.py`: S has database items as rows and queries as columns,
higher = more similar; GT is a boolean matrix of the same shape (§8.1). PR curves use the "multi"
matching of [SIM]/[VPRT] `createPR` (§8.2): every entry of S is a separate decision.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from models.sdr import dice_matrix, overlap_matrix

SCORINGS = ("paper", "clean")


def pr_curve(
    S: np.ndarray, GT: np.ndarray, n_thresholds: int = 100, GT_soft: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Precision-recall curve over `n_thresholds` thresholds `linspace(max S, min S)` (§8.2).

    For each threshold τ, B = S ≥ τ; P = TP/(TP+FP), R = TP/(TP+FN); (R = 0, P = 1) is prepended.

    Args:
        S: similarities, any shape (flattened).
        GT: same shape, truthy = positive pair.
        n_thresholds: number of thresholds.
        GT_soft: optional, same shape; pairs true here but not in GT are set to min S first, i.e. ignored
            except at the last threshold ([VPRT] GTsoft, §8.3). See `apply_tolerance`.

    Returns:
        (P, R): each (n_thresholds + 1,) float64, in threshold order (descending τ).

    Raises:
        ValueError: shapes differ, S is empty or not finite, or GT has no positive.
    """
    s = np.asarray(S, dtype=np.float64).ravel()
    gt = np.asarray(GT).astype(bool).ravel()
    if np.shape(S) != np.shape(GT):
        raise ValueError(f"S and GT shapes differ: {np.shape(S)} vs {np.shape(GT)}")
    if s.size == 0:
        raise ValueError("S is empty")
    if not np.all(np.isfinite(s)):
        raise ValueError("S contains NaN or infinite values")
    n_pos = int(np.count_nonzero(gt))
    if n_pos == 0:
        raise ValueError("GT has no positive: precision and recall are undefined")
    if n_thresholds < 1:
        raise ValueError(f"n_thresholds must be >= 1, got {n_thresholds}")
    if GT_soft is not None:
        if np.shape(GT_soft) != np.shape(S):
            raise ValueError(f"S and GT_soft shapes differ: {np.shape(S)} vs {np.shape(GT_soft)}")
        s = s.copy()
        s[np.asarray(GT_soft).astype(bool).ravel() & ~gt] = s.min()

    thresholds = np.linspace(s.max(), s.min(), n_thresholds)
    # Sorting once and counting with searchsorted gives exactly the counts of the per-threshold
    # `S >= τ` loop of [VPRT] createPR, in O(N log N) instead of O(N·thresholds) (Nordland: 3.2 M pairs).
    order = np.argsort(s, kind="stable")
    s_sorted = s[order]
    pos_below = np.concatenate(([0], np.cumsum(gt[order])))  # positives among the i smallest
    first = np.searchsorted(s_sorted, thresholds, side="left")  # entries < τ
    selected = s.size - first
    tp = n_pos - pos_below[first]
    fp = selected - tp
    fn = n_pos - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        # τ ≤ max S always selects at least one entry, so TP + FP > 0 (§8.2).
        p = tp / (tp + fp)
    r = tp / (tp + fn)
    P = np.concatenate(([1.0], p.astype(np.float64)))
    R = np.concatenate(([0.0], r.astype(np.float64)))
    return P, R


def auc(P: np.ndarray | Sequence[float], R: np.ndarray | Sequence[float]) -> float:
    """Area under the PR curve: trapezoidal rule of P over R in curve order (§8.2)."""
    return float(np.trapezoid(np.asarray(P, dtype=np.float64), np.asarray(R, dtype=np.float64)))


def recall_at_100_precision(P: np.ndarray | Sequence[float], R: np.ndarray | Sequence[float]) -> float:
    """Largest recall on the PR curve with precision exactly 1; 0 if only the prepended point (§8.3)."""
    p = np.asarray(P, dtype=np.float64)
    r = np.asarray(R, dtype=np.float64)
    at_one = r[p == 1.0]
    return float(at_one.max()) if at_one.size else 0.0


def recall_at_k(S: np.ndarray, GT: np.ndarray, k: int, valid: np.ndarray | None = None) -> float:
    """Fraction of queries whose k best database items include a positive (§8.3).

    Only queries with at least one (eligible) positive count. Ties in score are broken towards the
    older item, i.e. the lower database index (stable sort on -S).

    Args:
        S: (n_db, n_query) similarities.
        GT: (n_db, n_query) bool; for a tolerance pass the soft ground truth (`apply_tolerance`).
        k: number of retrieved items, >= 1.
        valid: optional (n_db, n_query) bool, database items eligible for each query (online loop
            closure: db = {j < i}); ineligible items are neither retrieved nor counted as positives.

    Returns:
        recall@k in [0, 1].

    Raises:
        ValueError: bad shapes, k < 1, or no query with a positive.
    """
    s = np.asarray(S, dtype=np.float64)
    gt = np.asarray(GT).astype(bool)
    if s.ndim != 2 or s.shape != gt.shape:
        raise ValueError(f"S and GT must be 2-D of one shape, got {s.shape} and {gt.shape}")
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    if valid is None:
        ok = np.ones_like(gt)
    else:
        ok = np.asarray(valid).astype(bool)
        if ok.shape != s.shape:
            raise ValueError(f"valid must have shape {s.shape}, got {ok.shape}")
    # Ineligible items sink below every eligible one; they can still fill a top-k slot when a query has
    # fewer than k eligible items, but are then masked out of the hit test.
    ranked_s = np.where(ok, -s, np.inf)
    order = np.argsort(ranked_s, axis=0, kind="stable")[:k]
    cols = np.arange(s.shape[1])
    hits = (gt & ok)[order, cols[None, :]].any(axis=0)
    has_pos = (gt & ok).any(axis=0)
    n = int(np.count_nonzero(has_pos))
    if n == 0:
        raise ValueError("no query has a positive among its eligible database items")
    return float(np.count_nonzero(hits & has_pos)) / n


def soft_ground_truth(GT_hard: np.ndarray, t: int) -> np.ndarray:
    """Widen a (n_db, n_query) ground truth by ±t database items (§8.3).

    GT_soft[i, q] is true if some GT_hard[i', q] is true with |i - i'| <= t; for frame-aligned sequences
    (Nordland: GT = same file index) this is |i - q| <= t.
    """
    gt = np.asarray(GT_hard).astype(bool)
    if t < 0:
        raise ValueError(f"tolerance must be >= 0, got {t}")
    if gt.ndim != 2:
        raise ValueError(f"GT must be 2-D (n_db, n_query), got shape {gt.shape}")
    soft = gt.copy()
    for d in range(1, min(t, gt.shape[0] - 1) + 1):
        soft[d:] |= gt[:-d]
        soft[:-d] |= gt[d:]
    return soft


def apply_tolerance(S: np.ndarray, GT_hard: np.ndarray, t: int) -> tuple[np.ndarray, np.ndarray]:
    """Soft ground truth with tolerance t (§8.3, [VPRT] GTsoft).

    Args:
        S: (n_db, n_query) similarities.
        GT_hard: (n_db, n_query) bool, exact matches.
        t: tolerance in database items (0 = none).

    Returns:
        (S_pr, GT_soft): S_pr (n_db, n_query) float64, S with the pairs true only within ±t set to min S —
        score it with `pr_curve(S_pr, GT_hard)`; GT_soft (n_db, n_query) bool, the ground truth for
        `recall_at_k`, where a hit within ±t counts.
    """
    s = np.asarray(S, dtype=np.float64)
    gt = np.asarray(GT_hard).astype(bool)
    if s.shape != gt.shape:
        raise ValueError(f"S and GT shapes differ: {s.shape} vs {gt.shape}")
    soft = soft_ground_truth(gt, t)
    s_pr = s.copy()
    if s.size:
        s_pr[soft & ~gt] = s.min()
    return s_pr, soft


def place_ground_truth(places: np.ndarray) -> np.ndarray:
    """(T, T) bool, true where two steps are at the same (x, y) place (§8.4); aliased twins are false."""
    p = np.asarray(places)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"places must have shape (T, 2), got {p.shape}")
    _, labels = np.unique(p, axis=0, return_inverse=True)
    labels = labels.ravel()
    return labels[:, None] == labels[None, :]


def grid_evaluation(descriptors: Sequence[np.ndarray], places: np.ndarray, scoring: str,
                    similarity: np.ndarray | None = None) -> dict[str, Any]:
    """Score one method's grid-world descriptors against place identity (§8.4).

    `paper` reproduces [SIM] `run00.py` + `utils.py` exactly: the whole T x T matrix, S[i, j] = raw overlap
    count for j ≥ i and 1.0 for j < i; GT[i, j] = same place for j ≥ i (diagonal included), false below.
    `clean`: the strict upper triangle (i < j) as a flat list of pairs, S = Dice, GT = same place.
    recall@K (both scorings): online loop closure, query i against database {j < i} by Dice, over the
    queries with a same-place step among j < i.

    Args:
        descriptors: T SDRs (sorted index arrays), one per step: input SDRs, TM or MCN winner cells.
        places: (T, 2) place of each step.
        scoring: "paper" or "clean".
        similarity: (T, T) a method's own similarity (rows: older steps) replacing Dice, and the overlap
            count of `paper` scoring, whose lower triangle then takes the minimum instead of 1.0 (the
            quirk's effect: those pairs come last); -inf entries (no full sequence path) rank last too.

    Returns:
        {"scoring", "auc", "recall_at_1", "recall_at_5", "recall_at_100p", "P": list[float],
        "R": list[float], "S": (T, T) float64}; S is the matrix the PR curve was built from for `paper`,
        and the full symmetric Dice matrix (whose strict upper triangle is scored) for `clean`.
    """
    if scoring not in SCORINGS:
        raise ValueError(f"scoring must be one of {SCORINGS}, got {scoring!r}")
    T = len(descriptors)
    gt_place = place_ground_truth(places)
    if gt_place.shape[0] != T:
        raise ValueError(f"{T} descriptors but {gt_place.shape[0]} places")
    upper = np.triu(np.ones((T, T), dtype=bool))  # j >= i
    if similarity is None:
        dice = dice_matrix(descriptors)
    else:
        dice = np.asarray(similarity, dtype=np.float64)
        if dice.shape != (T, T):
            raise ValueError(f"similarity must have shape {(T, T)}, got {dice.shape}")
        finite = np.isfinite(dice)
        dice = np.where(finite, dice, dice[finite].min())

    if scoring == "paper" and similarity is not None:
        S = np.where(upper, dice, dice.min())
        P, R = pr_curve(S, gt_place & upper)
    elif scoring == "paper":
        # The paper's normaliser is len() of a 1-tuple, so scores are raw overlap counts, and its lower
        # triangle is left at the initial 1.0 (§8.4): kept as is to reproduce the published AUCs.
        S = np.where(upper, overlap_matrix(descriptors).astype(np.float64), 1.0)
        P, R = pr_curve(S, gt_place & upper)
    else:
        S = dice
        iu = np.triu_indices(T, k=1)
        P, R = pr_curve(S[iu], gt_place[iu])

    # Rows are the database (steps j), columns the queries (steps i); Dice is symmetric. Only older steps
    # j < i are eligible, as in online loop closure.
    valid = np.triu(np.ones((T, T), dtype=bool), k=1)
    r1 = recall_at_k(dice, gt_place, 1, valid=valid)
    r5 = recall_at_k(dice, gt_place, 5, valid=valid)
    return {
        "scoring": scoring,
        "auc": auc(P, R),
        "recall_at_1": r1,
        "recall_at_5": r5,
        "recall_at_100p": recall_at_100_precision(P, R),
        "P": P.tolist(),
        "R": R.tolist(),
        "S": S,
    }


# ---------------------------------------------------------------------------------------------------
# Per-query metrics (the standard VPR protocol, beside the paper's all-pairs AUC of §8.2): each query
# gives one answer, its best database item, with a confidence; precision and recall are counted over
# the answers accepted at a confidence threshold.


def best_matches(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each query's best database item and its similarity as the confidence.

    Args:
        S: (n_db, n_q) similarities, higher = more similar (-inf allowed: never the best unless all are).

    Returns:
        best (n_q,) int64 row index (ties: the lower row), confidence (n_q,) float64 = S[best, q].
    """
    s = np.asarray(S, dtype=np.float64)
    if s.ndim != 2 or s.shape[0] == 0:
        raise ValueError(f"S must be 2-D with at least one database row, got shape {s.shape}")
    best = np.argmax(s, axis=0)
    return best.astype(np.int64), s[best, np.arange(s.shape[1])]


def query_pr_curve(confidence: np.ndarray, correct: np.ndarray, has_positive: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Precision-recall of one answer per query over confidence thresholds.

    At threshold τ the answers with confidence >= τ are accepted; TP = accepted and correct, FP =
    accepted and wrong (an answer to a query without any positive is always wrong); P = TP / (TP + FP),
    R = TP / (queries with a positive). One threshold per distinct confidence, highest first, so tied
    answers are accepted together; (R = 0, P = 1) is prepended.

    Args:
        confidence: (n,) higher = more confident (finite).
        correct: (n,) bool, the answer is a positive.
        has_positive: (n,) bool, the query has at least one positive in the database.

    Returns:
        (P, R), each (distinct confidences + 1,) float64.

    Raises:
        ValueError: shapes differ, a confidence is not finite, or no query has a positive.
    """
    c = np.asarray(confidence, dtype=np.float64).ravel()
    ok = np.asarray(correct).astype(bool).ravel()
    pos = np.asarray(has_positive).astype(bool).ravel()
    if not c.shape == ok.shape == pos.shape:
        raise ValueError(f"shapes differ: {c.shape}, {ok.shape}, {pos.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("confidence contains NaN or infinite values")
    n_pos = int(np.count_nonzero(pos))
    if n_pos == 0:
        raise ValueError("no query has a positive: recall is undefined")
    order = np.argsort(-c, kind="stable")
    tp = np.cumsum(ok[order] & pos[order])
    accepted = np.arange(1, c.size + 1)
    # The last answer of each run of equal confidence closes that threshold.
    last = np.flatnonzero(np.append(np.diff(c[order]) != 0, True))
    P = np.concatenate(([1.0], tp[last] / accepted[last]))
    R = np.concatenate(([0.0], tp[last] / n_pos))
    return P, R


def query_metrics(S: np.ndarray, GT: np.ndarray, confidence: np.ndarray | None = None,
                  best: np.ndarray | None = None) -> dict[str, Any]:
    """Per-query metrics of one method: answers, PR curve, `query_auc`, R@1, R@5, R@100P.

    Args:
        S: (n_db, n_q) similarities (for R@5 and, by default, the answers).
        GT: (n_db, n_q) bool; with a tolerance pass the soft ground truth (a hit within ±t counts).
        confidence, best: (n_q,) a method's own answers and confidences (OpenSeqSLAM's match score;
            best -1 = no answer, counted wrong); default `best_matches(S)`.

    Returns:
        {"best", "confidence", "correct" (n_q,), "P", "R", "query_auc", "recall_at_1", "recall_at_5",
        "query_recall_at_100p"}; recall@K over the queries with a positive (§8.3).
    """
    gt = np.asarray(GT).astype(bool)
    if best is None or confidence is None:
        best, confidence = best_matches(S)
    cols = np.arange(gt.shape[1])
    best = np.asarray(best, dtype=np.int64)
    correct = (best >= 0) & gt[np.maximum(best, 0), cols]  # best -1: no answer (a warm-up), wrong
    has_pos = gt.any(axis=0)
    P, R = query_pr_curve(confidence, correct, has_pos)
    return {"best": best, "confidence": np.asarray(confidence, dtype=np.float64), "correct": correct,
            "P": P, "R": R, "query_auc": auc(P, R),
            "recall_at_1": float(np.count_nonzero(correct & has_pos)) / int(np.count_nonzero(has_pos)),
            "recall_at_5": recall_at_k(S, gt, 5), "query_recall_at_100p": recall_at_100_precision(P, R)}
