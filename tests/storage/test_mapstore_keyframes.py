"""The `keyframes` table of map.sqlite (schema 3; issue 27 item 1, docs/design/science.md §12.1): a learned
row's packed features and camera commit with it, are append-only, are counted, and a version 2 file is
migrated to hold them."""

from __future__ import annotations

import dataclasses
import sqlite3
from pathlib import Path

import pytest

from storage.mapschema import SCHEMA_VERSION
from storage.mapstore import MapMeta, MapStore
from tests.storage.conftest import make_row

CAMERA = {"fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0, "distortion": []}


def test_a_keyframe_commits_with_its_row_and_reads_back(store: MapStore) -> None:
    s1 = store.append(dataclasses.replace(make_row(1), keyframe=(b"\x00" * 16 + b"features", CAMERA)))
    s2 = store.append(make_row(2, prev=1))  # a row without one
    s3 = store.append(dataclasses.replace(make_row(3, prev=2), keyframe=(b"\x01" * 16, None)))
    got = store.keyframes([s1, s2, s3, 99])
    assert got == {s1: (b"\x00" * 16 + b"features", CAMERA), s3: (b"\x01" * 16, None)}
    camera_bytes = len('{"fx":300.0,"fy":300.0,"cx":160.0,"cy":120.0,"distortion":[]}')
    assert store.keyframe_bytes() == (2, 24 + camera_bytes + 16)


def test_keyframes_are_append_only(store: MapStore) -> None:
    store.append(dataclasses.replace(make_row(1), keyframe=(b"k" * 16, None)))
    conn = sqlite3.connect(store.path)
    for sql in ("UPDATE keyframes SET features = x'00'", "DELETE FROM keyframes"):
        with pytest.raises(sqlite3.IntegrityError):
            conn.execute(sql)
    conn.close()


def test_a_version_2_file_is_migrated_to_hold_keyframes(tmp_path: Path, meta: MapMeta) -> None:
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as made:
        made.append(make_row(1))
    # Version 2's layout: today's without the keyframes table.
    conn = sqlite3.connect(path)
    conn.executescript("""
        DROP TABLE keyframes;
        DROP TRIGGER meta_no_update;
        UPDATE meta SET value = '2' WHERE key = 'schema_version';
        CREATE TRIGGER meta_no_update BEFORE UPDATE ON meta
        BEGIN SELECT RAISE(ABORT, 'map metadata is frozen'); END;
    """)
    conn.close()
    with MapStore.open(path, readonly=True) as ro:  # read-only: not migrated, reads as none stored
        assert ro.meta.schema_version == 2 and ro.keyframes([1]) == {} and ro.keyframe_bytes() == (0, 0)
    with MapStore.open(path) as store:
        assert store.meta.schema_version == SCHEMA_VERSION == 3
        seq = store.append(dataclasses.replace(make_row(2, prev=1), keyframe=(b"f" * 16, CAMERA)))
        assert store.keyframes([1, seq]) == {seq: (b"f" * 16, CAMERA)} and store.count() == 2
