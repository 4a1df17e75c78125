"""One map in memory: `MapRuntime`, the facade the registry, the routes and the domain call
(docs/design/service.md §1.2–§1.4, §4.3–§4.4, §6).

Each map owns a Temporal Memory, its sLSBH hasher (its own persisted projection), a `MapStore` (the
system of record) and an inverted index over winner cells. Every change to them runs in the map's
single writer thread, in submission order, so the memory sees frames in arrival order and never two at
once; different maps proceed in parallel.

This module builds the map's state and composes the concerns, each in its own module:

    writer.py       the writer thread and its order: observe, apply, the step and its persistence,
                    group commit, the automatic snapshot's trigger, forgetting, verification
    records.py      what a step makes (row, reply, loop closure, visit), pure
    snapshots.py    snapshots, their retention, restore and its memory budget
    recovering.py   recover, install, a tail replayed while serving, the index rebuilt; readiness
    room.py         `Room`: learning refused before its step while the disk is known full
    admission.py    the streams: admission within the stream window, a stream's reset
    repairing.py    listing and undoing the merges made from a stream's own trail
    resources.py    info, places, patch, memory
    settings.py     `RuntimeSettings`: the service settings a runtime reads

Which thread runs what:

    event loop     observe (queues the image, awaits the features, then queues the step), run,
                   require_ready
    writer         apply, snapshot, restore, reset_stream, info, memory, snapshots, snapshot_dir
                   (reach them through `run` / `submit`)
    start-up       recover (before the writer takes work; in the writer on the commit-failure path), close
"""

from __future__ import annotations

import asyncio
import threading
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import service.maps.runtime.idempotency as idempotency  # the module, not the package: no cycle via __init__
from models.frontend import slsbh
from models.localisation import InvertedIndex, PlaceMap
from models.memory.temporal_memory import TemporalMemory
from models.pipeline import Stream
from service.maps.config import MapConfig, map_model
from service.maps.results import RepairResult
from service.maps.runtime.admission import Admission
from service.maps.runtime.budget import MemoryBudget, index_row_bytes
from service.maps.runtime.durability import GroupCommit
from service.maps.runtime.recent import RecentAnswers
from service.maps.runtime.recovering import Recovering
from service.maps.runtime.repairing import Repairing
from service.maps.runtime.resources import Resources
from service.maps.runtime.room import Room
from service.maps.runtime.settings import RuntimeSettings
from service.maps.runtime.snapshots import Snapshots
from service.maps.runtime.writer import Writer
from storage.catalog import Catalog, MapRecord

__all__ = ["MapRuntime"]


class MapRuntime(Writer, Snapshots, Recovering, Admission, Repairing, Resources):
    """One map in memory, with its single writer thread; `state` is `ready` | `recovering` | `failed`
    (or `replaying`) and `state_reason` says why (module docstring: which thread runs which method,
    and which module holds each concern).

    Args:
        record: the map's catalog row (its stored options are parsed here: options this version
            rejects raise InvalidConfiguration, and the registry serves a FailedMap).
        catalog: the data directory's catalog (paths, snapshots, high-water marks).
        feature_dim: the map's backbone's feature dimension (the projection's rows).
        settings: what the runtime reads of the service's settings (`RuntimeSettings.of`).
        budget: the process-wide budget that holds this map's reservation (docs/design/service.md §1.8):
            each learned row reserves its index bytes first. None: a runtime built alone (tools, tests).
    """

    def __init__(self, record: MapRecord, catalog: Catalog, feature_dim: int, settings: RuntimeSettings, *,
                 budget: MemoryBudget | None = None) -> None:
        self.record = record
        self.map_id = record.map_id
        self.config = MapConfig.parse(record.params)
        self.layout = catalog.layout  # every path of the map (storage.layout)
        self.catalog = catalog
        self.settings = settings
        self.budget = budget
        self.row_bytes = index_row_bytes(self.config)
        # Idempotency-Keys: those of learned posts in the store (the last `idempotency_keys` seqs), those
        # of localisations in memory (service.maps.runtime.idempotency).
        self.keys = idempotency.KeyCache(settings.idempotency_cache)
        # admission
        self.streams: OrderedDict[str, Stream] = OrderedDict()
        self.stream_evictions = 0
        # recovery
        self.state = "recovering"
        self.state_reason: str | None = None
        self.recovery = None
        self._tail = None
        self._tail_started = 0.0
        self._localised = set()
        # snapshots
        self.covered = 0
        self.since_snapshot = 0
        self.snapshot_error = None
        self.snapshot_failures = 0
        self.restores = 0
        # the writer
        self.forgotten = 0
        self._closures_unlogged = False
        self.room = Room(self.map_id, self._has_room)
        self._writer = ThreadPoolExecutor(1, thread_name_prefix=f"map-{self.map_id}")
        # Learned rows are committed by the writer without their fsync and acknowledged once this has
        # synced them, one fsync per group (service.maps.runtime.durability).
        self._commits = GroupCommit(self._sync_store, f"sync-{self.map_id}")
        # The order in which observations reach the writer: each waits for the one before to be queued.
        self._turn = asyncio.Event()
        self._turn.set()
        # The listing of the merges a repair would undo, off the writer: one at a time (`own_trail_merges`).
        self._listing: Future[RepairResult] | None = None
        self._listing_lock = threading.Lock()
        sha = self.config.projection_sha256
        self.projection_path = self.layout.projection(sha)
        self.hasher = None
        self._projection_error = None
        # the checksum is verified on load: a map never runs on another matrix (docs/design/science.md §7)
        try:
            projection = slsbh.load_projection(self.projection_path, sha,
                                               shape=(feature_dim, int(self.config.sections.slsbh.k)))
            self.hasher = slsbh.Hasher(projection, float(self.config.sections.slsbh.s))
        except (slsbh.ProjectionError, OSError) as e:
            self._projection_error = str(e)
        self.cameras = {}
        # The memory, index and links the pure pipeline steps (models.pipeline); this runtime keeps
        # their order, their persistence and their snapshots.
        self.model = map_model(self.config, max_observations=settings.max_observations)
        self.store = None
        self.epoch = ""  # creation, restores and rewrites (`recover` reads the catalog's, `Recovering`)
        self._codes = OrderedDict()
        self.recent: RecentAnswers[Any] = RecentAnswers()  # the replies as sent (the route fills it)

    @property
    def tm(self) -> TemporalMemory:
        return self.model.tm

    @property
    def index(self) -> InvertedIndex:
        return self.model.index

    @property
    def place_map(self) -> PlaceMap:
        return self.model.place_map
