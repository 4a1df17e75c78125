"""The process-wide memory budget over all maps (docs/design/service.md §1.8).

One `MemoryBudget` per registry holds what every open map may keep in RAM: its Temporal Memory (exact,
preallocated), its projection (a dense one is a read-only memory map of the content-addressed file,
so maps with the same projection share its pages and it is counted once; a sparse one is loaded per
map), its localiser states at the stream cap, its cache of keyed replies at its cap, and its index
(an estimate per stored row, grown as rows are learned), plus the encoders, counted once. A map is
reserved before anything of it is allocated (create, open at start, restore) and a learned row
before its step; a reservation that does not fit raises `MemoryBudgetExceeded` and changes nothing.

One accounting for create, open and restart: the recovery that builds a map's memory (at its creation
and at every start) holds a second memory beside the runtime's empty one for a while, so every check
also keeps room for the largest memory of the maps held (the recovery room, `MemoryBudget._room`). A map that
learned within the budget therefore reopens under it: opened one after another, the maps never hold
more than they held while they learned, plus one second memory at a time.

The default total is `DEFAULT_SHARE` of the smaller of the host's memory and the cgroup limit of the
container (`CGROUP_LIMIT_FILES`, v2 then v1): the rest is for what no map owns (Python, torch's
working memory, request bodies, SQLite's page caches).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import gc
import os
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from models.frontend import slsbh
from models.memory.temporal_memory import planned_bytes
from service.maps.config import MapConfig
from service.maps.errors import MemoryBudgetExceeded
from service.maps.runtime.idempotency import CACHE_MAX_CHARS

__all__ = ["CGROUP_LIMIT_FILES", "DEFAULT_SHARE", "INDEX_ROW_OVERHEAD_BYTES", "POSTING_BYTES", "MapNeed",
           "MemoryBudget", "default_total", "encoder_bytes", "give_back", "index_row_bytes", "map_need",
           "memory_limit", "projection_bytes"]

#: Share of the smaller of host memory and cgroup limit that the maps and encoders may use by default.
DEFAULT_SHARE = 0.5
#: cgroup v2, then v1: the container's memory limit ("max" or a huge number: none).
CGROUP_LIMIT_FILES = (Path("/sys/fs/cgroup/memory.max"), Path("/sys/fs/cgroup/memory/memory.limit_in_bytes"))
#: An index posting (an int32 row number) with the slack of its doubling array (`models.localisation.index`).
POSTING_BYTES = 8
#: Per stored row besides its postings: seq, weight, stream row, the ranking scratch, the localiser's
#: graph links (int64 prev and next), each with its doubling slack.
INDEX_ROW_OVERHEAD_BYTES = 96


@functools.cache
def _malloc_trim() -> Any:
    """glibc's `malloc_trim`, or None (musl, macOS: their allocators return memory on their own terms)."""
    try:
        return ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return None


def give_back() -> None:
    """Return what a dropped map held to the OS, at once (a map deleted, a memory replaced by a restore).

    The budget counts a map's memory gone when the map is; the process must agree, or its RSS outgrows
    the budget it was sized by (a container's limit). A map's objects sit in reference cycles that only
    the collector's full pass frees, and that pass is rare: maps created and deleted in rounds stayed
    alive in dozens (docs/design/service.md §1.8). Then glibc keeps freed heap pages in its arenas until
    `malloc_trim`. Both pause the process (a full collection of its heap), paid on the rare operation
    that frees a map, never per frame."""
    gc.collect()
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def memory_limit(cgroup_files: Iterable[Path] = CGROUP_LIMIT_FILES) -> tuple[int, str]:
    """(bytes, source): the smaller of the host's physical memory (`host`) and the first cgroup limit
    found (`cgroup`)."""
    host = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    for path in cgroup_files:
        try:
            text = path.read_text().strip()
        except OSError:
            continue
        if text.isdigit() and 0 < int(text) < host:  # "max" (v2) or ~2**63 (v1): no limit
            return int(text), "cgroup"
        break
    return host, "host"


