"""A map's sLSBH projection: dense or very sparse by the map's size budget, persisted by SHA-256
(docs/design/science.md §7, docs/design/service.md §1.1).

A map holds its projection and its Temporal Memory; together they stay within `MAP_MODEL_BYTES`. The
dense matrix is D × k float32 (AlexNet conv3: 64,896 × 1,024 = 266 MB); where it would break the
budget the map gets the very sparse projection (Li, Hastie & Church 2006; `slsbh.make_sparse_projection`,
at parity with the dense one in docs/results.md §6), about √D · k nonzeros (1.3 MB for AlexNet).

Both are stored content-addressed as `<projections>/<sha256>.npy` (the name snapshots and imports
already carry): the dense matrix as a `.npy` array, the sparse one as NumPy's `.npz` container of its
arrays (no pickle); `load` tells them apart by the file's own format and checks the SHA-256 either way.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import numpy as np

from models.files import atomic_write
from models.frontend import slsbh

__all__ = ["MAP_MODEL_BYTES", "Projection", "load", "make", "nbytes", "projection_kind", "save"]

#: Projection plus Temporal Memory bytes per map at most (issue 14).
MAP_MODEL_BYTES = 100_000_000

Projection = np.ndarray | slsbh.SparseProjection
Kind = Literal["dense", "sparse"]


def projection_kind(feature_dim: int, k: int, tm_bytes: int) -> Kind:
    """`dense` when D × k float32 plus the memory fit in MAP_MODEL_BYTES, else `sparse`."""
    return "dense" if feature_dim * k * 4 + tm_bytes <= MAP_MODEL_BYTES else "sparse"


def make(kind: Kind, feature_dim: int, k: int, seed: int) -> Projection:
    """The projection of a new map: (D, k) dense float32, or its very sparse counterpart."""
    if kind == "dense":
        return slsbh.make_projection(feature_dim, k, seed)
    return slsbh.make_sparse_projection(feature_dim, k, seed)


def nbytes(P: Projection) -> int:
    """Bytes the projection holds in memory."""
    if isinstance(P, slsbh.SparseProjection):
        return int(P.indptr.nbytes + P.indices.nbytes + P.signs.nbytes)
    return int(P.nbytes)


def save(P: Projection, directory: Path) -> tuple[Path, str]:
    """Store P as `<directory>/<sha256>.npy` (atomic; an existing file is verified, not rewritten)."""
    if not isinstance(P, slsbh.SparseProjection):
        return slsbh.save_projection(P, directory)
    sha = P.sha256()
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{sha}.npy"
    if path.exists():
        try:
            load(path, sha, shape=P.shape)
            return path, sha
        except slsbh.ProjectionError:
            pass  # a damaged file under that name: the right bytes are at hand, rewrite it
    arrays = {"d": np.array(P.d, np.int64), "k": np.array(P.k, np.int64), "indptr": P.indptr,
              "indices": P.indices, "signs": P.signs}
    atomic_write(path, lambda f: np.savez(f, **arrays))
    return path, sha


def load(path: str | os.PathLike[str], expected_sha256: str, *, shape: tuple[int, int] | None = None
         ) -> Projection:
    """The stored projection, refusing anything but the expected bytes.

    Raises:
        slsbh.ProjectionError: unreadable, another shape, or another checksum.
    """
    try:
        with open(path, "rb") as f:
            is_zip = f.read(4) == b"PK\x03\x04"
    except OSError as e:
        raise slsbh.ProjectionError(f"cannot read projection {path}: {e}") from e
    if not is_zip:
        return slsbh.load_projection(path, expected_sha256, shape=shape)
    try:
        with np.load(path, allow_pickle=False) as z:
            P = slsbh.SparseProjection(int(z["d"]), int(z["k"]), z["indptr"], z["indices"], z["signs"])
    except (OSError, ValueError, KeyError) as e:
        raise slsbh.ProjectionError(f"cannot read sparse projection {path}: {e}") from e
    if shape is not None and tuple(P.shape) != tuple(shape):
        raise slsbh.ProjectionError(f"{path}: shape {P.shape}, expected {tuple(shape)}")
    if P.sha256() != str(expected_sha256).lower():
        raise slsbh.ProjectionError(f"{path}: SHA-256 {P.sha256()} is not the map's {expected_sha256}")
    return P
