"""A map's memory rebuilt from its store, and its snapshots (docs/design/service.md §1.5, §4.4): the one
rebuild path (memory.py: recover, rebuild, verify_map) and snapshots at the map level (snapshots.py:
take, list, locate, prune, export, import)."""

from service.maps.recovery.memory import (
    VISIT_CURSOR,
    VISIT_MARK,
    MapCheck,
    Rebuilt,
    Replay,
    Tail,
    begin,
    check_memory,
    open_catalog,
    rebuild,
    recover,
    verify_map,
)

__all__ = ["VISIT_CURSOR", "VISIT_MARK", "MapCheck", "Rebuilt", "Replay", "Tail", "begin", "check_memory",
           "open_catalog", "rebuild", "recover", "verify_map"]
