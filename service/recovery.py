"""Rebuilding a map's memory from its store: the one path that recovery at startup, restore and
`cortexloc verify` share (docs/design/service.md §4.4).

A rebuild starts from a fresh memory (replay from the first row) or from a snapshot's arrays, then
replays the store's rows after that point, comparing every replayed step's winner cells with the
stored ones. Streams, their bookkeeping and the arrays of a snapshot are converted here in both
directions (`memory_state`, `load_memory_state`).
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from models.frontend import slsbh
from models.frontend.adaptation import RunningMean
from models.memory.temporal_memory import StreamContext, TemporalMemory
from storage import snapshots
from storage.catalog import Catalog, MapRecord, StorageError
from storage.mapstore import MapStore, Observation

__all__ = ["MapCheck", "Rebuilt", "Stream", "load_memory_state", "memory_state", "rebuild", "verify_map"]


@dataclass
class Stream:
    """A stream's sequence state in one map (docs/design/service.md §1.3)."""

    context: StreamContext = field(default_factory=StreamContext)
    step: int = 0  # steps since the context was last empty
    last_learned_seq: int | None = None  # the learned observation the context continues
    learning: bool | None = None  # mode of the last step (a switch to learning starts a new sequence)
    adapt: RunningMean | None = None  # the stream's running mean of projections (models.frontend.adaptation)


def memory_state(tm: TemporalMemory, streams: Mapping[str, Stream]) -> dict[str, np.ndarray]:
    """The whole memory as arrays: TM, generator, every stream's context and bookkeeping."""
    names = {name.encode().hex(): name for name in streams}  # stream names may hold '.'
    state = tm.state_dict(streams={h: streams[n].context for h, n in names.items()})
    for h, n in names.items():
        st = streams[n]
        state[f"streammeta.{h}"] = np.array(
            [st.step, -1 if st.last_learned_seq is None else st.last_learned_seq,
             -1 if st.learning is None else int(st.learning)], dtype=np.int64)
        if st.adapt is not None:
            state[f"streamadapt.{h}"] = st.adapt.state()
    return state


def load_memory_state(state: Mapping[str, np.ndarray], adapt_tau: int
                      ) -> tuple[TemporalMemory, OrderedDict[str, Stream]]:
    """The reverse of `memory_state`: (memory, streams by name)."""
    tm = TemporalMemory.from_state(dict(state))
    streams: OrderedDict[str, Stream] = OrderedDict()
    for h, ctx in TemporalMemory.load_streams(dict(state)).items():
        step, last, learning = (int(v) for v in state[f"streammeta.{h}"])
        adapt = (RunningMean.from_state(adapt_tau, state[f"streamadapt.{h}"])
                 if adapt_tau and f"streamadapt.{h}" in state else None)
        streams[bytes.fromhex(h).decode()] = Stream(
            ctx, step, None if last < 0 else last, None if learning < 0 else bool(learning), adapt)
    return tm, streams


@dataclass
class Rebuilt:
    """The outcome of `rebuild`.

    Attributes:
        tm, streams: the rebuilt memory and stream states.
        replayed: rows replayed (after the snapshot, if any).
        mismatches: seqs whose replayed winner cells differ from the stored ones, in seq order.
        last_seq: the last row replayed (the start's seq when none was).
    """

    tm: TemporalMemory
    streams: OrderedDict[str, Stream]
    replayed: int = 0
    mismatches: list[int] = field(default_factory=list)
    last_seq: int = 0


