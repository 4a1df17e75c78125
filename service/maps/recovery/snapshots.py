"""Snapshots at the map level: take one, list, find, prune the automatic ones, import a downloaded tar
(docs/design/service.md §1.5, §4.4). The files themselves are `storage.snapshots`'s business."""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from models.frontend import slsbh
from service.maps.config import MapConfig
from service.maps.errors import InsufficientStorage, InvalidConfiguration, SnapshotInUse, SnapshotNotFound
from service.maps.recovery.memory import check_memory, remade_rows
from service.maps.results import SnapshotInfo
from storage import snapshots
from storage.catalog import Catalog, Lineage, SnapshotKind, SnapshotRecord, utc_now
from storage.layout import Layout
from storage.manifest import parse_manifest
from storage.mapstore import MapStore, StorageFull

__all__ = ["TarExport", "delete", "disk_use", "export", "import_snapshot", "info", "learned_difference",
           "listing", "locate", "prune_auto", "prune_kept", "recovery_base", "take"]

#: A snapshot as a tar stream: `size`, `chunks()`, `close()` (storage.archive).
TarExport = snapshots.TarExport

log = logging.getLogger("cortexloc.snapshots")


def info(rec: SnapshotRecord) -> SnapshotInfo:
    return SnapshotInfo(snapshot_id=rec.snapshot_id, seq=rec.seq, kind=rec.kind, created_at=rec.created_at,
                        bytes=rec.bytes, manifest_sha256=rec.manifest_sha256)


def disk_use(catalog: Catalog, map_id: str) -> dict[str, int]:
    """`snapshot_count` and `snapshots_bytes` of the map (every kind), for its resource and /metrics."""
    recs = catalog.list_snapshots(map_id)
    return {"snapshot_count": len(recs), "snapshots_bytes": sum(r.bytes for r in recs)}


def listing(catalog: Catalog, map_id: str) -> list[SnapshotInfo]:
    """The map's snapshots, newest first."""
    return [info(r) for r in catalog.list_snapshots(map_id)]


def locate(catalog: Catalog, map_id: str, snapshot_id: str) -> tuple[SnapshotRecord, Path]:
    """The snapshot's record and directory. Raises SnapshotNotFound."""
    rec = catalog.get_snapshot(map_id, snapshot_id)
    if rec is None:
        raise SnapshotNotFound(map_id, snapshot_id)
    return rec, catalog.snapshot_dir(rec)


def export(directory: Path, projection: Path) -> TarExport:
    """The snapshot at `directory` (`locate`) with the map's projection as a tar, streamed from the
    files with no copy. Blocks while every checksum is verified, before the first byte (a worker thread,
    not the writer). Raises SnapshotInvalid."""
    return TarExport(directory, {snapshots.PROJECTION_FILE: projection})


def take(store: MapStore, memory: Mapping[str, np.ndarray], catalog: Catalog, map_id: str,
         projection_path: Path, kind: str) -> SnapshotInfo:
    """A consistent cut at the store's current seq, with the memory's arrays; registered in the catalog.
    It goes where the catalog's `Layout` puts the map's snapshots.

    Raises:
        InsufficientStorage: no room to write (nothing is left behind).
    """
    sid = snapshots.new_snapshot_id()
    dest = catalog.layout.snapshot_dir(map_id, sid)
    dest.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    try:
        record = catalog.get_map(map_id)
        # the map's epoch and id marks travel with it: a move keeps both (docs/design/service.md §1.2)
        lineage = None if record is None else record.lineage(store.next_seq() - 1, store.last_closure_id())
        m = snapshots.create_snapshot(store, dict(memory), dest, kind=kind,
                                      external={snapshots.PROJECTION_FILE: projection_path}, lineage=lineage)
    except StorageFull as e:
        raise InsufficientStorage(f"the {kind} snapshot could not be written: no room to write; the map "
                                  "is unchanged") from e
    rec = catalog.register_snapshot(SnapshotRecord(
        snapshot_id=m.snapshot_id, map_id=map_id, seq=m.seq, kind=kind, created_at=m.created_at,
        bytes=m.bytes, manifest_sha256=m.manifest_sha256, path=str(dest)))
    log.info("map %s: %s snapshot %s at seq %d in %.2f s", map_id, kind, sid, m.seq, time.perf_counter() - t0)
    return info(rec)