def default_total() -> tuple[int, str]:
    """(bytes, source) of the budget when CORTEXLOC_MEMORY_BUDGET_BYTES is unset."""
    limit, source = memory_limit()
    return int(DEFAULT_SHARE * limit), f"{DEFAULT_SHARE:g} x {source}"


def encoder_bytes(encoder: Any) -> int:
    """Bytes of an encoder's network parameters and buffers (0 for one without a torch module)."""
    module = getattr(getattr(encoder, "backbone", None), "module", None)
    if module is None:
        return 0
    tensors = [*module.parameters(), *module.buffers()]
    return int(sum(t.numel() * t.element_size() for t in tensors))


def index_row_bytes(config: MapConfig) -> int:
    """Estimated index bytes of one stored row of a map with `config`: its 2n winner cells (one per
    active column of the sLSBH code, docs/design/science.md §7.3) as postings, plus the row's overhead."""
    s_conf = config.sections.slsbh
    return 2 * slsbh.n_ones(int(s_conf.k), float(s_conf.s)) * POSTING_BYTES + INDEX_ROW_OVERHEAD_BYTES


@dataclass(frozen=True)
class MapNeed:
    """What one map holds in RAM, by part (bytes). `projection_key` names a projection shared by the
    maps that have it (a dense matrix's SHA-256), None for one of the map's own."""

    tm: int
    projection: int
    localiser: int
    caches: int
    index: int
    projection_key: str | None = None

    def parts(self) -> dict[str, int]:
        return {"tm": self.tm, "projection": self.projection, "localiser": self.localiser,
                "caches": self.caches, "index": self.index}


def projection_bytes(kind: str, feature_dim: int, k: int) -> int:
    """Bytes of a (feature_dim, k) projection in memory: dense float32, or the very sparse one's CSC
    arrays at its expected density 1/√D (int64 indptr, int32 indices, int8 signs)."""
    if kind == "dense":
        return feature_dim * k * 4
    return (k + 1) * 8 + round(feature_dim ** 0.5 * k) * 5


def map_need(config: MapConfig, projection: int, rows: int, *, max_streams: int,
             key_cache: int) -> MapNeed:
    """The `MapNeed` of a map with this configuration (its `projection` kind chosen), `rows` stored rows
    and a projection of `projection` bytes (`projection_bytes`, or its file's size where no encoder
    says the feature dimension)."""
    return MapNeed(
        tm=planned_bytes(config.sections.tm), projection=int(projection),
        localiser=config.streams_bytes(max_streams),
        caches=CACHE_MAX_CHARS if key_cache else 0, index=rows * index_row_bytes(config),
        projection_key=(config.projection_sha256 or None) if config.projection == "dense" else None)


@dataclass
class _Held:
    need: MapNeed
    index: int = field(default=0)


