"""Rebuilding a map's memory from its store: the one path that recovery at startup, restore, the
commit-failure path and `cortexloc verify` share (docs/design/service.md §4.4).

A rebuild starts from a fresh memory (replay from the first row) or from a snapshot's arrays, then
replays the store's rows and visits (consolidated frames, docs/design/science.md §11.8) after that point,
in the order they were learned, comparing every replayed step's winner cells with the stored ones
(`rebuild`). `recover` picks the start: the newest snapshot on the store's branch that
verifies, loads and reproduces the rows after it, else a replay from the first row; then each replayed
stream resumes its place from the state its last learned step stored (`MapStore.stream_states`).
"""

from __future__ import annotations

import itertools
import logging
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from models import pipeline
from models.frontend import slsbh
from models.memory.temporal_memory import TemporalMemory
from models.pipeline import MapModel, Stream, load_memory_state
from service.maps.config import MapConfig, map_model
from service.maps.errors import InvalidConfiguration
from storage import snapshots
from storage.catalog import Catalog, MapRecord, SnapshotRecord, StorageError
from storage.layout import Layout
from storage.mapstore import MapStore, Observation, Visit

__all__ = ["VISIT_CURSOR", "VISIT_MARK", "MapCheck", "Rebuilt", "Replay", "Tail", "begin", "check_memory",
           "in_order", "learned_rows", "load_memory", "open_catalog", "rebuild", "recover", "remade_rows",
           "snapshot_array", "verify_map"]

#: The snapshot array holding the last visit id its memory learned (0 in a snapshot made before visits),
#: and that visit's `MapStore.visit_mark` (the branch check of visits, as a row's observation id is).
VISIT_CURSOR = "visit_cursor"
VISIT_MARK = "visit_mark"

log = logging.getLogger("cortexloc.recovery")
_LISTED = 20  # divergent seqs listed in a recovery note (the count says how many there are)


def snapshot_array(name: str) -> bool:
    """Whether a snapshot's memory holds an array of this name: `memory_state`'s, the visit cursor and
    its mark (what `Snapshots.snapshot` writes)."""
    return name in (VISIT_CURSOR, VISIT_MARK) or pipeline.memory_name(name)


def load_memory(path: Path) -> dict[str, np.ndarray]:
    """The arrays of the snapshot at `path` (`storage.snapshots.load_memory`): a member of a name no
    memory writes, compressed, or declaring more than it holds is refused (SnapshotInvalid) before its
    data is read."""
    return snapshots.load_memory(path, known=snapshot_array)


def check_memory(path: Path) -> None:
    """`load_memory`'s checks without reading any array: SnapshotInvalid (import, restore, `cortexloc
    verify`)."""
    snapshots.check_memory(path, known=snapshot_array)


@dataclass
class Rebuilt:
    """The outcome of `rebuild`.

    Attributes:
        model, streams: the rebuilt memory (its index and links empty: rebuilt from the rows by the
            caller) and stream states.
        replayed: rows replayed (after the snapshot, if any).
        mismatches: seqs whose replayed winner cells differ from the stored ones, in seq order.
        last_seq: the last row replayed (the start's seq when none was).
        covered: the last visit id the start's memory had learned (a snapshot's `VISIT_CURSOR`).
        visits: visits replayed.
        replayed_streams: the streams whose rows or visits were replayed.
    """

    model: MapModel
    streams: OrderedDict[str, Stream]
    replayed: int = 0
    mismatches: list[int] = field(default_factory=list)
    last_seq: int = 0
    covered: int = 0
    visits: int = 0
    replayed_streams: set[str] = field(default_factory=set)


def in_order(rows: Iterable[Observation], visits: Iterable[Visit]) -> Iterator[Observation | Visit]:
    """Rows (seq order) and visits (log order) merged as they were learned: a visit after the row
    `after_seq` and before the next."""
    pending = iter(visits)
    visit = next(pending, None)
    for row in rows:
        while visit is not None and visit.after_seq < row.seq:
            yield visit
            visit = next(pending, None)
        yield row
    while visit is not None:
        yield visit
        visit = next(pending, None)