def learned_difference(present: MapStore, snapshot: MapStore) -> tuple[int, int]:
    """(learned frames `present` holds that `snapshot` does not, those `snapshot` holds that `present` does
    not): what a restore from `snapshot` takes away and brings back (docs/design/service.md §1.5).

    A learned frame is a row, by its seq (held, dropped or joined: seqs are never handed out twice, across
    restores too), or a consolidated visit, by its id and mark (ids are handed out again on another
    branch); a row a repair split off a visit is that visit. Whole sets are compared, not the seqs after
    the snapshot's: after a restore, a frame of an earlier branch can have a lower seq than one kept.
    Visits are compared from the oldest both still log (pruning keeps the newest; below that one file
    cannot tell). Both are read in order, in pages: the memory is bounded whatever the map's size."""
    rows = _only_in_each(_unsplit(present), _unsplit(snapshot))
    first = max(present.visit_stats()[1], snapshot.visit_stats()[1])
    visits = _only_in_each(present.consolidated_visits(first), snapshot.consolidated_visits(first))
    return rows[0] + visits[0], rows[1] + visits[1]


def _unsplit(store: MapStore) -> Iterator[int]:
    """`learned_seqs` less the rows a repair split off a visit (docs/design/science.md §11.6): that frame is
    its visit, counted with the visits (as the replay counts it once)."""
    split = remade_rows(store)
    return (seq for seq in store.learned_seqs() if seq not in split)


def _only_in_each(a: Iterator[Any], b: Iterator[Any]) -> tuple[int, int]:
    """How many distinct items of ascending `a` are not in ascending `b`, and of `b` not in `a`."""
    a, b = _distinct(a), _distinct(b)
    only_a = only_b = 0
    x, y = next(a, None), next(b, None)
    while x is not None or y is not None:
        if y is None or (x is not None and x < y):
            only_a, x = only_a + 1, next(a, None)
        elif x is None or y < x:
            only_b, y = only_b + 1, next(b, None)
        else:
            x, y = next(a, None), next(b, None)
    return only_a, only_b


def _distinct(items: Iterator[Any]) -> Iterator[Any]:
    """Ascending `items` without repeats (a row joined and still stored is read twice)."""
    last: Any = None
    for item in items:
        if item != last:
            yield item
        last = item


def _remove(catalog: Catalog, rec: SnapshotRecord) -> None:
    """Unregister first: a crash between the two leaves an unlisted directory, never a listed hole."""
    catalog.delete_snapshot(rec.map_id, rec.snapshot_id)
    shutil.rmtree(catalog.snapshot_dir(rec), ignore_errors=True)


def prune_auto(catalog: Catalog, map_id: str, store: MapStore, keep: int) -> None:
    """Keep the `keep` newest automatic snapshots, and the `recovery_base` whatever its age; manual and
    pre-restore ones stay."""
    old = catalog.list_snapshots(map_id, kind="auto")[keep:]
    base = recovery_base(catalog, map_id, store) if old else None
    for rec in old:
        if rec.snapshot_id != base:
            _remove(catalog, rec)


def recovery_base(catalog: Catalog, map_id: str, store: MapStore) -> str | None:
    """The id of the snapshot the map's next recovery starts from: the newest whose cut is a row of
    `store` (one from a branch a restore abandoned is not, docs/design/service.md §4.4); None: none is."""
    for rec in catalog.list_snapshots(map_id):
        directory = catalog.snapshot_dir(rec)
        try:
            m = parse_manifest((directory / snapshots.MANIFEST_FILE).read_bytes(), str(directory))
        except (OSError, snapshots.SnapshotInvalid):
            continue  # recovery passes over it too
        row = store.get(m.seq) if m.seq > 0 else None
        if m.seq == 0 or (row is not None and row.observation_id == m.last_observation_id):
            return rec.snapshot_id
    return None


def delete(catalog: Catalog, map_id: str, snapshot_id: str, store: MapStore) -> None:
    """Delete one snapshot of any kind (`DELETE /v1/maps/{id}/snapshots/{sid}`).

    Raises:
        SnapshotNotFound. SnapshotInUse: it is the `recovery_base` (nothing is deleted).
    """
    rec, _ = locate(catalog, map_id, snapshot_id)
    if snapshot_id == recovery_base(catalog, map_id, store):
        raise SnapshotInUse(map_id, snapshot_id)
    _remove(catalog, rec)


