"""sLSBH: sparsified binary locality-sensitive hashing (docs/design/science.md §7).

A conv3 feature vector x (d = 64,896 floats, L2-normalised, §6) is projected to k values y = x·P and
turned into a 2k-bit code with exactly 2n ones: bits 0…k−1 mark the n largest entries of y, bits
k…2k−1 the n smallest ([MCN] RA-L 2019, [SIM] `run03.py` `getLSBH`, [NEOSLAM] `getLSBH.py`).
Codes are SDRs in the sense of `models.sdr`: sorted int32 indices of the ones.

The projection is part of the map (§7, DECISION): it is persisted as a `.npy` file named by the
SHA-256 of its raw little-endian C-order float32 bytes, and refused on load if the bytes differ.

Two projections:

* dense Gaussian (the default, §7.1): `make_projection`, (d, k) float32 with unit-norm columns;
* very sparse random projection (Li, Hastie & Church, KDD 2006), to MEASURE, not the default:
  `make_sparse_projection`, entries ±1 with density 1/√d before the same column normalisation,
  stored per column (CSR of Pᵀ) and applied by a compiled gather kernel (numba), deterministic.

Measured on the 2-core development CPU (numpy 2.4, torch 2.13, OpenBLAS, 2 threads, medians),
(N, 64,896) @ (64,896, 1024) float32: numpy 16.0 ms at N = 1, 23.4 ms at N = 16, 53.6 ms at N = 64;
torch 15.2, 34.4, 68.1 ms. The product is memory-bound (266 MB of P read per call), so numpy's BLAS
is used and torch input is converted to a NumPy view. The sparse projection (≈260k nonzeros) takes
0.20 ms for one row and 1.6–2.7 ms for 16 (0.25 ms and ≈0.15 ms per image including hashing), and at
s = 0.25 its codes preserve Dice as the dense ones do (within seed-to-seed spread).

Example:
    >>> P = make_projection(d=64896, k=1024, seed=0)            # (64896, 1024) float32
    >>> path, sha = save_projection(P, "maps/projections")     # content-addressed <sha>.npy
    >>> hasher = Hasher(load_projection(path, sha), s=0.25)
    >>> codes = hasher(features)                                # (N, 512) int32, sorted rows
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
import re
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit

from models.files import atomic_write
from models.sdr import INDEX_DTYPE

default_conf: dict[str, Any] = {"k": 1024, "s": 0.25, "seed": 0, "projection": "gaussian"}

D_CONV3 = 64_896  # 384×13×13 AlexNet conv3 values (docs/design/science.md §6)

# Rows per chunk when normalising, hashing or checking a projection: bounds the float64 scratch to
# 4096·k·8 bytes (32 MB at k = 1024) while keeping NumPy calls large.
_CHUNK_ROWS = 4096
# Rows of X per matmul in `Hasher.project`: bounds the float32 copy of a large torch/float64 input.
_BATCH_ROWS = 256

_SHA_RE = re.compile(r"^[0-9a-f]{64}$")
_LE_F4 = np.dtype("<f4")


class ProjectionError(ValueError):
    """A stored projection is not the one expected (checksum, dtype, shape or memory order)."""


# --------------------------------------------------------------------------------------------------
# Code size


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


# --------------------------------------------------------------------------------------------------
# Dense Gaussian projection


def make_projection(d: int = D_CONV3, k: int = 1024, seed: int = 0) -> np.ndarray:
    """Gaussian projection with unit-norm columns (docs/design/science.md §7.1).

    Draw order: one call `Generator(PCG64(seed)).standard_normal((d, k), dtype=float32)`, which fills
    P in C order (row 0 first); drawing row chunks in sequence into the same array gives identical
    bits. Column norms are accumulated in float64 over row chunks of 4096 in row order, and every entry
    is then `float32(float64(p) / norm64)`, correctly rounded, so the result depends only on the
    generator's stream. That stream is not guaranteed across NumPy versions (NEP 19), which is why the
    matrix is persisted and identified by `projection_sha256`, never regenerated from the seed.

    Peak memory is P itself (253.5 MiB at d = 64,896, k = 1024) plus one 32 MiB float64 chunk;
    drawing in row chunks would give the same bits but cannot lower that peak, since P is the result.
    About 1.7 s on the development CPU (1.4 s drawing, 0.3 s normalising).

    Args:
        d: input dimension (64,896 for AlexNet conv3).
        k: projected dimension.
        seed: PCG64 seed.

    Returns:
        P: (d, k) float32, C-contiguous, each column of unit L2 norm.

    Raises:
        ValueError: d or k < 1 (or, with vanishing probability, a zero column).
    """
    if d < 1 or k < 1:
        raise ValueError(f"d and k must be positive, got d={d}, k={k}")
    rng = np.random.Generator(np.random.PCG64(seed))
    P = rng.standard_normal((d, k), dtype=np.float32)
    # One reused float64 buffer: a fresh astype per chunk would hold two chunks at the reassignment.
    buf = np.empty((min(_CHUNK_ROWS, d), k), dtype=np.float64)
    sq = np.zeros(k, dtype=np.float64)
    for i in range(0, d, _CHUNK_ROWS):
        c = buf[: min(_CHUNK_ROWS, d - i)]
        np.copyto(c, P[i : i + _CHUNK_ROWS])
        sq += np.einsum("ij,ij->j", c, c)
    if not np.all(sq > 0):
        raise ValueError("projection has a zero column; use another seed")
    norm = np.sqrt(sq)
    for i in range(0, d, _CHUNK_ROWS):
        c = buf[: min(_CHUNK_ROWS, d - i)]
        np.copyto(c, P[i : i + _CHUNK_ROWS])
        c /= norm
        P[i : i + _CHUNK_ROWS] = c  # float64 → float32 rounds to nearest
    return P


def projection_sha256(P: np.ndarray) -> str:
    """SHA-256 of a dense projection's raw little-endian C-order float32 bytes (docs/design/science.md §7).

    The shape is not hashed (the spec identifies the bytes); `load_projection` checks it separately.

    Args:
        P: (d, k) float32 array, any memory order or byte order.

    Returns:
        64 lowercase hex digits.

    Raises:
        ProjectionError: P is not a 2-D float32 array.
    """
    _check_dense_dtype(P)
    h = hashlib.sha256()
    for i in range(0, P.shape[0], _CHUNK_ROWS):
        # No copy when P is already little-endian C-contiguous (the common case).
        h.update(np.ascontiguousarray(P[i : i + _CHUNK_ROWS], dtype=_LE_F4).data)
    return h.hexdigest()


def save_projection(P: np.ndarray, directory: str | os.PathLike[str]) -> tuple[Path, str]:
    """Store P content-addressed as `<directory>/<sha256>.npy` (docs/design/science.md §7, DECISION).

    Written atomically: a temporary file in the same directory, fsync, `os.replace`, then an fsync of
    the directory, so a reader never sees a partial file under the final name. If the file already
    exists it is verified, not rewritten (maps with the same checksum share it); a corrupt file under
    that name is replaced with a warning, since the correct bytes are at hand.

    Args:
        P: (d, k) float32 projection.
        directory: created if missing.

    Returns:
        (path, sha256).

    Raises:
        ProjectionError: P is not a 2-D float32 array.
    """
    _check_dense_dtype(P)
    sha = projection_sha256(P)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{sha}.npy"
    if path.exists():
        try:
            load_projection(path, sha, shape=P.shape)
            return path, sha
        except ProjectionError as exc:
            warnings.warn(f"replacing corrupt projection file {path}: {exc}", RuntimeWarning, stacklevel=2)
    arr = np.ascontiguousarray(P, dtype=_LE_F4)
    atomic_write(path, lambda f: np.lib.format.write_array(f, arr, version=(1, 0), allow_pickle=False))
    return path, sha


def load_projection(
    path: str | os.PathLike[str],
    expected_sha256: str,
    *,
    shape: tuple[int, int] | None = None,
    mmap: bool = True,
) -> np.ndarray:
    """Load a stored projection and refuse anything but the expected bytes (docs/design/science.md §7).

    Args:
        path: a `.npy` file written by `save_projection`.
        expected_sha256: the checksum recorded in the map.
        shape: expected (d, k), checked when given.
        mmap: map the file read-only instead of reading it: processes serving maps with the same
            projection share its pages, and nothing is copied. The whole file is still read once to
            verify the checksum.

    Returns:
        P: (d, k) float32, C-contiguous (a read-only `np.memmap` when `mmap`).

    Raises:
        ProjectionError: unreadable file, not little-endian float32, not 2-D, Fortran order, wrong
            shape, or checksum mismatch.
    """
    expected = str(expected_sha256).lower()
    if not _SHA_RE.match(expected):
        raise ProjectionError(f"expected_sha256 must be 64 hex digits, got {expected_sha256!r}")
    try:
        P = np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise ProjectionError(f"cannot read projection {path}: {exc}") from exc
    if P.dtype != _LE_F4:
        raise ProjectionError(f"{path}: dtype {P.dtype.str}, expected <f4")
    if P.ndim != 2:
        raise ProjectionError(f"{path}: {P.ndim}-D array, expected 2-D (d, k)")
    if not P.flags.c_contiguous:
        raise ProjectionError(f"{path}: not C-ordered")
    if shape is not None and tuple(P.shape) != tuple(shape):
        raise ProjectionError(f"{path}: shape {P.shape}, expected {tuple(shape)}")
    actual = projection_sha256(P)
    if actual != expected:
        raise ProjectionError(f"{path}: SHA-256 {actual} does not match the map's {expected}")
    return P


def _check_dense_dtype(P: np.ndarray) -> None:
    if not isinstance(P, np.ndarray) or P.ndim != 2 or P.dtype.kind != "f" or P.dtype.itemsize != 4:
        desc = f"{type(P).__name__} {getattr(P, 'dtype', '?')} {getattr(P, 'shape', '?')}"
        raise ProjectionError(f"projection must be a 2-D float32 array, got {desc}")


# --------------------------------------------------------------------------------------------------
# Very sparse projection (MEASURE; not the default)


@dataclass(frozen=True, eq=False)
class SparseProjection:
    """Very sparse random projection stored per output column (CSR of Pᵀ).

    Column j of P is nonzero at rows `indices[indptr[j]:indptr[j+1]]` (sorted ascending) with signs
    `signs[...]` ∈ {−1, +1}; its value there is sign / √m_j with m_j the column's nonzero count, so
    every column has unit L2 norm, as in §7.1. Li et al.'s scale (√ of their sparsity parameter)
    cancels in the normalisation and is not stored.

    Attributes:
        d: input dimension (rows of P).
        k: projected dimension (columns of P).
        indptr: (k + 1,) int64, indptr[0] = 0, strictly increasing (no empty column).
        indices: (nnz,) int32 row indices.
        signs: (nnz,) int8, ±1.
    """

    d: int
    k: int
    indptr: np.ndarray
    indices: np.ndarray
    signs: np.ndarray

    def __post_init__(self) -> None:
        ip, ix, sg = self.indptr, self.indices, self.signs
        if ip.dtype != np.int64 or ip.shape != (self.k + 1,) or ip[0] != 0 or np.any(np.diff(ip) < 1):
            raise ProjectionError("indptr must be (k + 1,) int64 from 0, every column non-empty")
        if ix.dtype != np.int32 or sg.dtype != np.int8 or ix.shape != sg.shape or ix.size != ip[-1]:
            raise ProjectionError("indices (int32) and signs (int8) must both have indptr[-1] entries")
        if ix.size and (ix.min() < 0 or ix.max() >= self.d):
            raise ProjectionError("row index out of range")
        if not np.all(np.abs(sg) == 1):
            raise ProjectionError("signs must be ±1")

    @property
    def nnz(self) -> int:
        """Number of nonzero entries."""
        return int(self.indptr[-1])

    @property
    def density(self) -> float:
        """Fraction of nonzero entries of the (d, k) matrix."""
        return self.nnz / (self.d * self.k)

    @property
    def shape(self) -> tuple[int, int]:
        """(d, k), as for a dense projection."""
        return (self.d, self.k)

    @functools.cached_property
    def values(self) -> np.ndarray:
        """(nnz,) float32 entries: sign / √m_j, each correctly rounded from float64."""
        counts = np.diff(self.indptr).astype(np.float64)
        scale = np.repeat(1.0 / np.sqrt(counts), np.diff(self.indptr))
        return (self.signs * scale).astype(np.float32)

    def sha256(self) -> str:
        """SHA-256 over the canonical arrays, the sparse counterpart of `projection_sha256`.

        Hashed in order: the ASCII tag `slsbh-sparse-v1`, d and k as little-endian int64, indptr as
        little-endian int64, indices as little-endian int32, signs as int8. The float values are a
        function of these and are not hashed.
        """
        h = hashlib.sha256(b"slsbh-sparse-v1")
        h.update(np.array([self.d, self.k], dtype="<i8").tobytes())
        h.update(np.ascontiguousarray(self.indptr, dtype="<i8").data)
        h.update(np.ascontiguousarray(self.indices, dtype="<i4").data)
        h.update(np.ascontiguousarray(self.signs, dtype="i1").data)
        return h.hexdigest()

    def to_dense(self) -> np.ndarray:
        """(d, k) float32 dense equivalent (tests and small d only)."""
        P = np.zeros((self.d, self.k), dtype=np.float32)
        cols = np.repeat(np.arange(self.k), np.diff(self.indptr))
        P[self.indices, cols] = self.values
        return P

    def matmul(self, X: np.ndarray) -> np.ndarray:
        """X·P, nnz multiply-adds per row instead of d·k.

        Y[r, j] is the float32 sum over the column's entries in storage order, computed sequentially
        without reassociation, so the result is bit-identical whatever the batch size, kernel or
        thread count (unlike a BLAS product).

        Args:
            X: (N, d) float32.

        Returns:
            Y: (N, k) float32.
        """
        X = np.ascontiguousarray(X, dtype=np.float32)
        if X.shape[0] < _SPARSE_TRANSPOSE_MIN_ROWS:
            return _sparse_rows(X, self.indptr, self.indices, self.values)
        # With several rows, gathering whole rows of Xᵀ (N contiguous floats) per entry lets the inner
        # loop vectorise over the batch: 2.5 ms instead of 6.3 ms for 16 rows at the real size.
        return _sparse_batch(np.ascontiguousarray(X.T), self.indptr, self.indices, self.values).T


# Below this many rows the per-row kernel wins (0.3 ms per row against 0.9 ms for one row through the
# batch kernel at the real size).
_SPARSE_TRANSPOSE_MIN_ROWS = 4


@njit(cache=True)
def _sparse_rows(X, indptr, indices, values):  # pragma: no cover - compiled
    N, k = X.shape[0], indptr.shape[0] - 1
    Y = np.empty((N, k), np.float32)
    for r in range(N):
        for j in range(k):
            acc = np.float32(0.0)
            for q in range(indptr[j], indptr[j + 1]):
                acc += X[r, indices[q]] * values[q]
            Y[r, j] = acc
    return Y


@njit(cache=True)
def _sparse_batch(XT, indptr, indices, values):  # pragma: no cover - compiled
    N, k = XT.shape[1], indptr.shape[0] - 1
    Y = np.zeros((k, N), np.float32)
    for j in range(k):
        acc = Y[j]
        for q in range(indptr[j], indptr[j + 1]):
            v = values[q]
            row = XT[indices[q]]
            for r in range(N):
                acc[r] += row[r] * v
    return Y


def make_sparse_projection(
    d: int = D_CONV3, k: int = 1024, seed: int = 0, density: float | None = None
) -> SparseProjection:
    """Very sparse random projection (Li, Hastie & Church 2006), columns normalised as in §7.1.

    Each entry is nonzero with probability `density` (default 1/√d, i.e. their s = √d), independently,
    with an equiprobable sign. Draw order from `Generator(PCG64(seed))`: for each column j in
    order, m_j = binomial(d, density), then the m_j rows as `choice(d, m_j, replace=False)` (sorted
    afterwards); after all columns, one `integers(0, 2, nnz)` call gives the signs (0 → −1, 1 → +1)
    in storage order. A binomial count and a uniform subset is the same law as i.i.d. Bernoulli
    entries, at O(nnz) cost instead of O(d·k).

    Args:
        d: input dimension.
        k: projected dimension.
        seed: PCG64 seed.
        density: fraction of nonzero entries, 0 < density ≤ 1; 1/√d when None.

    Returns:
        The projection; `.sha256()` identifies it.

    Raises:
        ValueError: bad d, k or density, or an empty column (probability k·e^(−√d) by default, about
            1e-108 at the real size; a different seed fixes it).
    """
    if d < 1 or k < 1:
        raise ValueError(f"d and k must be positive, got d={d}, k={k}")
    density = 1.0 / math.sqrt(d) if density is None else float(density)
    if not (math.isfinite(density) and 0.0 < density <= 1.0):
        raise ValueError(f"density must satisfy 0 < density <= 1, got {density!r}")
    rng = np.random.Generator(np.random.PCG64(seed))
    cols: list[np.ndarray] = []
    counts = np.empty(k, dtype=np.int64)
    for j in range(k):
        m = int(rng.binomial(d, density))
        if m == 0:
            raise ValueError(f"sparse projection column {j} is empty; use another seed or a higher density")
        cols.append(np.sort(rng.choice(d, m, replace=False)).astype(np.int32))
        counts[j] = m
    indptr = np.zeros(k + 1, dtype=np.int64)
    np.cumsum(counts, out=indptr[1:])
    indices = np.concatenate(cols)
    signs = (rng.integers(0, 2, size=indices.size, dtype=np.int8) * 2 - 1).astype(np.int8)
    return SparseProjection(d=d, k=k, indptr=indptr, indices=indices, signs=signs)


# --------------------------------------------------------------------------------------------------
# Hashing


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