def remade_rows(store: MapStore, after_seq: int = 0) -> set[int]:
    """The rows after `after_seq` a repair re-made from a visit (docs/design/science.md §11.6): stored rows
    the memory did not learn as rows (their visit taught it, and replays): no learned frame of their own."""
    return {r.seq for r in store.repairs() if r.kind == "split" and r.seq > after_seq}


def learned_rows(store: MapStore, after_seq: int = 0) -> Iterator[Observation]:
    """The rows after `after_seq` the memory learned as rows, in seq order (less `remade_rows`)."""
    remade = remade_rows(store, after_seq)
    return (r for r in store.rows(after_seq=after_seq) if r.seq not in remade)


class Replay:
    """A replay that can run in slices (docs/design/service.md §4.4): `rebuild`'s loop, resumable, so the
    map's writer can answer localising frames between slices while a recovery's tail replays.

    Args: as `rebuild`'s.
    """

    def __init__(self, start: TemporalMemory | Mapping[str, np.ndarray], rows: Iterable[Observation],
                 like: MapModel, *, stop_at_mismatch: bool = True,
                 progress: Callable[[int], None] | None = None, visits: Iterable[Visit] = ()) -> None:
        if isinstance(start, TemporalMemory):
            tm, streams, covered = start, OrderedDict(), 0
        else:
            tm, streams = load_memory_state(start, like.adapt_tau, like.condition_frames)
            covered = int(start.get(VISIT_CURSOR, 0))
        self.out = Rebuilt(like.fresh(tm), streams, covered=covered)
        self.stop_at_mismatch, self.progress = stop_at_mismatch, progress
        self._pending = in_order(rows, visits)
        self.finished = False

    def run(self, steps: int | None = None) -> bool:
        """Replay the next `steps` rows and visits (None: all); True once the replay is over (every row
        replayed, or a mismatch with `stop_at_mismatch`)."""
        out = self.out
        model = out.model
        for row in self._pending if steps is None else itertools.islice(self._pending, steps):
            st = out.streams.get(row.stream)
            if st is None:
                st = out.streams[row.stream] = Stream()
            out.streams.move_to_end(row.stream)  # most recently used last, as the live map keeps them
            out.replayed_streams.add(row.stream)
            prev = row.context_prev_seq
            if isinstance(row, Visit) and row.row is None:
                winners = pipeline.revisit(model, st, row.input_sdr, row=row.seq, prev_seq=prev)
                out.visits += 1
            elif isinstance(row, Visit):  # a row a warm-up join turned into a visit: the row's step (§11.8)
                winners = pipeline.replay(model, st, row.input_sdr, seq=row.row, prev_seq=prev)
                out.replayed += 1
            else:
                winners = pipeline.replay(model, st, row.input_sdr, seq=row.seq, prev_seq=prev)
                out.replayed += 1
                out.last_seq = row.seq
            if not np.array_equal(winners, row.winner_cells):
                out.mismatches.append(row.row if isinstance(row, Visit) and row.row is not None else row.seq)
                if self.stop_at_mismatch:
                    self.finished = True
                    return True
            if self.progress is not None:
                self.progress(out.replayed)
            steps = None if steps is None else steps - 1
        # islice stopped early only when its count ran out; otherwise the rows are exhausted
        self.finished = steps is None or steps > 0
        return self.finished


