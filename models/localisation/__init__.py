"""Sequence-level localisation of a stream over the map's links (docs/design/science.md §11)."""

from models.localisation.graph import SequenceGraph
from models.localisation.index import IndexFull, InvertedIndex, Match
from models.localisation.localiser import (
    HYPOTHESIS_BYTES,
    MIN_CONTRAST,
    NULL_PRIOR,
    LocaliserState,
    Place,
    SequenceLocaliser,
    informative,
    top_candidates,
)
from models.localisation.options import LocaliserOptions, LocaliserParams, default_conf
from models.localisation.places import PlaceMap, graph_from_rows
from models.localisation.trail import CodeStats, OwnTrail

__all__ = [
    "HYPOTHESIS_BYTES",
    "MIN_CONTRAST",
    "NULL_PRIOR",
    "CodeStats",
    "IndexFull",
    "InvertedIndex",
    "LocaliserOptions",
    "LocaliserParams",
    "LocaliserState",
    "Match",
    "OwnTrail",
    "Place",
    "PlaceMap",
    "SequenceGraph",
    "SequenceLocaliser",
    "default_conf",
    "graph_from_rows",
    "informative",
    "top_candidates",
]
