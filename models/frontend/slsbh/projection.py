"""sLSBH projections P, (d, k) float32 with unit-norm columns (docs/design/science.md §7.1, §7.2):
dense Gaussian (`make_projection`) or very sparse ±1 (`SparseProjection`, `make_sparse_projection`),
content-addressed by the SHA-256 of their bytes (`projection_sha256`, `save_projection`,
`load_projection`)."""

from __future__ import annotations

import functools
import hashlib
import math
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit

from models import presets
from storage.base.files import atomic_write

D_CONV3 = 64_896  # 384×13×13 AlexNet conv3 values (docs/design/science.md §6)

# Rows per chunk when normalising, hashing or checking a projection: bounds the float64 scratch to
# 4096·k·8 bytes (32 MB at k = 1024) while keeping NumPy calls large.
_CHUNK_ROWS = 4096

_SHA_RE = re.compile(r"^[0-9a-f]{64}$")
_LE_F4 = np.dtype("<f4")


class ProjectionError(ValueError):
    """A stored projection is not the one expected (checksum, dtype, shape or memory order)."""


# --------------------------------------------------------------------------------------------------
# Dense Gaussian projection


def make_projection(d: int = D_CONV3, k: int | None = None, seed: int = 0) -> np.ndarray:
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
        k: projected dimension; None: the sLSBH default (`presets.SlsbhParams`).
        seed: PCG64 seed.

    Returns:
        P: (d, k) float32, C-contiguous, each column of unit L2 norm.

    Raises:
        ValueError: d or k < 1 (or, with vanishing probability, a zero column).
    """
    k = presets.SlsbhParams().k if k is None else k
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


def save_projection(P: np.ndarray | SparseProjection, directory: str | os.PathLike[str]) -> tuple[Path, str]:
    """Store P content-addressed as `<directory>/<sha256>.npy` (docs/design/science.md §7, DECISION): a
    dense matrix as a `.npy` array, a `SparseProjection` as NumPy's `.npz` container of its arrays (no
    pickle), under the same name, so snapshots and imports carry either unchanged.

    Written atomically: a temporary file in the same directory, fsync, `os.replace`, then an fsync of
    the directory, so a reader never sees a partial file under the final name. If the file already
    exists it is verified, not rewritten (maps with the same checksum share it); a corrupt file under
    that name is replaced with a warning, since the correct bytes are at hand.

    Args:
        P: (d, k) float32 projection, or its very sparse counterpart.
        directory: created if missing.

    Returns:
        (path, sha256).

    Raises:
        ProjectionError: P is not a 2-D float32 array.
    """
    sparse = isinstance(P, SparseProjection)
    if not sparse:
        _check_dense_dtype(P)
    sha = P.sha256() if sparse else projection_sha256(P)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{sha}.npy"
    if path.exists():
        try:
            load_projection(path, sha, shape=P.shape)
            return path, sha
        except ProjectionError as exc:
            warnings.warn(f"replacing corrupt projection file {path}: {exc}", RuntimeWarning, stacklevel=2)
    if sparse:
        arrays = {"d": np.array(P.d, np.int64), "k": np.array(P.k, np.int64), "indptr": P.indptr,
                  "indices": P.indices, "signs": P.signs}
        atomic_write(path, lambda f: np.savez(f, **arrays))
        return path, sha
    arr = np.ascontiguousarray(P, dtype=_LE_F4)
    atomic_write(path, lambda f: np.lib.format.write_array(f, arr, version=(1, 0), allow_pickle=False))
    return path, sha


def load_projection(
    path: str | os.PathLike[str],
    expected_sha256: str,
    *,
    shape: tuple[int, int] | None = None,
    mmap: bool = True,
) -> np.ndarray | SparseProjection:
    """Load a stored projection and refuse anything but the expected bytes (docs/design/science.md §7).

    Args:
        path: a file written by `save_projection` (a dense `.npy` or a sparse `.npz`, told apart by
            the file's own format).
        expected_sha256: the checksum recorded in the map.
        shape: expected (d, k), checked when given.
        mmap: map the file read-only instead of reading it: processes serving maps with the same
            projection share its pages, and nothing is copied. The whole file is still read once to
            verify the checksum.

    Returns:
        P: (d, k) float32, C-contiguous (a read-only `np.memmap` when `mmap`), or a `SparseProjection`.

    Raises:
        ProjectionError: unreadable file, not little-endian float32, not 2-D, Fortran order, wrong
            shape, or checksum mismatch.
    """
    expected = str(expected_sha256).lower()
    if not _SHA_RE.fullmatch(expected):
        raise ProjectionError(f"expected_sha256 must be 64 hex digits, got {expected_sha256!r}")
    try:
        with open(path, "rb") as f:
            is_zip = f.read(4) == b"PK\x03\x04"
        if is_zip:
            with np.load(path, allow_pickle=False) as z:
                S = SparseProjection(int(z["d"]), int(z["k"]), z["indptr"], z["indices"], z["signs"])
        else:
            P = np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (OSError, ValueError, EOFError, KeyError) as exc:
        raise ProjectionError(f"cannot read projection {path}: {exc}") from exc
    if is_zip:
        if shape is not None and tuple(S.shape) != tuple(shape):
            raise ProjectionError(f"{path}: shape {S.shape}, expected {tuple(shape)}")
        if S.sha256() != expected:
            raise ProjectionError(f"{path}: SHA-256 {S.sha256()} does not match the map's {expected}")
        return S
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
    d: int = D_CONV3, k: int | None = None, seed: int = 0, density: float | None = None
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
        k: projected dimension; None: the sLSBH default (`presets.SlsbhParams`).
        seed: PCG64 seed.
        density: fraction of nonzero entries, 0 < density ≤ 1; 1/√d when None.

    Returns:
        The projection; `.sha256()` identifies it.

    Raises:
        ValueError: bad d, k or density, or an empty column (probability k·e^(−√d) by default, about
            1e-108 at the real size; a different seed fixes it).
    """
    k = presets.SlsbhParams().k if k is None else k
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
