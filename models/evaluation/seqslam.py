"""SeqSLAM-style sequence filter over a pairwise similarity matrix (science.md §5, "seqslam").

The strong non-neural reference: any gain a sequence memory shows must beat what this plain filter
gets from the same single-image similarities (Milford & Wyeth, ICRA 2012, as restated in
stschubert/VPR_Tutorial): contrast-normalise the difference matrix per query, then score every
(database i, query j) by the best straight line through the normalised differences over a window of
queries ending at j.
"""

from __future__ import annotations

import numpy as np


def contrast_normalise(D: np.ndarray, radius: int = 10) -> np.ndarray:
    """Local contrast normalisation of a difference matrix along the database axis.

    Args:
        D: (n_db, n_q) differences, lower = more similar.
        radius: half-width of the database window used for the local mean and std.

    Returns:
        (n_db, n_q) float64: (D - local mean) / local std, per query column.
    """
    D = np.asarray(D, dtype=np.float64)
    n = D.shape[0]
    # Cumulative sums give every window's mean and variance in O(n_db * n_q).
    c1 = np.vstack([np.zeros((1, D.shape[1])), np.cumsum(D, axis=0)])
    c2 = np.vstack([np.zeros((1, D.shape[1])), np.cumsum(D * D, axis=0)])
    lo = np.clip(np.arange(n) - radius, 0, n)
    hi = np.clip(np.arange(n) + radius + 1, 0, n)
    count = (hi - lo)[:, None]
    mean = (c1[hi] - c1[lo]) / count
    var = np.maximum((c2[hi] - c2[lo]) / count - mean * mean, 0.0)
    return (D - mean) / (np.sqrt(var) + 1e-9)


def seqslam(S: np.ndarray, window: int = 10, velocities: tuple[float, ...] = (0.8, 0.9, 1.0, 1.1, 1.25),
            radius: int = 10) -> np.ndarray:
    """Sequence-filtered similarity.

    Args:
        S: (n_db, n_q) pairwise similarity, higher = more similar (e.g. cosine of features).
        window: number of consecutive queries in a path (ending at the scored query).
        velocities: database steps per query step that a path may take.
        radius: contrast-normalisation half-window (database frames).

    Returns:
        (n_db, n_q) similarity, higher = more similar: minus the mean normalised difference along
        the best path. Queries with fewer than `window` predecessors use the ones they have.
    """
    S = np.asarray(S, dtype=np.float64)
    Dn = contrast_normalise(-S, radius)
    n_db, n_q = Dn.shape
    best = np.full((n_db, n_q), np.inf)
    rows = np.arange(n_db)
    for v in velocities:
        total = np.zeros((n_db, n_q))
        count = np.zeros((n_db, n_q))
        for k in range(min(window, n_q)):
            # Query j - k pairs with database i - round(v * k): a straight line ending at (i, j).
            src_rows = rows - round(v * k)
            valid_rows = src_rows >= 0
            block = np.zeros((n_db, n_q))
            ok = np.zeros((n_db, n_q), dtype=bool)
            block[valid_rows, k:] = Dn[src_rows[valid_rows], : n_q - k]
            ok[valid_rows, k:] = True
            total += block
            count += ok
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(count > 0, total / np.maximum(count, 1), np.inf)
        best = np.minimum(best, mean)
    return -best
