"""The `keyframes` table of map.sqlite (schema 3; issue 27 item 1, docs/design/science.md §12.1): a learned
row's packed features and camera commit with it, are append-only, are counted, and an older file is
migrated to hold them and a logged closure's verification (schema 4)."""

from __future__ import annotations

import dataclasses
import sqlite3
from pathlib import Path

import pytest

from storage.mapschema import SCHEMA_VERSION, NewClosure
from storage.mapstore import MapMeta, MapStore
from tests.storage.conftest import make_row
from tests.storage.test_mapstore_places import V9_UNDONE

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


@pytest.mark.parametrize("version", [2, 3])
def test_an_older_file_is_migrated_to_hold_keyframes_and_closure_verifications(tmp_path: Path, meta: MapMeta,
                                                                              version: int) -> None:
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as made:
        made.append(make_row(1))
    # Version 3's layout is today's without the keyframes table and the closures' verification and
    # consolidated_into and span columns; version 2's has no loop_closures either.
    older = ("DROP TABLE loop_closures;" if version == 2
             else "ALTER TABLE loop_closures DROP COLUMN verification; "
                  "ALTER TABLE loop_closures DROP COLUMN consolidated_into; "
                  "ALTER TABLE loop_closures DROP COLUMN span; "
                  "ALTER TABLE loop_closures DROP COLUMN span_seqs;")
    conn = sqlite3.connect(path)
    conn.executescript(V9_UNDONE + f"""
        DROP TABLE keyframes;
        DROP TABLE joins;
        DROP TABLE visits;
        DROP TABLE dropped;
        DROP TABLE recency;
        DROP TABLE visit_keys;
        DROP TABLE stream_states;
        ALTER TABLE observations DROP COLUMN place;
        {older}
        DROP TRIGGER meta_no_update;
        UPDATE meta SET value = '{version}' WHERE key = 'schema_version';
        CREATE TRIGGER meta_no_update BEFORE UPDATE ON meta
        BEGIN SELECT RAISE(ABORT, 'map metadata is frozen'); END;
    """)
    conn.close()
    with MapStore.open(path, readonly=True) as ro:  # read-only: not migrated, reads as none stored
        assert ro.meta.schema_version == version and ro.keyframes([1]) == {} and ro.keyframe_bytes() == (0, 0)
        assert ro.closures(0, 10) == []
    with MapStore.open(path) as store:
        assert store.meta.schema_version == SCHEMA_VERSION
        closure = NewClosure(stream="s", place_seq=1, confidence=0.99, support=3,
                             verification={"verified": True, "inliers": 40})
        seq = store.append(dataclasses.replace(make_row(2, prev=1), keyframe=(b"f" * 16, CAMERA),
                                               closure=closure))
        assert store.keyframes([1, seq]) == {seq: (b"f" * 16, CAMERA)} and store.count() == 2
        assert [c.verification for c in store.closures(0, 10)] == [{"verified": True, "inliers": 40}]