def rebuild(start: TemporalMemory | Mapping[str, np.ndarray], rows: Iterable[Observation], like: MapModel, *,
            stop_at_mismatch: bool = True, progress: Callable[[int], None] | None = None,
            visits: Iterable[Visit] = ()) -> Rebuilt:
    """Replay `rows` (in seq order) on a fresh memory or a snapshot's arrays, checking each step.

    Each row goes through `models.pipeline.replay`, the step and the stream bookkeeping the writer's
    `models.pipeline.observe` gave it. A localisation stream lives only in snapshots (its frames are not
    rows): one held by the snapshot comes back with its context and its localiser state, so it answers as
    it would have without the restart; after a replay from the first row it starts afresh
    (docs/design/service.md §1.2).

    Args:
        start: a fresh `TemporalMemory` (used in place) or the arrays of a snapshot's `memory.npz`.
        rows: the observations after the start (all of them for a fresh memory).
        visits: the visits after the start (`models.pipeline.revisit`; a mismatch is listed by the seq of
            the row it was consolidated into).
        like: the map's model whose options (memory kind, adaptation, ...) and index and links sizes the
            rebuilt one takes; it is not changed.
        stop_at_mismatch: stop at the first divergent row (recovery tries an older start then);
            False replays every row and lists every divergent seq (`cortexloc verify`, the last resort).
        progress: called with the number of rows replayed so far, once per row.

    Returns:
        The rebuilt memory (empty index and links), and what the replay found.
    """
    replay = Replay(start, rows, like, stop_at_mismatch=stop_at_mismatch, progress=progress, visits=visits)
    replay.run()
    return replay.out


def _snapshot_start(store: MapStore, catalog: Catalog, rec: SnapshotRecord
                    ) -> tuple[snapshots.Manifest, dict[str, np.ndarray]] | None:
    """Snapshot `rec` as the start of a replay of `store`: (its manifest, its memory arrays); None when it
    is from a branch a restore abandoned (its last row, or its last visit, is not this store's).

    Raises:
        SnapshotInvalid, OSError, ValueError: it cannot be used (damaged, unreadable, a memory
            `load_memory` refuses, or the visits after it were pruned: the store's
            `visits_pruned_through` is past its visit cursor).
    """
    path = catalog.snapshot_dir(rec)
    m = snapshots.verify(path)
    if m.seq > 0 and store.observation_id(m.seq) != m.last_observation_id:  # (held or joined away)
        return None
    memory = load_memory(path)
    cursor = int(memory.get(VISIT_CURSOR, 0))
    last = store.visit_stats()[2]
    mark = store.visit_mark(cursor) if cursor else None
    if cursor and mark != str(memory.get(VISIT_MARK, "")) and (cursor > last or mark is not None):
        return None  # its visits are from a branch a restore abandoned
    pruned = store.visits_pruned_through()
    if pruned > cursor:  # visits it did not learn were pruned meanwhile
        raise ValueError(f"visits after {cursor} were pruned (through {pruned})")
    return m, memory


@dataclass
class Tail:
    """A recovery begun at a snapshot, its replay of the rows and visits after it not yet run (`begin`):
    the map localises from the replay's memory while the writer runs it in slices (§4.4), then `recover`
    finishes it.

    Attributes:
        replay: the replay from the snapshot (its `out.model` and `out.streams` are the memory).
        snapshot_id, snapshot_seq: the snapshot it starts from.
        steps: rows and visits to replay.
        tried: the snapshots looked at by `begin` (this one included): a fallback tries the others.
        skipped: those passed over, and why (the recovery note's `skipped_snapshots`).
        t0: when the recovery began (`time.perf_counter`).
    """

    replay: Replay
    snapshot_id: str
    snapshot_seq: int
    steps: int
    tried: set[str]
    skipped: list[dict[str, str]]
    t0: float


def _pass_over(map_id: str, snapshot_id: str, reason: str, skipped: list[dict[str, str]]) -> None:
    skipped.append({"snapshot_id": snapshot_id, "reason": reason})
    log.warning("map %s: snapshot %s passed over: %s", map_id, snapshot_id, reason)


