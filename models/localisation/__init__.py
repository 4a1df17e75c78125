"""Sequence-level localisation of a stream over the map's links (docs/design/science.md §11)."""

from models.localisation.graph import SequenceGraph
from models.localisation.localiser import (
    HYPOTHESIS_BYTES,
    NULL_PRIOR,
    LocaliserParams,
    LocaliserState,
    OwnTrail,
    Place,
    SequenceLocaliser,
    default_conf,
    top_candidates,
)
from models.localisation.trail import CodeStats

__all__ = [
    "HYPOTHESIS_BYTES",
    "NULL_PRIOR",
    "CodeStats",
    "LocaliserParams",
    "LocaliserState",
    "OwnTrail",
    "Place",
    "SequenceGraph",
    "SequenceLocaliser",
    "default_conf",
    "top_candidates",
]