class MemoryBudget:
    """The reservations of the open maps against `total` bytes (thread-safe: writers of several maps
    grow their indexes at once).

    Args:
        total: the budget (CORTEXLOC_MEMORY_BUDGET_BYTES, or `default_total`).
        source: where `total` came from (`setting`, `0.5 x host`, `0.5 x cgroup`).

    The encoders' bytes (counted once, whatever the maps) are told by `set_encoders`, outside the lock:
    an encoder being built must not hold up the writers that reserve their rows.
    """

    def __init__(self, total: int, source: str = "setting") -> None:
        self.total, self.source = int(total), source
        self._encoders = 0
        self._transient = 0  # held while a restore builds a map's new index beside the old one
        self._held: dict[str, _Held] = {}
        self._lock = threading.Lock()

    def _shared_keys(self, without: str | None = None) -> set[str]:
        return {h.need.projection_key for m, h in self._held.items()
                if m != without and h.need.projection_key is not None}

    def _used(self) -> int:
        shared: set[str] = set()
        used = self._encoders + self._transient
        for h in self._held.values():
            key = h.need.projection_key
            if key is None or key not in shared:
                used += h.need.projection
            if key is not None:
                shared.add(key)
            used += h.need.tm + h.need.localiser + h.need.caches + h.index
        return used

    def _asked(self, map_id: str, need: MapNeed) -> int:
        shared = need.projection_key is not None and need.projection_key in self._shared_keys(map_id)
        return need.tm + need.localiser + need.caches + need.index + (0 if shared else need.projection)

    def _room(self) -> int:
        """The recovery room: bytes every check keeps free beyond what is held, the largest memory of the
        maps held, for the second memory a recovery builds beside a map's empty one (at its creation, at
        each start; docs/design/service.md §1.8)."""
        return max((h.need.tm for h in self._held.values()), default=0)

    def used(self) -> int:
        with self._lock:
            return self._used()

    def held(self) -> tuple[int, int]:
        """(bytes used, a restore's second index included; the recovery room kept free), read together."""
        with self._lock:
            return self._used(), self._room()

    def fits(self, map_id: str, need: MapNeed) -> tuple[bool, int, int]:
        """(fits, used, asked) for reserving `need` as `map_id` (its own reservation not counted):
        `used` is what the others hold plus the recovery room they keep, `asked` the map's parts plus
        what its own memory adds to that room (its recovery's second memory, `_room`)."""
        with self._lock:
            return self._fits(map_id, need)

    def _fits(self, map_id: str, need: MapNeed) -> tuple[bool, int, int]:
        held = self._held.pop(map_id, None)
        try:
            room = self._room()
            used, asked = self._used() + room, self._asked(map_id, need) + max(0, need.tm - room)
        finally:
            if held is not None:
                self._held[map_id] = held
        return used + asked <= self.total, used, asked

    def reserve(self, map_id: str, need: MapNeed) -> None:
        """Hold `need` for `map_id`, replacing what it held. Raises MemoryBudgetExceeded (nothing held
        changes)."""
        with self._lock:
            ok, used, asked = self._fits(map_id, need)
            if not ok:
                raise MemoryBudgetExceeded(map_id, used, asked, self.total)
            self._held[map_id] = _Held(need, need.index)

    def grow_index(self, map_id: str, nbytes: int) -> None:
        """`nbytes` more (or, negative, fewer) index bytes for `map_id`: a learned row, a restore.
        Raises MemoryBudgetExceeded when growing does not fit beside the recovery room (nothing held
        changes): a row that would keep a map from reopening at the next start is refused now."""
        with self._lock:
            held = self._held.get(map_id)
            if held is None:
                return  # a map the budget does not hold (tools and tests build runtimes alone)
            used = self._used() + self._room()
            if nbytes > 0 and used + nbytes > self.total:
                raise MemoryBudgetExceeded(map_id, used, nbytes, self.total)
            held.index = max(0, held.index + nbytes)

    @contextlib.contextmanager
    def transient(self, map_id: str, nbytes: int) -> Iterator[None]:
        """Hold `nbytes` more while the block runs, beside the recovery room: a restore rebuilds the
        map's index beside the one it replaces (its second memory is the room's). Raises
        MemoryBudgetExceeded before the block (nothing held changes)."""
        with self._lock:
            used = self._used() + self._room()
            if used + nbytes > self.total:
                raise MemoryBudgetExceeded(map_id, used, nbytes, self.total)
            self._transient += nbytes
        try:
            yield
        finally:
            with self._lock:
                self._transient -= nbytes

    def set_index(self, map_id: str, nbytes: int) -> None:
        """The index estimate of `map_id` after a recovery rebuilt it (its rows as they are now)."""
        with self._lock:
            if map_id in self._held:
                self._held[map_id].index = nbytes

    def set_encoders(self, nbytes: int) -> None:
        """The bytes of the encoders built so far (`encoder_bytes` of each)."""
        with self._lock:
            self._encoders = int(nbytes)

    def release(self, map_id: str) -> None:
        with self._lock:
            self._held.pop(map_id, None)

    def report(self) -> tuple[int, dict[str, dict[str, int]]]:
        """(encoder bytes, map_id -> its parts as held now, `projection` 0 where another map holds a
        shared one first)."""
        with self._lock:
            seen: set[str] = set()
            maps = {}
            for map_id, h in self._held.items():
                parts = {**h.need.parts(), "index": h.index}
                key = h.need.projection_key
                if key is not None and key in seen:
                    parts["projection"] = 0
                if key is not None:
                    seen.add(key)
                maps[map_id] = parts
            return self._encoders, maps