def prune_kept(catalog: Catalog, map_id: str, store: MapStore, kind: SnapshotKind, keep: int,
               max_bytes: int) -> list[str]:
    """Delete the oldest snapshots of `kind` (`manual`, or `pre-restore`: each kind counted apart) beyond
    the newest `keep` or `max_bytes` in all (0: no such limit), never the newest of the kind (even alone
    over the byte limit: a manual one was just asked for, a pre-restore one holds what its restore took
    away) nor the `recovery_base`. Returns the ids deleted."""
    base = recovery_base(catalog, map_id, store)
    kept = total = 0
    deleted = []
    for i, rec in enumerate(catalog.list_snapshots(map_id, kind=kind)):  # newest first
        kept, total = kept + 1, total + rec.bytes
        if i and rec.snapshot_id != base and ((keep and kept > keep) or (max_bytes and total > max_bytes)):
            _remove(catalog, rec)
            deleted.append(rec.snapshot_id)
            kept, total = kept - 1, total - rec.bytes
    return deleted


def import_snapshot(data_dir: Path, catalog: Catalog, tar_path: Path, max_bytes: int, *,
                    fits: Callable[[snapshots.Manifest], None] = lambda m: None, moved: bool = False) -> str:
    """Create a map from a downloaded snapshot tar (`cortexloc import`, server stopped).

    The map takes the id marks of the manifest's lineage, so no seq or loop-closure id the map had handed
    out when the snapshot was taken is handed out again. `moved`: the map itself, moved here (between
    shards: its owner drained and snapshotted it last), keeps its creation and counts, so its epoch;
    otherwise it is another map, with an epoch of its own (docs/design/service.md §1.2).

    The manifest (the tar's first member) is checked before anything is written: its ids follow
    the API's rules (`storage.snapshots`), the map is new here, and the files it declares fit in
    `max_bytes` and in the free space of the data directory. Every checksum is then verified (the
    snapshot's files, and the projection against the map's recorded SHA-256), and the memory's arrays
    checked by their headers (`check_memory`: known names, stored, no more declared than held), before
    anything is registered; the map recovers from that snapshot when the server
    starts. Every path comes from `Layout(data_dir)`.

    Returns:
        The imported map's id.

    Raises:
        SnapshotInvalid: a bad or too large tar, or a memory `check_memory` refuses. ValueError: the map
            exists, or no projection.
        MemoryBudgetExceeded: from `fits`, which sees the manifest before anything is written.
    """
    layout = Layout(data_dir)

    def acceptable(m: snapshots.Manifest) -> None:
        if catalog.get_map(m.map_id) is not None:
            raise ValueError(f"map {m.map_id!r} exists here already")
        need = sum(e.bytes for e in (*m.files.values(), *m.external.values()))
        free = shutil.disk_usage(data_dir).free
        if need > free:
            raise ValueError(f"the snapshot needs {need} bytes, {data_dir} has {free} free")
        fits(m)

    staging = layout.import_staging(snapshots.new_snapshot_id())  # a start removes it if this is killed
    with tar_path.open("rb") as f:
        manifest = snapshots.import_tar(f, staging, max_bytes=max_bytes, check=acceptable)
    try:
        map_id = manifest.map_id
        try:  # the same gate as a created map's: an option this version rejects is refused here
            config = MapConfig.parse(manifest.params)
        except InvalidConfiguration as e:
            raise snapshots.SnapshotInvalid(f"the snapshot's map configuration: {e}") from e
        check_memory(staging)
        sha = manifest.projection_sha256
        target = layout.projection(sha)
        staged = staging / snapshots.PROJECTION_FILE
        if staged.exists():
            slsbh.load_projection(staged, sha)  # refuses another matrix
            if not target.exists():
                staged.replace(target)
            else:
                staged.unlink()
        if not target.exists():
            raise ValueError(f"the tar holds no projection and {target} is missing")
        layout.map_dir(map_id).mkdir(parents=True)
        MapStore.install_copy(staging / snapshots.DB_FILE, layout.map_db(map_id))
        snap_dir = layout.snapshot_dir(map_id, manifest.snapshot_id)
        snap_dir.parent.mkdir(parents=True)
        staging.replace(snap_dir)
        line = manifest.lineage
        if line is not None and not moved:
            line = Lineage(utc_now(), seq_high_water=line.seq_high_water,
                           closure_high_water=line.closure_high_water)
        catalog.create_map(map_id, config.stored(), preset=config.preset, state="ready", lineage=line)
        catalog.register_snapshot(SnapshotRecord(
            snapshot_id=manifest.snapshot_id, map_id=map_id, seq=manifest.seq, kind=manifest.kind,
            created_at=manifest.created_at, bytes=manifest.bytes,
            manifest_sha256=manifest.manifest_sha256, path=str(snap_dir)))
        return map_id
    finally:
        shutil.rmtree(staging, ignore_errors=True)
