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

Modules: `projection` (dense and sparse P, persistence by SHA-256) and `hashing` (`hash_projected`,
`Hasher`); import from this package.

Example:
    >>> P = make_projection(d=64896, k=1024, seed=0)            # (64896, 1024) float32
    >>> path, sha = save_projection(P, "maps/projections")     # content-addressed <sha>.npy
    >>> hasher = Hasher(load_projection(path, sha), s=0.25)
    >>> codes = hasher(features)                                # (N, 512) int32, sorted rows
"""

from models.frontend.slsbh.hashing import Hasher, Projection, hash_projected, n_ones
from models.frontend.slsbh.projection import (
    D_CONV3,
    ProjectionError,
    SparseProjection,
    load_projection,
    make_projection,
    make_sparse_projection,
    projection_sha256,
    save_projection,
)

__all__ = [
    "D_CONV3",
    "Hasher",
    "Projection",
    "ProjectionError",
    "SparseProjection",
    "hash_projected",
    "load_projection",
    "make_projection",
    "make_sparse_projection",
    "n_ones",
    "projection_sha256",
    "save_projection",
]
