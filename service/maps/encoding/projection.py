"""A map's sLSBH projection: dense or very sparse by the map's size budget, persisted by SHA-256
(docs/design/science.md §7, docs/design/service.md §1.1).

A map holds its projection, its Temporal Memory and its streams' localiser states; together they stay
within the one map-size budget, CORTEXLOC_MAX_MAP_BYTES (`model_bytes` is refused above it before
anything is written; the projection takes what is left). The dense matrix is D × k float32 (AlexNet
conv3: 64,896 × 1,024 = 266 MB); where it would break the budget the map gets the very sparse
projection (Li, Hastie & Church 2006; `slsbh.make_sparse_projection`, at parity with the dense one in
docs/results.md §6), about √D · k nonzeros (1.3 MB for AlexNet).

Both are stored content-addressed by `slsbh.save_projection` and read back, checksum verified, by
`slsbh.load_projection` (docs/design/science.md §7).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from models.frontend import slsbh
from models.memory.temporal_memory import planned_bytes
from service.maps.config import MapConfig

__all__ = ["Projection", "for_map", "make", "model_bytes", "nbytes", "projection_kind"]

Projection = np.ndarray | slsbh.SparseProjection
Kind = Literal["dense", "sparse"]


def projection_kind(feature_dim: int, k: int, model_bytes: int, budget: int) -> Kind:
    """`dense` when D × k float32 plus the rest of the map (`model_bytes`) fit in `budget`, else `sparse`."""
    return "dense" if feature_dim * k * 4 + model_bytes <= budget else "sparse"


def model_bytes(config: MapConfig, max_streams: int) -> int:
    """What a map of this configuration may hold besides its projection: the memory and every stream's
    localiser state and condition (`MapConfig.streams_bytes`, docs/design/science.md §11.3, §11.10) at
    the stream cap."""
    return planned_bytes(config.sections.tm) + config.streams_bytes(max_streams)


def for_map(config: MapConfig, feature_dim: int, max_streams: int, budget: int) -> tuple[Kind, Projection]:
    """A new map's projection kind and matrix (the kind by `projection_kind` within `budget`,
    CORTEXLOC_MAX_MAP_BYTES; the seed `slsbh.seed`)."""
    k = int(config.sections.slsbh.k)
    kind = projection_kind(feature_dim, k, model_bytes(config, max_streams), budget)
    return kind, make(kind, feature_dim, k, int(config.sections.slsbh.seed))


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