def begin(store: MapStore, catalog: Catalog, map_id: str, like: MapModel) -> Tail | None:
    """The newest snapshot of `store` that verifies and loads (`load_memory`), as the start of its replay
    (not run); None when there is none (`recover` then replays from the first row). One from a branch a
    restore abandoned is skipped silently, a damaged one passed over (`Tail.skipped`)."""
    t0 = time.perf_counter()
    tried: set[str] = set()
    skipped: list[dict[str, str]] = []
    for rec in catalog.list_snapshots(map_id):
        tried.add(rec.snapshot_id)
        try:
            start = _snapshot_start(store, catalog, rec)
            if start is None:
                continue  # from a branch a restore abandoned
            m, memory = start
            cursor = int(memory.get(VISIT_CURSOR, 0))
            replay = Replay(memory, learned_rows(store, m.seq), like,
                            visits=store.visits(after_id=cursor, rows_after=m.seq))
        except Exception as e:  # an unusable snapshot is passed over, never fatal
            _pass_over(map_id, rec.snapshot_id, str(e) or type(e).__name__, skipped)
            continue
        steps = (store.count_after(m.seq) - len(remade_rows(store, m.seq))
                 + max(0, store.visit_stats()[2] - cursor))
        return Tail(replay, rec.snapshot_id, m.seq, steps, tried, skipped, t0)
    return None


def recover(store: MapStore, catalog: Catalog, map_id: str, like: MapModel, *,
            begun: Tail | None = None) -> tuple[Rebuilt, dict[str, Any]]:
    """The memory of `store`: the newest usable snapshot, then a verified replay of the rows after it.

    A snapshot that does not verify, cannot be loaded (a memory `load_memory` refuses among the
    reasons), or whose replay does not reproduce the stored winner cells is passed over for the next
    older one; one from a branch a restore abandoned (its last
    row is not this store's row at that seq) is skipped silently. The last resort is a replay from the
    first row on a fresh memory: it is served, and the rows whose stored winner cells it did not
    reproduce are listed.

    Args:
        store: the map's open store (the system of record).
        catalog: lists the map's snapshots, newest first.
        map_id: the map.
        like: the map's model (`rebuild`); its TM's parameters make the fresh memory of the last resort.
        begun: a recovery `begin` started (its replay run in part, or whole, by the caller): it is
            finished here, and the snapshots it looked at are not tried again.

    Returns:
        (the rebuilt memory, the note the map resource shows as `recovery`).
    """
    t0 = begun.t0 if begun is not None else time.perf_counter()
    skipped: list[dict[str, str]] = list(begun.skipped) if begun is not None else []
    done: Rebuilt | None = None
    if begun is not None:
        begun.replay.run()
        if not begun.replay.out.mismatches:
            done = begun.replay.out
            note: dict[str, Any] = {"source": "snapshot", "snapshot_id": begun.snapshot_id,
                                    "snapshot_seq": begun.snapshot_seq}
        else:
            _pass_over(map_id, begun.snapshot_id,
                       f"the replay after it diverged at seq {begun.replay.out.mismatches[0]}", skipped)
    for rec in catalog.list_snapshots(map_id) if done is None else ():
        if begun is not None and rec.snapshot_id in begun.tried:
            continue
        try:
            start = _snapshot_start(store, catalog, rec)
            if start is None:
                continue  # from a branch a restore abandoned
            m, memory = start
            done = rebuild(memory, learned_rows(store, m.seq), like,
                           visits=store.visits(after_id=int(memory.get(VISIT_CURSOR, 0)), rows_after=m.seq))
        except Exception as e:  # an unusable snapshot is passed over, never fatal
            reason = str(e) or type(e).__name__
        else:
            if not done.mismatches:
                note = {"source": "snapshot", "snapshot_id": rec.snapshot_id, "snapshot_seq": m.seq}
                break
            reason = f"the replay after it diverged at seq {done.mismatches[0]}"
            done = None  # its memory is as large as the map's: free it before the next attempt
        _pass_over(map_id, rec.snapshot_id, reason, skipped)
    if done is None:
        done = rebuild(TemporalMemory(like.tm.options), learned_rows(store), like, stop_at_mismatch=False,
                       visits=store.visits())
        note = {"source": "replay", "mismatches": len(done.mismatches),
                "mismatched_seqs": done.mismatches[:_LISTED]}
        pruned = store.visits_pruned_through()
        if pruned:
            # The visits that taught the memory before the prune cursor are gone (a snapshot covered
            # them, and none that does is usable now): the replay serves every row, but its memory
            # lacks what they taught, which matching winner cells do not show (§4.4).
            note.update(complete=False, visits_pruned_through=pruned)
            log.error("map %s: no usable snapshot covers the visits pruned through id %d; the replay from "
                      "the first row serves every row but cannot reproduce what those visits taught",
                      map_id, pruned)
        if done.mismatches:
            log.error("map %s: the replay from the first row did not reproduce the stored winner cells "
                      "of %d row(s), first seq %d; serving the replayed memory (run `cortexloc verify`)",
                      map_id, len(done.mismatches), done.mismatches[0])
    note.update(replayed=done.replayed, visits_replayed=done.visits,
                resumed_streams=_resume(store, done, like), skipped_snapshots=skipped,
                seconds=round(time.perf_counter() - t0, 3))
    return done, note


