"""Forgetting at the hard cap on rows held (docs/design/science.md §11.9), pure: which rows a map forgets
before a learned row when its index is full.

The one home of the rule: the map writer (`service.maps.runtime.MapRuntime.apply`) persists what this
decides before the row that needed the room; the evaluation (`service.evaluation.service_path`) applies
it to its model alone, so a map measured beyond its cap is the map served.
"""

from __future__ import annotations

from models.localisation.index import InvertedIndex
from models.localisation.options import LocaliserOptions
from models.localisation.places import PlaceMap

__all__ = ["batch", "rule", "to_forget"]


def rule(percent: int) -> str:
    """The rule as the map resource states it (`places.forgetting`), at the map's `forget_percent`
    (`LocaliserOptions`: at least that percentage of the cap is forgotten at a time, and why)."""
    return ("when the rows held reach max_rows, the least recently used places (made, visited or joined "
            f"by a learning stream) are forgotten whole, at least {percent}% of max_rows at a time; a "
            "place over max_appearances drops its least recently used appearance")


def batch(cap: int, percent: int = LocaliserOptions().forget_percent) -> int:
    """The least number of rows one forgetting drops at a cap of `cap` rows and `percent` of it (at least
    one)."""
    return max(1, cap * percent // 100)


def to_forget(index: InvertedIndex, place_map: PlaceMap) -> list[int]:
    """The rows to forget before the next learned row: none under the cap (`index.max_observations` rows
    held); at it, the least recently used places, whole, at least `batch(cap, forget_percent)` rows
    (`PlaceMap.least_recent`). The caller drops them (`models.pipeline.drop`), durably first where
    it stores them."""
    cap = index.max_observations
    if len(index) < cap:
        return []
    return place_map.least_recent(batch(cap, place_map.options.forget_percent))
