"""SDR helpers.

An SDR is a sorted 1-D array of distinct non-negative indices (its "ones"). Dense binary vectors are
accepted at the edges and converted once. Dice(a, b) = 2·|a ∩ b| / (|a| + |b|) is the paper's
"normalised overlap" (docs/design/science.md, notation).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from storage.base.dtypes import INDEX_DTYPE  # one home, shared with the store (storage/base/dtypes.py)


def from_dense(dense: np.ndarray) -> np.ndarray:
    """Indices of the ones of a dense binary vector.

    Args:
        dense: (width,) array, nonzero = one.

    Returns:
        (w,) int32, sorted ascending.
    """
    return np.flatnonzero(np.asarray(dense)).astype(INDEX_DTYPE)


def to_dense(sdr: np.ndarray, width: int) -> np.ndarray:
    """Dense (width,) uint8 vector with ones at `sdr`."""
    out = np.zeros(width, dtype=np.uint8)
    out[np.asarray(sdr, dtype=np.int64)] = 1
    return out


def overlap(a: np.ndarray, b: np.ndarray) -> int:
    """|a ∩ b| of two sorted SDRs."""
    return int(np.intersect1d(a, b, assume_unique=True).size)


def dice(a: np.ndarray, b: np.ndarray) -> float:
    """2·overlap / (|a| + |b|); 0 when both are empty."""
    total = len(a) + len(b)
    return 0.0 if total == 0 else 2.0 * overlap(a, b) / total


def _incidence(sdrs: Sequence[np.ndarray]) -> np.ndarray:
    """(n, u) float32 incidence matrix over the u distinct indices used by any SDR.

    Compressing to the used indices keeps the matrix small even when the index space is large
    (65,536 TM cells, or an MCN's unbounded column count).
    """
    lengths = np.fromiter((len(s) for s in sdrs), dtype=np.int64, count=len(sdrs))
    parts = [np.asarray(s, dtype=np.int64) for s in sdrs]
    flat = np.concatenate(parts) if parts else np.zeros(0, np.int64)
    used, inverse = np.unique(flat, return_inverse=True)
    rows = np.repeat(np.arange(len(sdrs)), lengths)
    m = np.zeros((len(sdrs), max(len(used), 1)), dtype=np.float32)
    m[rows, inverse] = 1.0
    return m


def overlap_matrix(rows: Sequence[np.ndarray], cols: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """Pairwise overlap counts.

    Args:
        rows: n SDRs (database).
        cols: m SDRs (queries); `rows` when omitted.

    Returns:
        O: (n, m) int64, O[i, j] = |rows[i] ∩ cols[j]|.
    """
    cols = rows if cols is None else cols
    m = _incidence(list(rows) + list(cols))
    a, b = m[: len(rows)], m[len(rows) :]
    # float32 matmul is exact for integer counts below 2**24.
    return np.rint(a @ b.T).astype(np.int64)


def dice_matrix(rows: Sequence[np.ndarray], cols: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """Pairwise Dice similarity.

    Returns:
        S: (n, m) float64 in [0, 1], higher = more similar; 0 where both SDRs are empty.
    """
    cols = rows if cols is None else cols
    o = overlap_matrix(rows, cols).astype(np.float64)
    wr = np.fromiter((len(s) for s in rows), dtype=np.float64, count=len(rows))
    wc = np.fromiter((len(s) for s in cols), dtype=np.float64, count=len(cols))
    denom = wr[:, None] + wc[None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(denom > 0, 2.0 * o / np.where(denom > 0, denom, 1.0), 0.0)
    return s
