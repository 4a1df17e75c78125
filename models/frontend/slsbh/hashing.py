"""sLSBH hashing (docs/design/science.md §7.3, §7.4): projected values (N, k) -> codes (N, 2n), the n
largest and the n smallest entries of each row; `Hasher` = projection + hashing."""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np

from models.frontend.slsbh.projection import SparseProjection, _check_dense_dtype, projection_sha256
from models.sdr import INDEX_DTYPE

# Rows of X per matmul in `Hasher.project`: bounds the float32 copy of a large torch/float64 input.
_BATCH_ROWS = 256


def n_ones(k: int, s: float) -> int:
    """Ones per half of an sLSBH code: n = floor(s·k + 0.5) (docs/design/science.md §7.3).

    Args:
        k: projected dimension (≥ 1).
        s: sparsity, 0 < s ≤ 0.5.

    Returns:
        n ≥ 1; the code has 2n ones out of 2k bits.

    Raises:
        ValueError: k < 1, s outside (0, 0.5], or s so small that n = 0 (an empty code has no Dice).
    """
    if isinstance(k, bool) or int(k) != k or k < 1:
        raise ValueError(f"k must be a positive integer, got {k!r}")
    s = float(s)
    if not (math.isfinite(s) and 0.0 < s <= 0.5):
        raise ValueError(f"s must satisfy 0 < s <= 0.5, got {s!r}")
    n = math.floor(s * int(k) + 0.5)
    if n < 1:
        raise ValueError(f"s={s} gives n=0 ones for k={k}; use s >= {0.5 / k:.3g}")
    return n


def hash_projected(Y: np.ndarray, s: float) -> np.ndarray:
    """sLSBH codes of projected values (docs/design/science.md §7.3–7.4).

    Bits 0…k−1: ones at the n largest entries of each row; bits k…2k−1: ones at k + j for the n
    smallest entries j. Ties are ordered by value, then by lower index (a stable order), in both
    halves: among equal values at a boundary the lower indices win.

    Fully vectorised and O(N·k): `np.partition` finds each row's boundary value t, every entry
    strictly beyond t is taken, and the remaining places go to the entries equal to t in index
    order (a running count along the row). No per-row sort.

    Args:
        Y: (N, k) projected values (float32 normally; compared in their own dtype). Must be finite.
        s: sparsity, n = floor(s·k + 0.5) (see `n_ones`).

    Returns:
        codes: (N, 2n) int32, each row sorted ascending, n indices in [0, k) then n in [k, 2k).

    Raises:
        ValueError: Y not 2-D, not finite, or s out of range.
    """
    Y = np.asarray(Y)
    if Y.ndim != 2:
        raise ValueError(f"Y must be (N, k), got shape {Y.shape}")
    N, k = Y.shape
    n = n_ones(k, s)
    if N == 0:
        return np.zeros((0, 2 * n), dtype=INDEX_DTYPE)
    if not np.all(np.isfinite(Y)):
        raise ValueError("Y contains NaN or infinity")
    top = _select(Y, n, largest=True)
    bottom = _select(Y, n, largest=False)
    out = np.empty((N, 2 * n), dtype=INDEX_DTYPE)
    out[:, :n] = top
    out[:, n:] = bottom + k
    return out


def _select(Y: np.ndarray, n: int, largest: bool) -> np.ndarray:
    """(N, n) int32 sorted column indices of the n largest (smallest) entries per row, ties → lower index."""
    N, k = Y.shape
    if largest:
        # n-th largest = element at position k − n of the ascending order.
        t = np.partition(Y, k - n, axis=1)[:, k - n : k - n + 1]
        beyond = np.greater(Y, t)
    else:
        t = np.partition(Y, n - 1, axis=1)[:, n - 1 : n]
        beyond = np.less(Y, t)
    equal = np.equal(Y, t)
    # Places left for boundary ties (≥ 1 since t itself is among the n), filled left to right.
    need = n - beyond.sum(axis=1, keepdims=True)
    chosen = beyond | (equal & (np.cumsum(equal, axis=1) <= need))
    # Exactly n per row, and nonzero() walks rows in order and columns ascending: reshape is exact.
    return np.nonzero(chosen)[1].astype(INDEX_DTYPE).reshape(N, n)


Projection = np.ndarray | SparseProjection


class Hasher:
    """x ↦ sLSBH code: project with P, then `hash_projected` (docs/design/science.md §7).

    Args:
        P: (d, k) float32 dense projection (may be a read-only memmap from `load_projection`) or a
            `SparseProjection`.
        s: sparsity, 0 < s ≤ 0.5.

    Attributes:
        d, k: projection shape.
        s, n: sparsity and ones per half; codes have 2n ones out of `width` = 2k bits.
    """

    def __init__(self, P: Projection, s: float) -> None:
        if isinstance(P, SparseProjection):
            self.P: Projection = P
        else:
            _check_dense_dtype(P)
            # The BLAS wants native-endian C order; a memmap from load_projection already is one.
            native = P.dtype == np.float32 and P.flags.c_contiguous
            self.P = P if native else np.ascontiguousarray(P, np.float32)
        self.d, self.k = (int(v) for v in self.P.shape)
        self.s = float(s)
        self.n = n_ones(self.k, self.s)

    @property
    def width(self) -> int:
        """Bits of a code (2k)."""
        return 2 * self.k

    @property
    def sparse(self) -> bool:
        """True for a `SparseProjection`."""
        return isinstance(self.P, SparseProjection)

    def sha256(self) -> str:
        """Checksum of the projection (`projection_sha256` or `SparseProjection.sha256`)."""
        return self.P.sha256() if isinstance(self.P, SparseProjection) else projection_sha256(self.P)

    def project(self, X: Any) -> np.ndarray:
        """y = x·P for a batch, in float32.

        Args:
            X: (N, d) or (d,) numpy array or torch tensor (any float dtype; any device).

        Returns:
            Y: (N, k) float32, or (k,) for a 1-D input.
        """
        X2, one = self._as_rows(X)
        Y = np.empty((X2.shape[0], self.k), dtype=np.float32)
        for i in range(0, X2.shape[0], _BATCH_ROWS):
            xb = np.ascontiguousarray(X2[i : i + _BATCH_ROWS], dtype=np.float32)
            Y[i : i + _BATCH_ROWS] = xb @ self.P if not self.sparse else self.P.matmul(xb)
        return Y[0] if one else Y

    def __call__(self, X: Any) -> np.ndarray:
        """sLSBH codes of a batch.

        Args:
            X: (N, d) or (d,) features, numpy or torch, normally L2-normalised (§6).

        Returns:
            codes: (N, 2n) int32 sorted rows, or (2n,) for a 1-D input.
        """
        X2, one = self._as_rows(X)
        codes = hash_projected(self.project(X2), self.s)
        return codes[0] if one else codes

    def _as_rows(self, X: Any) -> tuple[np.ndarray, bool]:
        torch = sys.modules.get("torch")  # a tensor can only exist if torch is already imported
        if torch is not None and isinstance(X, torch.Tensor):
            X = X.detach().to(device="cpu", dtype=torch.float32).numpy()
        X = np.asarray(X)
        one = X.ndim == 1
        X2 = X[None, :] if one else X
        if X2.ndim != 2 or X2.shape[1] != self.d:
            raise ValueError(f"X must be (N, {self.d}) or ({self.d},), got shape {X.shape}")
        return X2, one