def _resume(store: MapStore, done: Rebuilt, like: MapModel) -> int:
    """Give each replayed stream back what its replay cannot (its localiser state, its adaptation),
    as its last learned step stored it: it resumes its place as after a clean shutdown, whose snapshot
    holds it (docs/design/service.md §4.4). Returns how many streams resumed. A stream without one (its
    state pruned with an older snapshot the recovery passed over, or a file before schema 7) keeps the
    start's state and finds its place again (a warm-up)."""
    resumed = 0
    for name, packed in store.stream_states().items():
        st = done.streams.get(name)
        # A reset after a stream's last learned step (no row records it) holds whether or not the stream
        # had rows to replay: one restored from the snapshot alone is reset too (an outside probe: a
        # reset answered 200, then a kill, and the stream went on with its old sequence).
        if st is not None and (name in done.replayed_streams or pipeline.was_reset(packed)):
            pipeline.resume(st, packed, like.adapt_tau)
            resumed += 1
    return resumed


@dataclass
class MapCheck:
    """What `verify_map` found for one map.

    Attributes:
        map_id: the map.
        rows: rows replayed and compared.
        mismatches: seqs whose stored winner cells the replay from the first row did not reproduce.
        snapshots_ok: ids of the snapshots whose every checksum verified.
        snapshots_bad: snapshot id -> why it does not verify.
        problems: anything else wrong (store unreadable or damaged, projection missing or changed, a
            pruned visit log that no usable snapshot covers, a warm-up join that does not hold).
        start: the snapshot the replay started from (None: the first row): once visits were pruned
            (`MapStore.visits_pruned_through`), the earliest usable one that covers them (§4.4); the rows
            up to its seq are then not replayed.
        seconds: wall time of the check.
    """

    map_id: str
    rows: int = 0
    mismatches: list[int] = field(default_factory=list)
    snapshots_ok: list[str] = field(default_factory=list)
    snapshots_bad: dict[str, str] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    start: str | None = None
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return not (self.mismatches or self.snapshots_bad or self.problems)


def _covering(store: MapStore, catalog: Catalog, map_id: str
              ) -> tuple[str, snapshots.Manifest, dict[str, np.ndarray]] | None:
    """The earliest usable snapshot of `store` that covers its pruned visits: (its id, manifest, memory
    arrays); None: there is none."""
    for rec in reversed(catalog.list_snapshots(map_id)):
        try:
            start = _snapshot_start(store, catalog, rec)
        except Exception:  # damaged (listed in snapshots_bad), unreadable, or before the prune cursor
            continue
        if start is not None:
            return rec.snapshot_id, *start
    return None


