"""The sizes of one map in memory and on disk (docs/design/service.md §1.4): `GET /v1/maps/{id}/memory`."""

from __future__ import annotations

from typing import TYPE_CHECKING

from service.maps.results import IndexMemory, MemoryInfo, StorageMemory, StreamsMemory, TmMemory

if TYPE_CHECKING:
    from service.maps.runtime import MapRuntime

__all__ = ["memory_info"]


def memory_info(rt: MapRuntime) -> MemoryInfo:
    """Writer: exact sizes, counts and caps of `rt`'s memory, index, streams and files."""
    size = rt.tm.size()
    store = rt.store
    return MemoryInfo(
        tm=TmMemory(columns=size["columns"], cells_per_column=rt.tm.cells_per_column,
                    cells=size["cells"],
                    max_segments_per_cell=int(rt.params["tm"]["maxSegmentsPerCell"]),
                    max_synapses_per_segment=int(rt.params["tm"]["maxSynapsesPerSegment"]),
                    segments=size["segments"], segment_capacity=size["segment_capacity"],
                    synapses=size["synapses"], synapse_capacity=size["synapse_capacity"],
                    allocated_bytes=size["bytes"], evicted_segments_total=size["evictions"],
                    overrun_synapses_total=size["overrun_destroyed"]),
        index=IndexMemory(observations=len(rt.index), max_observations=rt.index.max_observations,
                          postings=rt.index.postings(), bytes=rt.index.nbytes()),
        streams=StreamsMemory(count=len(rt.streams), max=rt.max_streams,
                              bytes=sum(sum(v.nbytes for v in s.context.state_dict().values())
                                        for s in rt.streams.values())),
        projection_bytes=rt.projection_path.stat().st_size if rt.projection_path.exists() else 0,
        storage=StorageMemory(db_bytes=store.db_bytes() if store else 0,
                              wal_bytes=store.wal_bytes() if store else 0,
                              snapshots_bytes=rt.catalog.snapshots_bytes(rt.map_id)))
