"""Sequence-level localisation of a stream over the map's links (docs/design/science.md §11)."""

from models.localisation.graph import SequenceGraph
from models.localisation.localiser import (
    NULL_PRIOR,
    LocaliserState,
    Place,
    SequenceLocaliser,
    default_conf,
    top_candidates,
)

__all__ = ["NULL_PRIOR", "LocaliserState", "Place", "SequenceGraph", "SequenceLocaliser", "default_conf",
           "top_candidates"]