def open_catalog(data_dir: Path) -> Catalog:
    """The catalog of a data directory, read-only (`cortexloc verify` while the server may run)."""
    return Catalog.open(Layout(data_dir).catalog, readonly=True)


def verify_map(catalog: Catalog, record: MapRecord, *,
               progress: Callable[[int, int], None] | None = None) -> MapCheck:
    """The offline full check of one map (`cortexloc verify`), changing nothing on disk: the store's
    integrity, its warm-up joins (`MapStore.join_problems`, docs/design/science.md §11.8), a replay from the
    first row comparing every row's stored winner cells (from the earliest
    usable snapshot that covers the pruned visits once some were: `MapCheck.start`, §4.4), every
    snapshot's checksums and memory (`check_memory`), and the projection's SHA-256.

    Args:
        catalog: the data directory's catalog (opened read-only).
        record: the map.
        progress: called with (rows replayed, rows the replay steps: `_replayed_rows`).
    """
    t0 = time.perf_counter()
    out = MapCheck(record.map_id)
    layout = catalog.layout
    sha = str(record.params.get("projection_sha256", ""))
    projection = layout.projection(sha)
    try:
        slsbh.load_projection(projection, sha)  # the same check a starting server makes
    except slsbh.ProjectionError as e:
        out.problems.append(f"projection: {e}")
    for rec in catalog.list_snapshots(record.map_id):
        try:
            snapshots.verify(catalog.snapshot_dir(rec))
            check_memory(catalog.snapshot_dir(rec))
            out.snapshots_ok.append(rec.snapshot_id)
        except snapshots.SnapshotInvalid as e:
            out.snapshots_bad[rec.snapshot_id] = str(e)
    try:
        with MapStore.open(layout.map_db(record.map_id), readonly=True) as store:
            if not store.integrity_check():
                out.problems.append("map.sqlite fails PRAGMA integrity_check")
            total = store.count()
            config = MapConfig.parse(record.params)
            like = map_model(config, max_observations=max(total, 1))
            out.problems += store.join_problems(like.place_map.reach())
            start: TemporalMemory | Mapping[str, np.ndarray] | None = like.tm
            after_seq = after_id = 0
            pruned = store.visits_pruned_through()
            if pruned:  # a replay from the first row would lack them: start at a snapshot that covers them
                found = _covering(store, catalog, record.map_id)
                if found is None:
                    out.problems.append(f"the visit log was pruned through id {pruned} and no usable "
                                        "snapshot covers it: the memory cannot be replayed")
                    start = None
                else:
                    out.start, m, memory = found
                    start, after_seq, after_id = memory, m.seq, int(memory.get(VISIT_CURSOR, 0))
            if start is not None:
                steps = 0 if progress is None else _replayed_rows(store, after_seq, after_id)
                done = rebuild(start, learned_rows(store, after_seq), like, stop_at_mismatch=False,
                               visits=store.visits(after_id=after_id, rows_after=after_seq),
                               progress=None if progress is None else lambda n: progress(n, steps))
                out.rows, out.mismatches = done.replayed, done.mismatches
    except (StorageError, OSError) as e:
        out.problems.append(f"map.sqlite unreadable: {e}")
    except InvalidConfiguration as e:
        out.problems.append(f"configuration: {e}")
    out.seconds = time.perf_counter() - t0
    return out


def _replayed_rows(store: MapStore, after_seq: int, after_id: int) -> int:
    """How many rows a replay after row `after_seq` and visit `after_id` steps (`Replay.out.replayed`, what
    `verify`'s progress counts): those it learns as rows (`learned_rows`: the stored rows less those a
    repair re-made) and the rows a warm-up join turned into visits (§11.8), not the rows held."""
    joined = sum(1 for v in store.visits(after_id=after_id, rows_after=after_seq) if v.row is not None)
    return store.count_after(after_seq) - len(remade_rows(store, after_seq)) + joined
