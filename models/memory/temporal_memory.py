"""Numenta's Temporal Memory with NuPIC 1.0.5 semantics in fixed, preallocated memory.

docs/design/science.md §3 is the specification: parameter names as in NuPIC/htm.core (§3.1), learned
connections kept apart from the per-stream sequence context (§3.2), the step of §3.3, the bounded-memory rules
of §3.5 (LRU segment eviction, lowest-permanence overrun, decay below 1e-5, empty segments destroyed) and
the randomness rules of §3.6 (one seeded `numpy.random.Generator`, drawn only while learning).

The hot loops live in `models.memory._tm_kernels` (numba); this module is the readable interface.

Example:
    >>> tm = TemporalMemory(presets.TmOptions.of(presets.tm_params("cortexloc-grid")))
    >>> ctx = tm.new_context()
    >>> winners = tm.compute(np.array([3, 17, 40]), learn=True, context=ctx)
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field, fields
from typing import Any

import numba
import numpy as np

from models import presets
from models.memory import _tm_kernels as kern
from models.memory import _tm_synapses as syn

_EMPTY = np.zeros(0, dtype=np.int64)
_EMPTY32 = np.zeros(0, dtype=np.int32)


def _alloc(n: int, dtype: type, value: int | float = 0) -> np.ndarray:
    """Allocate and touch every page now: a map's memory is committed when it is created, so it can
    neither grow later nor fail later (np.zeros would leave pages to be faulted in during learning)."""
    a = np.empty(n, dtype=dtype)
    a.fill(value)
    return a


def _i64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int64)


@dataclass
class StepStats:
    """Per-step statistics (docs/design/science.md §3.3): counts of the step just computed."""

    active_columns: int = 0
    predicted_columns: int = 0
    bursting_columns: int = 0
    predictive_cells: int = 0  # cells predicted for the *next* step
    winner_cells: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass
class StreamContext:
    """Sequence state of one stream (docs/design/science.md §3.2): what the next step continues from.

    Attributes:
        active_cells, winner_cells: (n,) int64 sorted cell ids of the previous step.
        active_segs, matching_segs: (n,) int64 sorted segment ids computed from `active_cells`.
        active_pot, matching_pot: (n,) int32 active potential synapse counts of those segments.
        version: the connections version the segment lists were computed at.
    """

    active_cells: np.ndarray = field(default_factory=lambda: _EMPTY)
    winner_cells: np.ndarray = field(default_factory=lambda: _EMPTY)
    active_segs: np.ndarray = field(default_factory=lambda: _EMPTY)
    active_pot: np.ndarray = field(default_factory=lambda: _EMPTY32)
    matching_segs: np.ndarray = field(default_factory=lambda: _EMPTY)
    matching_pot: np.ndarray = field(default_factory=lambda: _EMPTY32)
    version: int = -1
    stats: StepStats = field(default_factory=StepStats)

    def reset(self) -> None:
        """Break the sequence: nothing is predicted or learned across this point."""
        self.active_cells = _EMPTY
        self.winner_cells = _EMPTY
        self.active_segs = _EMPTY
        self.active_pot = _EMPTY32
        self.matching_segs = _EMPTY
        self.matching_pot = _EMPTY32
        self.version = -1
        self.stats = StepStats()

    def state_dict(self) -> dict[str, np.ndarray]:
        return {
            "active_cells": self.active_cells.copy(),
            "winner_cells": self.winner_cells.copy(),
            "active_segs": self.active_segs.copy(),
            "active_pot": self.active_pot.copy(),
            "matching_segs": self.matching_segs.copy(),
            "matching_pot": self.matching_pot.copy(),
            "version": np.array(self.version, dtype=np.int64),
            "stats": np.array(list(self.stats.as_dict().values()), dtype=np.int64),
        }

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray]) -> StreamContext:
        return cls(
            active_cells=_i64(state["active_cells"]),
            winner_cells=_i64(state["winner_cells"]),
            active_segs=_i64(state["active_segs"]),
            active_pot=np.ascontiguousarray(state["active_pot"], dtype=np.int32),
            matching_segs=_i64(state["matching_segs"]),
            matching_pot=np.ascontiguousarray(state["matching_pot"], dtype=np.int32),
            version=int(state["version"]),
            stats=StepStats(*(int(v) for v in state["stats"])),
        )


#: The arrays of a context's `state_dict`: one per field.
_CONTEXT_FIELDS = frozenset(f.name for f in fields(StreamContext))


def validate(options: presets.TmOptions) -> list[str]:
    """Check parameters as NuPIC does; return the warnings of docs/design/science.md §3.1.

    Names, types and ranges are `presets.TmParams`'s (`TmOptions.of`); the rules between parameters are
    here.

    Raises:
        presets.ParamsError (a ValueError): minThreshold > activationThreshold.
    """
    o = options
    if o.minThreshold > o.activationThreshold:
        raise presets.ParamsError("tm", [("minThreshold", (
            f"minThreshold ({o.minThreshold}) must not exceed activationThreshold "
            f"({o.activationThreshold})"))])
    notes = []
    if o.activationThreshold > o.maxSynapsesPerSegment:
        notes.append(
            f"activationThreshold {o.activationThreshold} > maxSynapsesPerSegment "
            f"{o.maxSynapsesPerSegment}: this memory can never predict"
        )
    if o.maxNewSynapseCount > o.maxSynapsesPerSegment:
        notes.append("maxNewSynapseCount > maxSynapsesPerSegment: growth is cut by the synapse cap")
    if o.initialPermanence >= o.connectedPermanence:
        notes.append("initialPermanence >= connectedPermanence: one-shot learning")
    return notes


def _layout(o: presets.TmOptions) -> dict[str, tuple[int, Any, int]]:
    """Every array a memory with options `o` preallocates: name -> (length, dtype, fill value).

    One table for both the constructor and `planned_bytes`, so the reported size is exact.
    """
    cells = int(o.columnDimensions) * int(o.cellsPerColumn)
    n_seg = cells * int(o.maxSegmentsPerCell)
    k = int(o.maxSynapsesPerSegment)
    n_slot = n_seg * k
    n_blocks = syn.pool_blocks(n_slot, cells)
    return {
        "presyn": (n_slot, np.uint16 if cells <= 65536 else np.uint32, 0),
        "perm": (n_slot, np.float32, 0),
        "nsyn": (n_seg, np.uint16, 0),
        "last_used": (n_seg, np.int64, 0),
        "seg_count": (cells, np.uint16, 0),
        "rev": (n_blocks * syn.B, np.int32 if n_seg << (syn.slot_bits(k) + 1) < 2**31 else np.int64, 0),
        "rpos": (n_slot, np.int32 if n_blocks * syn.B < 2**31 else np.int64, 0),
        "blk_prev": (n_blocks, np.int64, -1),
        "blk_fill": (n_blocks, np.int32, 0),
        "tail": (cells, np.int64, -1),
        "pool": (1, np.int64, 0),
        # Packed counts and stamp of `_tm_kernels.activity` (the word `count_bits` was written for).
        "seg_act": (n_seg, np.uint16 if k < 64 else np.uint32 if k < 256 else np.int64, 0),
        "epoch": (1, np.int64, 0),
        "matching": (n_seg, np.int32 if n_seg < 2**31 else np.int64, 0),
        "mask_active": (cells, np.bool_, 0),
        "mask_winner": (cells, np.bool_, 0),
        "mask_scratch": (cells, np.bool_, 0),
        "cand": (cells, np.int64, 0),
        "counters": (4, np.int64, 0),
    }


def planned_bytes(options: presets.TmOptions) -> int:
    """Exact bytes a `TemporalMemory(options)` preallocates (`size()["bytes"]`), without allocating."""
    validate(options)
    arrays = sum(n * np.dtype(dtype).itemsize for n, dtype, _ in _layout(options).values())
    return arrays + 5 * 4 + 7 * 8  # plus the float32 and int64 parameter vectors


class TemporalMemory:
    """Learned connections of one map (docs/design/science.md §3.2) plus its seeded generator.

    Args:
        options: the parameters (`presets.TmOptions`, e.g. `TmOptions.of(presets.tm_params(name))`);
            None: NuPIC's defaults.

    Attributes:
        options: the parameters; params: the same by NuPIC name (a memory's state stores them as JSON).
        warnings: configuration warnings of docs/design/science.md §3.1 (not errors: presets reproduce them).
        iteration: learning iterations so far; version: bumped by every step that changes connections.
    """

    _CANONICAL = ("presyn", "perm", "nsyn", "last_used")
    #: The arrays `state_dict` writes besides the contexts' (`ctx.<field>`, `stream.<name>.<field>`).
    _STATE = (*_CANONICAL, "params", "counters", "scalars", "rng", "numpy_version", "numba_version")

    def __init__(self, options: presets.TmOptions | None = None) -> None:
        o = presets.TmOptions() if options is None else options
        self.warnings = validate(o)
        self.options = o
        self.params = o.values()
        self.n_columns = int(o.columnDimensions)
        self.cells_per_column = int(o.cellsPerColumn)
        self.n_cells = self.n_columns * self.cells_per_column
        S = int(o.maxSegmentsPerCell)
        Kc = int(o.maxSynapsesPerSegment)
        f32 = np.float32
        # Parameters cast to float32 once (docs/design/science.md §3.6).
        self._p = np.array(
            [o.initialPermanence, f32(o.connectedPermanence) - f32(syn.EPS),
             o.permanenceIncrement, o.permanenceDecrement, o.predictedSegmentDecrement], dtype=f32)
        self._ip = np.array(
            [self.cells_per_column, S, Kc, o.activationThreshold, o.minThreshold,
             o.maxNewSynapseCount, syn.slot_bits(Kc)], dtype=np.int64)
        a = {name: _alloc(n, dtype, fill) for name, (n, dtype, fill) in _layout(o).items()}
        # Canonical state (docs/design/science.md §3.5 table).
        self.presyn, self.perm, self.nsyn, self.last_used = a["presyn"], a["perm"], a["nsyn"], a["last_used"]
        # Auxiliary, fixed-capacity, derived from the canonical arrays.
        self._seg_count = a["seg_count"]
        # Reverse index (see models.memory._tm_kernels): blocks of entries per presynaptic cell; the unused
        # blocks form the free list through blk_prev.
        a["blk_prev"][:] = np.arange(1, a["blk_prev"].size + 1)
        a["blk_prev"][-1] = -1
        self._rx = (a["rev"], a["rpos"], a["blk_prev"], a["blk_fill"], a["tail"], a["pool"])
        # Scratch for one step: packed per-segment counts with their epoch, the matching list, masks
        # over cells, growth candidates.
        self._seg_act, self._epoch, self._matching = a["seg_act"], a["epoch"], a["matching"]
        self._mask_active, self._mask_winner = a["mask_active"], a["mask_winner"]
        self._mask_scratch, self._cand = a["mask_scratch"], a["cand"]
        self.counters = a["counters"]
        self.iteration = 0
        self.version = 0
        self.rng = np.random.Generator(np.random.PCG64(int(o.seed)))
        self.context = StreamContext()

    # ---------------------------------------------------------------- stepping

    def new_context(self) -> StreamContext:
        """A fresh sequence context (a new stream)."""
        return StreamContext()

    def reset(self, context: StreamContext | None = None) -> None:
        """Break sequence context of `context` (default: the built-in stream)."""
        (context or self.context).reset()

    def compute(self, active_columns: np.ndarray, learn: bool = True,
                context: StreamContext | None = None) -> np.ndarray:
        """One Temporal Memory step (docs/design/science.md §3.3).

        Args:
            active_columns: (a,) column indices in [0, columnDimensions); sorted and deduplicated here.
            learn: adapt the connections (mapping); False leaves connections and generator untouched.
            context: the stream's sequence state, updated in place (default: the built-in stream).

        Returns:
            winner_cells: (w,) int64 sorted cell ids, the place descriptor.
        """
        ctx = context or self.context
        cols = np.asarray(active_columns)
        if cols.dtype == np.bool_:
            raise ValueError("active_columns are indices, not a dense boolean mask (use np.flatnonzero)")
        cols = np.unique(cols.astype(np.int64))
        if cols.size and (cols[0] < 0 or cols[-1] >= self.n_columns):
            raise ValueError(f"active column out of range [0, {self.n_columns})")
        if ctx.version != self.version and ctx.active_cells.size:
            # Another stream learned since this context's segments were computed.
            self._activate_dendrites(ctx, ctx.active_cells, learn=False)
        active, winners, n_pred, n_burst, changed = kern.step(
            cols, bool(learn), ctx.active_cells, ctx.winner_cells, ctx.active_segs, ctx.active_pot,
            ctx.matching_segs, ctx.matching_pot, self.iteration, self._p, self._ip, self.rng,
            self.presyn, self.perm, self.nsyn, self.last_used, self._seg_count, self._rx, self._mask_active,
            self._mask_winner, self._mask_scratch, self._cand, self.counters)
        if changed:
            self.version += 1
        n_predictive = self._activate_dendrites(ctx, active, learn=bool(learn))
        if learn:
            self.iteration += 1
        ctx.active_cells = active
        ctx.winner_cells = winners
        ctx.stats = StepStats(cols.size, n_pred, n_burst, n_predictive, winners.size)
        return winners

    def _activate_dendrites(self, ctx: StreamContext, active: np.ndarray, learn: bool) -> int:
        a, ap, m, mp, n_predictive = kern.activity(
            active, learn, self.iteration, self._ip, self.last_used, self._rx, self._seg_act, self._epoch,
            self._matching)
        ctx.active_segs, ctx.active_pot, ctx.matching_segs, ctx.matching_pot = a, ap, m, mp
        ctx.version = self.version
        return int(n_predictive)

    def connected_presyn(self, segment: int) -> np.ndarray:
        """(n,) int64 sorted presynaptic cells of `segment`'s connected synapses (permanence >=
        connectedPermanence, as the kernels test it; docs/design/science.md §3.3); empty for a free slot."""
        K = int(self._ip[syn.I_K])
        lo = int(segment) * K
        hi = lo + int(self.nsyn[segment])
        return np.sort(self.presyn[lo:hi][self.perm[lo:hi] >= self._p[syn.P_CONN]].astype(np.int64))

    def predictive_cells(self, context: StreamContext | None = None) -> np.ndarray:
        """(p,) int64 sorted cells predicted for the next step of `context`."""
        ctx = context or self.context
        return np.unique(ctx.active_segs // int(self._ip[syn.I_S]))

    # ---------------------------------------------------------------- inspection

    def size(self) -> dict[str, int]:
        """Exact counts and bytes (docs/design/science.md §3.5).

        Returns:
            segments, synapses (live), segment_capacity, synapse_capacity, evictions,
            overrun_destroyed, decay_destroyed, empty_destroyed, canonical_bytes (the reference layout),
            bytes (everything this object preallocated: canonical + reverse index + scratch).
        """
        canonical = sum(getattr(self, n).nbytes for n in self._CANONICAL)
        aux = sum(a.nbytes for a in (self._seg_count, *self._rx, self._seg_act,
                                     self._epoch, self._matching, self._mask_active, self._mask_winner,
                                     self._mask_scratch, self._cand, self.counters, self._p, self._ip))
        return {
            "columns": self.n_columns,
            "cells": self.n_cells,
            "segments": int(np.count_nonzero(self.nsyn)),
            "synapses": int(self.nsyn.sum(dtype=np.int64)),
            "segment_capacity": int(self.nsyn.size),
            "synapse_capacity": int(self.presyn.size),
            "evictions": int(self.counters[syn.C_EVICT]),
            "overrun_destroyed": int(self.counters[syn.C_OVERRUN]),
            "decay_destroyed": int(self.counters[syn.C_DECAY]),
            "empty_destroyed": int(self.counters[syn.C_EMPTY]),
            "canonical_bytes": int(canonical),
            "bytes": int(canonical + aux),
        }

    # ---------------------------------------------------------------- persistence

    def state_dict(self, streams: dict[str, StreamContext] | None = None) -> dict[str, np.ndarray]:
        """The whole state as plain numpy arrays (copies); see `from_state` and `load_streams`.

        Args:
            streams: named stream contexts to include (docs/design/science.md §3.6: every context is in the
                snapshot); the built-in context is always included under the `ctx.` prefix.
        """
        bg = self.rng.bit_generator.state
        mask64 = (1 << 64) - 1
        rng_words = [bg["state"]["state"] >> 64, bg["state"]["state"] & mask64,
                     bg["state"]["inc"] >> 64, bg["state"]["inc"] & mask64,
                     bg["has_uint32"], bg["uinteger"]]
        out = {n: getattr(self, n).copy() for n in self._CANONICAL}
        out.update({
            "params": np.array(json.dumps(self.params, sort_keys=True)),
            "counters": self.counters.copy(),
            "scalars": np.array([self.iteration, self.version], dtype=np.int64),
            "rng": np.array(rng_words, dtype=np.uint64),
            # The generator stream is stable only for one NumPy build (NEP 19), and the kernels draw
            # through numba's implementation of it.
            "numpy_version": np.array(np.__version__),
            "numba_version": np.array(numba.__version__),
        })
        out.update({f"ctx.{k}": v for k, v in self.context.state_dict().items()})
        for name, ctx in (streams or {}).items():
            if "." in name:
                raise ValueError(f"stream name {name!r} must not contain '.'")
            out.update({f"stream.{name}.{k}": v for k, v in ctx.state_dict().items()})
        return out

    @classmethod
    def state_name(cls, name: str) -> bool:
        """Whether `state_dict` (with any streams) writes an array of this name: a snapshot's loader refuses
        any other before reading it (docs/design/service.md §4.4)."""
        kind, _, rest = name.partition(".")
        if kind == "ctx":
            return rest in _CONTEXT_FIELDS
        if kind == "stream":
            return rest.partition(".")[2] in _CONTEXT_FIELDS
        return name in cls._STATE

    @staticmethod
    def load_streams(state: dict[str, np.ndarray]) -> dict[str, StreamContext]:
        """The named stream contexts saved by `state_dict(streams=...)`."""
        fields: dict[str, dict[str, np.ndarray]] = {}
        for key, value in state.items():
            if key.startswith("stream."):
                _, name, field_name = key.split(".", 2)
                fields.setdefault(name, {})[field_name] = value
        return {name: StreamContext.from_state(f) for name, f in fields.items()}

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray]) -> TemporalMemory:
        """Rebuild a memory saved by `state_dict` (the reverse index is rebuilt, not loaded)."""
        tm = cls(presets.TmOptions.of(json.loads(str(state["params"]))))
        for n in cls._CANONICAL:
            src = np.asarray(state[n])
            dst = getattr(tm, n)
            if src.shape != dst.shape or src.dtype != dst.dtype:
                raise ValueError(
                    f"state array {n!r}: expected {dst.dtype}{dst.shape}, got {src.dtype}{src.shape}")
            dst[...] = src
        tm.counters[...] = state["counters"]
        tm.iteration, tm.version = (int(v) for v in state["scalars"])
        w = [int(v) for v in state["rng"]]
        tm.rng.bit_generator.state = {
            "bit_generator": "PCG64",
            "state": {"state": (w[0] << 64) | w[1], "inc": (w[2] << 64) | w[3]},
            "has_uint32": w[4], "uinteger": w[5],
        }
        Kc = int(tm._ip[syn.I_K])
        S = int(tm._ip[syn.I_S])
        syn.rebuild_index(tm.nsyn, tm.presyn, tm.perm, tm._p, Kc, tm._rx)
        tm._seg_count[...] = np.count_nonzero(tm.nsyn.reshape(-1, S), axis=1)
        tm.context = StreamContext.from_state(
            {k[4:]: v for k, v in state.items() if k.startswith("ctx.")})
        for lib, version in (("numpy", np.__version__), ("numba", numba.__version__)):
            if str(state.get(f"{lib}_version", version)) != version:
                warnings.warn(f"state saved with another {lib} version: the random stream may differ",
                              stacklevel=2)
        return tm
