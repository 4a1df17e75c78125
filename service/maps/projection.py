"""A map's sLSBH projection: dense or very sparse by the map's size budget, persisted by SHA-256
(docs/design/science.md §7, docs/design/service.md §1.1).

A map holds its projection and its Temporal Memory; together they stay within `MAP_MODEL_BYTES`. The
dense matrix is D × k float32 (AlexNet conv3: 64,896 × 1,024 = 266 MB); where it would break the
budget the map gets the very sparse projection (Li, Hastie & Church 2006; `slsbh.make_sparse_projection`,
at parity with the dense one in docs/results.md §6), about √D · k nonzeros (1.3 MB for AlexNet).

Both are stored content-addressed by `slsbh.save_projection` and read back, checksum verified, by
`slsbh.load_projection` (docs/design/science.md §7).
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from models.frontend import slsbh
from models.localisation import SequenceLocaliser
from models.memory.temporal_memory import planned_bytes

__all__ = ["MAP_MODEL_BYTES", "Projection", "for_map", "make", "model_bytes", "nbytes", "projection_kind"]

#: Projection plus Temporal Memory bytes per map at most (issue 14).
MAP_MODEL_BYTES = 100_000_000

Projection = np.ndarray | slsbh.SparseProjection
Kind = Literal["dense", "sparse"]


def projection_kind(feature_dim: int, k: int, tm_bytes: int) -> Kind:
    """`dense` when D × k float32 plus the memory fit in MAP_MODEL_BYTES, else `sparse`."""
    return "dense" if feature_dim * k * 4 + tm_bytes <= MAP_MODEL_BYTES else "sparse"


def model_bytes(params: dict[str, Any], max_streams: int) -> int:
    """What a map of these parameters may hold besides its projection: the memory and every stream's
    localiser state (beam x HYPOTHESIS_BYTES, docs/design/science.md §11.3) at the stream cap."""
    return planned_bytes(params["tm"]) + max_streams * SequenceLocaliser(params["localiser"]).state_bytes()


def for_map(params: dict[str, Any], feature_dim: int, max_streams: int) -> tuple[Kind, Projection]:
    """A new map's projection kind and matrix (the kind by `projection_kind`, the seed `slsbh.seed`)."""
    k = int(params["slsbh"]["k"])
    kind = projection_kind(feature_dim, k, model_bytes(params, max_streams))
    return kind, make(kind, feature_dim, k, int(params["slsbh"]["seed"]))


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
