"""catalog.sqlite: maps, states, snapshot registry (newest first), seq high-water marks."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from storage.catalog import Catalog, MapExists, MapNotFound, SnapshotRecord


def snap(map_id: str, sid: str, seq: int, kind: str = "manual") -> SnapshotRecord:
    return SnapshotRecord(snapshot_id=sid, map_id=map_id, seq=seq, kind=kind,
                          created_at="2025-01-01T00:00:00.000000Z", bytes=100 + seq,
                          manifest_sha256="cd" * 32, path=f"maps/{map_id}/snapshots/{sid}")


@pytest.fixture
def catalog(tmp_path: Path) -> Catalog:
    c = Catalog.open(tmp_path / "catalog.sqlite")
    yield c
    c.close()


def test_map_crud(catalog: Catalog, tmp_path: Path) -> None:
    params = {"tm": {"cellsPerColumn": 4}, "seed": 1}
    rec = catalog.create_map("lab", params, preset="cortexloc-default", state="recovering")
    assert rec.state == "recovering" and rec.params == params and rec.seq_high_water == 0
    assert catalog.get_map("lab") == rec
    assert catalog.get_map("nope") is None
    with pytest.raises(MapExists):
        catalog.create_map("lab", {})
    catalog.create_map("yard", {})
    assert [m.map_id for m in catalog.list_maps()] == ["lab", "yard"]

    failed = catalog.set_state("lab", "failed", "replay-divergence")
    assert (failed.state, failed.state_reason) == ("failed", "replay-divergence")
    assert catalog.set_state("lab", "ready").state_reason is None
    with pytest.raises(ValueError):
        catalog.set_state("lab", "sleeping")  # type: ignore[arg-type]
    with pytest.raises(MapNotFound):
        catalog.set_state("nope", "ready")

    # Durable and reopenable, with WAL + FULL like the map files.
    catalog.close()
    again = Catalog.open(tmp_path / "catalog.sqlite")
    assert again.get_map("lab").state == "ready"
    assert sqlite3.connect(tmp_path / "catalog.sqlite").execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    again.delete_map("yard")
    assert again.get_map("yard") is None
    with pytest.raises(MapNotFound):
        again.delete_map("yard")
    again.close()


def test_a_restore_raises_the_marks_and_counts_itself(catalog: Catalog) -> None:
    catalog.create_map("lab", {})
    fresh = catalog.get_map("lab")
    assert (fresh.seq_high_water, fresh.closure_high_water, fresh.restores) == (0, 0, 0)
    marked = catalog.mark_restore("lab", 12, 40)
    assert (marked.seq_high_water, marked.closure_high_water, marked.restores) == (12, 40, 1)
    again = catalog.mark_restore("lab", 5, 7)  # never lowered; every restore counts
    assert (again.seq_high_water, again.closure_high_water, again.restores) == (12, 40, 2)
    assert catalog.get_map("lab") == again
    with pytest.raises(MapNotFound):
        catalog.mark_restore("nope", 1, 1)


def test_a_rewrite_changes_the_epoch_and_a_map_without_one_keeps_the_epoch_it_had(catalog: Catalog) -> None:
    made = catalog.create_map("lab", {})
    assert made.epoch == f"{made.created_at}/0"  # as before rewrites were counted: no follower rebuilds
    assert catalog.mark_rewrite("lab").epoch == f"{made.created_at}/0/1"
    assert catalog.mark_repaired("lab", 9).repaired_below == 9
    assert catalog.mark_repaired("lab", 4).repaired_below == 9  # never lowered
    assert catalog.mark_restore("lab", 1, 1).epoch == f"{made.created_at}/1/1"
    assert catalog.get_map("lab").repaired_below == 0  # a restore's log is another: nothing judged
    again = catalog.mark_rewrite("lab")  # every rewrite counts
    assert (again.rewrites, again.epoch) == (2, f"{made.created_at}/1/2")
    with pytest.raises(MapNotFound):
        catalog.mark_rewrite("nope")
    with pytest.raises(MapNotFound):
        catalog.mark_repaired("nope", 1)


def test_a_version_1_catalog_gains_the_closure_mark_and_the_restore_count(tmp_path) -> None:
    path = tmp_path / "catalog.sqlite"
    old = sqlite3.connect(path)  # the version 1 schema, as written before the closure mark
    old.executescript("""
        CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
        INSERT INTO meta VALUES ('schema_version', '1');
        CREATE TABLE maps (map_id TEXT PRIMARY KEY, created_at TEXT NOT NULL, state TEXT NOT NULL,
            state_reason TEXT NULL, preset TEXT NULL, params TEXT NOT NULL,
            seq_high_water INTEGER NOT NULL DEFAULT 0);
        INSERT INTO maps VALUES ('lab', '2026-01-01T00:00:00Z', 'ready', NULL, NULL, '{}', 9);""")
    old.commit()
    old.close()
    with Catalog.open(path, readonly=True) as ro:  # read as it is: no columns yet, nothing restored
        assert (ro.get_map("lab").seq_high_water, ro.get_map("lab").restores) == (9, 0)
    with Catalog.open(path) as catalog:
        rec = catalog.mark_restore("lab", 3, 5)
        assert rec.epoch == "2026-01-01T00:00:00Z/1"
        rewritten = catalog.mark_rewrite("lab")  # version 3's columns too
        assert catalog.mark_repaired("lab", 7).repaired_below == 7
    assert (rec.seq_high_water, rec.closure_high_water, rec.restores) == (9, 5, 1)
    assert (rewritten.restores, rewritten.rewrites, rewritten.epoch) == (1, 1, "2026-01-01T00:00:00Z/1/1")
    with sqlite3.connect(path) as conn:
        assert conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0] == "3"


def test_snapshot_registry(catalog: Catalog) -> None:
    catalog.create_map("lab", {})
    catalog.create_map("yard", {})
    catalog.register_snapshot(snap("lab", "s1", 10, "auto"))
    catalog.register_snapshot(snap("lab", "s2", 20, "pre-restore"))
    catalog.register_snapshot(snap("lab", "s3", 10, "manual"))  # after a restore: lower seq, newer
    catalog.register_snapshot(snap("yard", "s1", 3))  # ids are per map
    assert [s.snapshot_id for s in catalog.list_snapshots("lab")] == ["s3", "s2", "s1"]
    assert [s.snapshot_id for s in catalog.list_snapshots("lab", kind="auto")] == ["s1"]
    assert catalog.get_snapshot("lab", "s2") == snap("lab", "s2", 20, "pre-restore")
    assert catalog.get_snapshot("lab", "zz") is None
    assert catalog.snapshots_bytes("lab") == 110 + 120 + 110
    with pytest.raises(ValueError):
        catalog.register_snapshot(snap("lab", "s1", 11))  # duplicate id
    with pytest.raises(ValueError):
        catalog.register_snapshot(snap("lab", "s9", 1, "hourly"))
    with pytest.raises(MapNotFound):
        catalog.register_snapshot(snap("nope", "s1", 1))

    assert catalog.delete_snapshot("lab", "s2") is True
    assert catalog.delete_snapshot("lab", "s2") is False
    assert [s.snapshot_id for s in catalog.list_snapshots("lab")] == ["s3", "s1"]

    # Deleting a map removes its registrations (and returns them so their files can go too).
    gone = catalog.delete_map("lab")
    assert [s.snapshot_id for s in gone] == ["s3", "s1"]
    assert catalog.list_snapshots("lab") == []
    assert [s.snapshot_id for s in catalog.list_snapshots("yard")] == ["s1"]
    catalog.create_map("lab", {})  # a new map with the old id starts clean
    assert catalog.list_snapshots("lab") == [] and catalog.get_map("lab").restores == 0


def test_snapshot_paths_are_stored_relative_to_the_data_directory(catalog: Catalog, tmp_path: Path) -> None:
    catalog.create_map("lab", {})
    inside = tmp_path / "maps" / "lab" / "snapshots" / "s1"
    catalog.register_snapshot(SnapshotRecord(**{**snap("lab", "s1", 1).__dict__, "path": str(inside)}))
    rec = catalog.get_snapshot("lab", "s1")
    assert rec.path == "maps/lab/snapshots/s1" and catalog.snapshot_dir(rec) == tmp_path / rec.path
    for outside in ("/elsewhere/maps/lab/snapshots/s2", "maps/../../x/s2"):
        with pytest.raises(ValueError):
            catalog.register_snapshot(SnapshotRecord(**{**snap("lab", "s2", 2).__dict__, "path": outside}))


def test_a_catalog_write_is_one_transaction_until_it_returns(catalog: Catalog, tmp_path: Path) -> None:
    # sqlite-utils writes inside the catalog's BEGIN IMMEDIATE as savepoints: nothing is committed (seen
    # by another connection) before the block ends, and an error rolls every statement of it back.
    other = sqlite3.connect(tmp_path / "catalog.sqlite")
    with pytest.raises(RuntimeError), catalog._write() as db:
        db["maps"].insert({"map_id": "half", "created_at": "t", "state": "ready", "params": "{}"})
        db["maps"].update("half", {"state": "failed"})
        assert other.execute("SELECT count(*) FROM maps").fetchone()[0] == 0
        raise RuntimeError("stop")
    assert other.execute("SELECT count(*) FROM maps").fetchone()[0] == 0 and catalog.get_map("half") is None
    other.close()
