"""A `map.sqlite` as version 1 wrote it (before per-row metadata, thumbnails and idempotency keys): the
schema spelled out as it was, so the migration is tested against the real old layout."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

from storage.mapschema import INPUT_DTYPE, encode
from storage.mapstore import MapMeta, MapStore, Observation

V1_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE observations (
    seq              INTEGER PRIMARY KEY CHECK (seq > 0),
    observation_id   TEXT NOT NULL UNIQUE,
    stream           TEXT NOT NULL,
    context_prev_seq INTEGER NULL CHECK (context_prev_seq IS NULL OR context_prev_seq < seq),
    label            TEXT NULL,
    created_at       TEXT NOT NULL,
    image_sha256     TEXT NOT NULL,
    input_sdr        BLOB NOT NULL,
    winner_cells     BLOB NOT NULL
);
CREATE TRIGGER observations_no_update BEFORE UPDATE ON observations
BEGIN SELECT RAISE(ABORT, 'observations are append-only'); END;
CREATE TRIGGER observations_no_delete BEFORE DELETE ON observations
BEGIN SELECT RAISE(ABORT, 'observations are append-only'); END;
CREATE TRIGGER meta_no_update BEFORE UPDATE ON meta
BEGIN SELECT RAISE(ABORT, 'map metadata is frozen'); END;
CREATE TRIGGER meta_no_delete BEFORE DELETE ON meta
BEGIN SELECT RAISE(ABORT, 'map metadata is frozen'); END;
"""


def write_v1(path: Path, meta: MapMeta, rows: list[Observation]) -> None:
    """A version 1 file at `path` (which must not exist) holding `meta` and `rows` as stored."""
    conn = sqlite3.connect(path)
    conn.executescript(V1_SCHEMA)
    conn.executemany("INSERT INTO meta VALUES (?, ?)", [
        ("schema_version", "1"), ("map_id", json.dumps(meta.map_id)),
        ("params", json.dumps(meta.params, sort_keys=True)),
        ("projection_sha256", json.dumps(meta.projection_sha256)),
        ("encoder_id", json.dumps(meta.encoder_id)),
        ("cell_dtype", json.dumps(meta.cell_dtype))])
    conn.executemany("INSERT INTO observations VALUES (?,?,?,?,?,?,?,?,?)", [
        (r.seq, r.observation_id, r.stream, r.context_prev_seq, r.label, r.created_at, r.image_sha256,
         encode(r.input_sdr, INPUT_DTYPE, "input_sdr"),
         encode(r.winner_cells, meta.cell_dtype, "winner_cells"))
        for r in rows])
    conn.commit()
    conn.close()


def downgrade(path: Path) -> None:
    """Rewrite the map file at `path` as version 1 would have written its rows (metadata dropped)."""
    with MapStore.open(path, readonly=True) as store:
        meta, rows = store.meta, list(store.rows())
    for leftover in (path, Path(f"{path}-wal"), Path(f"{path}-shm")):
        leftover.unlink(missing_ok=True)
    write_v1(path, meta, rows)