def rebuild(start: TemporalMemory | Mapping[str, np.ndarray], rows: Iterable[Observation], *,
            adapt_tau: int = 0, stop_at_mismatch: bool = True,
            progress: Callable[[int], None] | None = None) -> Rebuilt:
    """Replay `rows` (in seq order) on a fresh memory or a snapshot's arrays, checking each step.

    A localisation stream's context was never durable: one held by the snapshot is dropped, so its
    next step starts afresh exactly as after a restart without the snapshot (docs/design/service.md §1.2).

    Args:
        start: a fresh `TemporalMemory` (used in place) or the arrays of a snapshot's `memory.npz`.
        rows: the observations after the start (all of them for a fresh memory).
        adapt_tau: the map's adaptation time constant (restores the streams' running means).
        stop_at_mismatch: stop at the first divergent row (recovery tries an older start then);
            False replays every row and lists every divergent seq (`cortexloc verify`, the last resort).
        progress: called with the number of rows replayed so far, once per row.

    Returns:
        The rebuilt memory, and what the replay found.
    """
    if isinstance(start, TemporalMemory):
        out = Rebuilt(start, OrderedDict())
    else:
        tm, streams = load_memory_state(start, adapt_tau)
        out = Rebuilt(tm, OrderedDict((n, st) for n, st in streams.items() if st.learning is not False))
    for row in rows:
        st = out.streams.get(row.stream)
        if st is None:
            st = out.streams[row.stream] = Stream()
        if row.context_prev_seq is None:
            st.context.reset()
        winners = out.tm.compute(row.input_sdr, learn=True, context=st.context)
        out.replayed += 1
        out.last_seq = row.seq
        if not np.array_equal(winners, row.winner_cells):
            out.mismatches.append(row.seq)
            if stop_at_mismatch:
                break
        st.step = 1 if row.context_prev_seq is None else st.step + 1  # steps taken, as in observe
        st.last_learned_seq, st.learning = row.seq, True
        if progress is not None:
            progress(out.replayed)
    return out


@dataclass
class MapCheck:
    """What `verify_map` found for one map.

    Attributes:
        map_id: the map.
        rows: rows replayed and compared.
        mismatches: seqs whose stored winner cells the replay from the first row did not reproduce.
        snapshots_ok: ids of the snapshots whose every checksum verified.
        snapshots_bad: snapshot id -> why it does not verify.
        problems: anything else wrong (store unreadable or damaged, projection missing or changed).
        seconds: wall time of the check.
    """

    map_id: str
    rows: int = 0
    mismatches: list[int] = field(default_factory=list)
    snapshots_ok: list[str] = field(default_factory=list)
    snapshots_bad: dict[str, str] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return not (self.mismatches or self.snapshots_bad or self.problems)


def verify_map(catalog: Catalog, record: MapRecord, *,
               progress: Callable[[int, int], None] | None = None) -> MapCheck:
    """The offline full check of one map (`cortexloc verify`), changing nothing on disk: the store's
    integrity, a replay from the first row comparing every row's stored winner cells, every snapshot's
    checksums, and the projection's SHA-256.

    Args:
        catalog: the data directory's catalog (opened read-only).
        record: the map.
        progress: called with (rows replayed, rows in the store).
    """
    t0 = time.perf_counter()
    out = MapCheck(record.map_id)
    root = catalog.root
    sha = str(record.params.get("projection_sha256", ""))
    projection = root / "projections" / f"{sha}.npy"
    try:
        slsbh.load_projection(projection, sha)  # the same check a starting server makes
    except slsbh.ProjectionError as e:
        out.problems.append(f"projection: {e}")
    for rec in catalog.list_snapshots(record.map_id):
        try:
            snapshots.verify(catalog.snapshot_dir(rec))
            out.snapshots_ok.append(rec.snapshot_id)
        except snapshots.SnapshotInvalid as e:
            out.snapshots_bad[rec.snapshot_id] = str(e)
    try:
        with MapStore.open(Path(root) / "maps" / record.map_id / "map.sqlite", readonly=True) as store:
            if not store.integrity_check():
                out.problems.append("map.sqlite fails PRAGMA integrity_check")
            total = store.count()
            done = rebuild(TemporalMemory(record.params["tm"]), store.rows(), stop_at_mismatch=False,
                           progress=None if progress is None else lambda n: progress(n, total))
            out.rows, out.mismatches = done.replayed, done.mismatches
    except (StorageError, OSError) as e:
        out.problems.append(f"map.sqlite unreadable: {e}")
    out.seconds = time.perf_counter() - t0
    return out
