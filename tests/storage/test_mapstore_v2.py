"""map.sqlite version 2 (docs/design/service.md §4.2): per-row metadata, thumbnails and idempotency keys
committed with their row, the bounded key table, and the migration of a version 1 file."""

from __future__ import annotations

import dataclasses
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from storage.mapschema import SCHEMA_VERSION, KeyRecord
from storage.mapstore import MapMeta, MapStore, StorageError
from tests.storage.conftest import make_row
from tests.storage.v1_files import write_v1


def test_metadata_and_thumbnail_round_trip(store: MapStore) -> None:
    meta = {"stamp": 12.5, "pose": {"x": 1.0, "y": -2.0, "yaw": 0.5, "frame_id": "map"}, "note": "dock"}
    seq = store.append(dataclasses.replace(make_row(1), metadata=meta, thumbnail=b"\xff\xd8\xffjpeg"))
    plain = store.append(make_row(2))
    assert store.get(seq).metadata == meta and store.get(plain).metadata is None
    assert [r.metadata for r in store.rows()] == [meta, None]
    assert store.thumbnail(seq) == b"\xff\xd8\xffjpeg" and store.thumbnail(plain) is None
    assert store.with_thumbnails([seq, plain, 99]) == {seq}
    assert [r.seq for r in store.page(0, 1)] == [seq] and [r.seq for r in store.page(seq, 10)] == [plain]


def test_thumbnails_are_append_only(store: MapStore) -> None:
    store.append(dataclasses.replace(make_row(1), thumbnail=b"jpeg"))
    conn = sqlite3.connect(store.path)
    for sql in ("UPDATE thumbnails SET jpeg = x'00'", "DELETE FROM thumbnails"):
        with pytest.raises(sqlite3.IntegrityError, match="append-only"):
            conn.execute(sql)
    conn.close()


def test_a_key_commits_with_its_row_or_not_at_all(store: MapStore) -> None:
    record = KeyRecord("key-00000001", "f" * 64, '{"seq": 1}')
    seq = store.append(dataclasses.replace(make_row(1), key=record))
    assert store.key_record("key-00000001") == record and store.key_record("other-key") is None
    # The same key again: the whole append fails (the row included), nothing changes.
    with pytest.raises(StorageError):
        store.append(dataclasses.replace(make_row(2), key=record))
    assert store.count() == 1 and store.last_seq() == seq
    assert store.next_seq() == seq + 1


def test_keys_are_bounded_to_the_last_seqs(tmp_path: Path, meta: MapMeta) -> None:
    with MapStore.create(tmp_path / "map.sqlite", meta, max_keys=3) as store:
        for i in range(1, 7):
            store.append(dataclasses.replace(make_row(i), key=KeyRecord(f"key-{i:08d}", "f", "{}")))
        assert [i for i in range(1, 7) if store.key_record(f"key-{i:08d}")] == [4, 5, 6]
        assert store.count() == 6  # the rows stay: only their keys go


def test_a_version_1_file_opens_migrates_and_learns(tmp_path: Path, meta: MapMeta) -> None:
    path = tmp_path / "map.sqlite"
    with MapStore.create(tmp_path / "model.sqlite", meta) as model:
        model.append_many([make_row(1), make_row(2, prev=1)])
        old_rows = list(model.rows())
    write_v1(path, dataclasses.replace(meta, schema_version=1), old_rows)
    # Read-only (cortexloc verify): nothing changes, the rows read with no metadata.
    with MapStore.open(path, readonly=True) as ro:
        assert ro.meta.schema_version == 1 and [r.metadata for r in ro.rows()] == [None, None]
        assert ro.thumbnail(1) is None and ro.key_record("k") is None
    with MapStore.open(path) as store:
        assert store.meta.schema_version == SCHEMA_VERSION
        assert [r.observation_id for r in store.rows()] == [r.observation_id for r in old_rows]
        assert np.array_equal(store.get(2).winner_cells, old_rows[1].winner_cells)
        seq = store.append(dataclasses.replace(make_row(3, prev=2), metadata={"stamp": 3.0},
                                               thumbnail=b"jpeg", key=KeyRecord("key-00000003", "f", "{}")))
        assert seq == 3 and store.get(3).metadata == {"stamp": 3.0} and store.thumbnail(3) == b"jpeg"
    conn = sqlite3.connect(path)
    version = conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0]
    assert version == str(SCHEMA_VERSION)
    # The append-only and frozen-meta rules hold after the migration.
    for sql in ("UPDATE observations SET label = 'x'", "DELETE FROM observations",
                "UPDATE meta SET value = '9'", "DELETE FROM meta"):
        with pytest.raises(sqlite3.IntegrityError):
            conn.execute(sql)
    conn.close()
    with MapStore.open(path) as again:  # a second open finds nothing to migrate
        assert again.count() == 3
