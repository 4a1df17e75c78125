"""The sizes of one map in memory and on disk (docs/design/service.md §1.4): `GET /v1/maps/{id}/memory`."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from models.pipeline import MapModel, Stream
from models.presets import TmOptions
from service.maps.results import IndexMemory, MemoryInfo, StorageMemory, StreamsMemory, TmMemory
from storage.base.process import rss_bytes
from storage.mapstore import MapStore

__all__ = ["memory_info"]


def memory_info(model: MapModel, streams: Mapping[str, Stream], *, tm_params: TmOptions,
                max_streams: int, projection: Path, store: MapStore | None,
                snapshots_bytes: int) -> MemoryInfo:
    """Writer: exact sizes, counts and caps of a map's memory, index, streams and files."""
    tm, index = model.tm, model.index
    size = tm.size()
    keyframes, keyframe_bytes = store.keyframe_bytes() if store else (0, 0)
    return MemoryInfo(
        tm=TmMemory(columns=size["columns"], cells_per_column=tm.cells_per_column,
                    cells=size["cells"],
                    max_segments_per_cell=int(tm_params.maxSegmentsPerCell),
                    max_synapses_per_segment=int(tm_params.maxSynapsesPerSegment),
                    segments=size["segments"], segment_capacity=size["segment_capacity"],
                    synapses=size["synapses"], synapse_capacity=size["synapse_capacity"],
                    allocated_bytes=size["bytes"], evicted_segments_total=size["evictions"],
                    overrun_synapses_total=size["overrun_destroyed"]),
        index=IndexMemory(observations=len(index), max_observations=index.max_observations,
                          postings=index.postings(), bytes=index.nbytes()),
        streams=StreamsMemory(count=len(streams), max=max_streams,
                              bytes=sum(sum(v.nbytes for v in s.context.state_dict().values())
                                        + (s.condition.state().nbytes if s.condition else 0)
                                        for s in streams.values())),
        projection_bytes=projection.stat().st_size if projection.exists() else 0,
        storage=StorageMemory(db_bytes=store.db_bytes() if store else 0,
                              wal_bytes=store.wal_bytes() if store else 0,
                              snapshots_bytes=snapshots_bytes, keyframes=keyframes,
                              keyframe_bytes=keyframe_bytes),
        process_rss_bytes=rss_bytes())
