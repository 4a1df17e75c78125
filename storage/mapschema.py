"""`map.sqlite`'s layout: its schema, its rows as Python values, and the creation of a new file
(docs/design/service.md §4.2). `storage.mapstore` reads and appends; this module says what is stored
(and, for each schema version, what a file holds: `Holds`).

A row, once committed, is never changed or removed: triggers in the file refuse UPDATE and DELETE on
`observations` and `thumbnails`, and the frozen `meta` likewise. The logs and keys are bounded: the
oldest keys, loop closures and covered visits are pruned, and a stream's state once a snapshot holds it
(docs/design/service.md §4.2).

Version 2 added a row's `metadata`, the `thumbnails` and `idempotency_keys` tables; version 3 the
`loop_closures` log (docs/design/service.md §4.2: every revisit a stream was told of, bounded, the
oldest pruned like the keys); version 4 the `keyframes` table (a learned row's local features and
camera, docs/design/science.md §12.1) and a logged closure's `verification`; version 5 places
(docs/design/science.md §11.8, §11.9): a row's `place` (the row whose place it joined), the `visits` log
(a consolidated frame: the memory learned it, no row was made; replayed like a row) and the `dropped`
rows (out of the index and their places: an appearance over its place's cap, a forgotten place); version
6 the rows' `recency`; version 7 `visit_keys`, a consolidated frame's Idempotency-Key and reply, kept
for the keys' window whatever the visit log's pruning, and `stream_states`, what a replay cannot give
back of a learning stream (its localiser state), written with each learned step; version 8 a logged
closure's `consolidated_into` (the closure of a consolidated frame, a visit, names the row it was
consolidated into: it has no row of its own, and a localising stream's closure has neither); version
9 the `repairs` log and a logged closure's `retracts` (a repair of merges made from a stream's own
recent trail, docs/design/science.md §11.6: a visit re-made as its own row, a row given back its own
place, a closure retracted by a new entry that names it); version 10 the `joins`, a learning stream's
warm-up rows joined to the old places its confident path found (docs/design/science.md §11.8); version 11 a
logged closure's `span` and `span_seqs` (how many places the stream may have been at, and their rows:
docs/design/science.md §11.11); version 12 a joined row turned into a visit: the join, in its
transaction, logs the row's frame as a visit (`visits.row_seq`: the row's seq; `seq`: the old row whose place
it joined) and deletes the row (its observation, thumbnail and keyframe: the file's delete triggers let a
joined row go, nothing else), so a restarted drive's warm-up adds to the bounded visit log, not to the
rows (docs/design/science.md §11.8); version 13 the `flat` rows, those whose frame was too flat to say
where it is (docs/design/science.md §11.7: a later flat frame whose path names one is a visit of it; an
older file's rows are not known flat); version 14 a join that keeps its row (`joins.kept`: the row stays,
a new appearance of the old row's place, docs/design/science.md §11.8). An older
file is brought up to date when it is opened for writing (`migrate`), in one transaction: its rows keep
`place` NULL (read as the place its learning stream's logged loop closure names, else its own). Opened
read-only (`cortexloc verify`, a snapshot's copy) an older file is read as it is; a file of a newer version
than `SCHEMA_VERSION` is refused (`storage.mapstore.MapStore.open`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import sqlite3
import tempfile
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from storage._common import (
    StorageError,
    StorageFull,
    StoreCorrupt,
    connect,
    is_full_error,
    transaction,
    utc_now,
)
from storage.base.dtypes import INDEX_DTYPE
from storage.base.files import fsync_dir

__all__ = [
    "CELL_DTYPES",
    "COLUMNS",
    "INPUT_DTYPE",
    "SCHEMA_VERSION",
    "DuplicateObservation",
    "Holds",
    "JoinedRow",
    "KeyRecord",
    "LoopClosure",
    "MapMeta",
    "NewClosure",
    "NewObservation",
    "NewVisit",
    "Observation",
    "Repair",
    "StoreCorrupt",
    "Visit",
    "cell_dtype_for",
    "create_file",
    "decode",
    "encode",
    "load_json",
    "migrate",
    "read_meta",
]

#: Bump when the layout of map.sqlite changes; `open` refuses files from a newer version.
SCHEMA_VERSION = 14
#: Active columns are stored as little-endian uint16 (sLSBH widths are far below 65,536).
INPUT_DTYPE = "uint16"
#: Allowed dtypes of the winner-cell blobs; chosen once per map from its cell count.
CELL_DTYPES = ("uint16", "uint32")


_SCHEMA = """
CREATE TABLE meta (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL              -- JSON
);
CREATE TABLE observations (
    seq              INTEGER PRIMARY KEY CHECK (seq > 0),
    observation_id   TEXT NOT NULL UNIQUE,
    stream           TEXT NOT NULL,
    context_prev_seq INTEGER NULL CHECK (context_prev_seq IS NULL OR context_prev_seq < seq),
    label            TEXT NULL,
    created_at       TEXT NOT NULL,
    image_sha256     TEXT NOT NULL,
    input_sdr        BLOB NOT NULL,  -- sorted little-endian uint16 active columns
    winner_cells     BLOB NOT NULL,  -- sorted little-endian uint16 or uint32 (meta.cell_dtype) cells
    metadata         TEXT NULL       -- the client's small JSON object (stamp, pose, ...), compact
);
-- The append-only rule enforced by the file itself, not only by this module's API.
CREATE TRIGGER observations_no_update BEFORE UPDATE ON observations
BEGIN SELECT RAISE(ABORT, 'observations are append-only'); END;
CREATE TRIGGER observations_no_delete BEFORE DELETE ON observations
BEGIN SELECT RAISE(ABORT, 'observations are append-only'); END;
-- The resolved parameters are frozen into the map (docs/design/service.md §1.1): another configuration is
-- another map.
CREATE TRIGGER meta_no_update BEFORE UPDATE ON meta
BEGIN SELECT RAISE(ABORT, 'map metadata is frozen'); END;
CREATE TRIGGER meta_no_delete BEFORE DELETE ON meta
BEGIN SELECT RAISE(ABORT, 'map metadata is frozen'); END;
"""

# What version 2 added beside `observations.metadata`; created with a new file and by `migrate`.
_V2_TABLES = """
CREATE TABLE thumbnails (
    seq  INTEGER PRIMARY KEY REFERENCES observations (seq),
    jpeg BLOB NOT NULL               -- a small JPEG of the frame, for people (never replayed)
);
CREATE TRIGGER thumbnails_no_update BEFORE UPDATE ON thumbnails
BEGIN SELECT RAISE(ABORT, 'thumbnails are append-only'); END;
CREATE TRIGGER thumbnails_no_delete BEFORE DELETE ON thumbnails
BEGIN SELECT RAISE(ABORT, 'thumbnails are append-only'); END;
-- A learned post's Idempotency-Key, committed with its row: a repeat is answered from here.
CREATE TABLE idempotency_keys (
    key         TEXT PRIMARY KEY,
    fingerprint TEXT NOT NULL,       -- SHA-256 of what the request asked (body and parameters)
    seq         INTEGER NOT NULL UNIQUE REFERENCES observations (seq),
    reply       TEXT NOT NULL,       -- the reply's JSON as first sent
    created_at  TEXT NOT NULL
);
"""

# What version 3 added: the loop-closure log (docs/design/science.md §11.6). A learning stream's entry
# commits with its row (`seq`); a localising stream's alone (it stores no observation). `place_seq` is a
# stored row; `idempotency_key` keeps a repeated post from logging twice. Pruned oldest first.
_V3_TABLES = """
CREATE TABLE loop_closures (
    id              INTEGER PRIMARY KEY,   -- log order: the page cursor
    stream          TEXT NOT NULL,
    seq             INTEGER NULL REFERENCES observations (seq),   -- the frame's row, if learned
    place_seq       INTEGER NOT NULL REFERENCES observations (seq),
    confidence      REAL NOT NULL,
    support         INTEGER NOT NULL,
    metadata        TEXT NULL,             -- the frame's metadata (stamp, pose), compact JSON
    idempotency_key TEXT NULL UNIQUE,
    created_at      TEXT NOT NULL
);
CREATE TRIGGER loop_closures_no_update BEFORE UPDATE ON loop_closures
BEGIN SELECT RAISE(ABORT, 'loop closures are append-only'); END;
"""

# What version 4 added: a learned row's keyframe (maps with the `keyframes` option only): its local
# features packed by `models.geometry.pack` and the camera it was taken with, for verifying revisits;
# and a logged loop closure's geometric verification (docs/design/science.md §12), compact JSON.
_V4_TABLES = """
CREATE TABLE keyframes (
    seq      INTEGER PRIMARY KEY REFERENCES observations (seq),
    features BLOB NOT NULL,          -- models.geometry.pack: header, xy float32, descriptors uint8
    camera   TEXT NULL               -- {fx, fy, cx, cy, distortion} of the frame, compact JSON
);
CREATE TRIGGER keyframes_no_update BEFORE UPDATE ON keyframes
BEGIN SELECT RAISE(ABORT, 'keyframes are append-only'); END;
CREATE TRIGGER keyframes_no_delete BEFORE DELETE ON keyframes
BEGIN SELECT RAISE(ABORT, 'keyframes are append-only'); END;
"""


# What version 5 added (docs/design/science.md §11.8, §11.9; docs/design/service.md §4.2). `visits`: a
# learning stream's consolidated frame, committed before its reply, replayed after the snapshot that does
# not cover it (`after_seq`: the last row stored before it, the replay order), pruned to a bound once a
# snapshot covers it. `dropped`: rows no longer held (their data stays: the replay and the snapshots
# need them).
_V5_TABLES = """
CREATE TABLE visits (
    id               INTEGER PRIMARY KEY,   -- log order
    after_seq        INTEGER NOT NULL,      -- the last row stored before it
    stream           TEXT NOT NULL,
    seq              INTEGER NOT NULL REFERENCES observations (seq),   -- the row it was consolidated into
    context_prev_seq INTEGER NULL,          -- the row its stream continued (NULL: a new sequence)
    input_sdr        BLOB NOT NULL,
    winner_cells     BLOB NOT NULL,
    metadata         TEXT NULL,
    created_at       TEXT NOT NULL,
    idempotency_key  TEXT NULL UNIQUE,
    fingerprint      TEXT NULL,
    reply            TEXT NULL
);
CREATE TABLE dropped (
    seq        INTEGER PRIMARY KEY REFERENCES observations (seq),
    reason     TEXT NOT NULL,               -- appearance-cap | forgotten | joined (version 10)
    after_seq  INTEGER NOT NULL,
    created_at TEXT NOT NULL
);
"""
_PLACE_COLUMN = "ALTER TABLE observations ADD COLUMN place INTEGER NULL;"

# What version 6 added (docs/design/science.md §11.9; docs/design/service.md §4.2): when each row was last
# used (the appearance cap and forgetting read it), written in the transaction of the row or visit that
# used it, so a recovery gives every row the recency the live map had (a row's own making and the visits
# kept do not say which row a step's answer was, nor the clock of a visit after a restore).
_V6_TABLES = """
CREATE TABLE recency (
    seq  INTEGER PRIMARY KEY REFERENCES observations (seq),
    used INTEGER NOT NULL                   -- the seq-space clock of its last use
);
"""


# What version 7 added (docs/design/service.md §4.2, §4.4): a consolidated frame's Idempotency-Key and
# reply, committed with its visit, bounded like the row keys (those of the last `max_keys` visits), and kept
# when the visit log is pruned: a retry is answered for the keys' window, not only while its visit is
# logged. And each learning stream's state after its last learned step that a replay cannot rebuild,
# upserted in that step's transaction, pruned once a snapshot holds it: a stream resumes its place after
# a crash as after a clean shutdown.
_V7_TABLES = """
CREATE TABLE visit_keys (
    key         TEXT PRIMARY KEY,
    fingerprint TEXT NOT NULL,
    visit       INTEGER NOT NULL UNIQUE,   -- the visit's id (its log order; it may be pruned since)
    reply       TEXT NOT NULL,
    created_at  TEXT NOT NULL
);
CREATE TABLE stream_states (
    stream  TEXT PRIMARY KEY,
    clock   INTEGER NOT NULL,          -- the seq-space clock of the stream's last learned step
    state   BLOB NOT NULL              -- models.pipeline.resume_state: npz of its localiser, adaptation
);
"""
#: An older file's visit keys, those of the visits still logged (the pruned ones are gone with them).
_COPY_VISIT_KEYS = """
INSERT INTO visit_keys (key, fingerprint, visit, reply, created_at)
SELECT idempotency_key, fingerprint, id, reply, created_at FROM visits WHERE idempotency_key IS NOT NULL;
"""


# What version 10 added (docs/design/science.md §11.8; docs/design/service.md §4.2): the warm-up joins. A
# row a learning stream made while it warmed up or was unsure, that the confident path it then found
# explains (an old row represents it), shows the old row's place and is held no more (`dropped`, reason
# `joined`), both in the transaction of the step that found it. Rows are append-only, so the join is its
# own record, read by the recovery after the rows (`MapStore.joins`).
_V10_TABLES = """
CREATE TABLE joins (
    seq        INTEGER PRIMARY KEY REFERENCES observations (seq),   -- the row joined
    place_seq  INTEGER NOT NULL REFERENCES observations (seq),      -- the old row whose place it joined
    stream     TEXT NOT NULL,
    after_seq  INTEGER NOT NULL,                                    -- the last row stored before it
    created_at TEXT NOT NULL,
    CHECK (place_seq < seq)
);
"""


def _version_step(version: int) -> str:
    """The script that lifts the frozen meta's trigger for the version number alone."""
    return f"""
DROP TRIGGER meta_no_update;
UPDATE meta SET value = '{version}' WHERE key = 'schema_version';
CREATE TRIGGER meta_no_update BEFORE UPDATE ON meta
BEGIN SELECT RAISE(ABORT, 'map metadata is frozen'); END;
"""


#: Version 1 -> 2 (`migrate`), run as one script inside one transaction. ADD COLUMN changes no row (the
#: new column reads NULL), so the append-only triggers stay as they are; the frozen meta's trigger is
#: lifted for the version number alone and put back in the same transaction.
_MIGRATE_V2 = "ALTER TABLE observations ADD COLUMN metadata TEXT NULL;" + _V2_TABLES + _version_step(2)
#: Version 2 -> 3: a new table, no row changes.
_MIGRATE_V3 = _V3_TABLES + _version_step(3)
#: Version 3 -> 4: a new table, and a column no row has yet (ADD COLUMN: reads NULL, no row changes).
_CLOSURE_VERIFICATION = "ALTER TABLE loop_closures ADD COLUMN verification TEXT NULL;"
_MIGRATE_V4 = _V4_TABLES + _CLOSURE_VERIFICATION + _version_step(4)
#: Version 4 -> 5: new tables, and a column no row has yet (every older row reads NULL: no row changes).
_MIGRATE_V5 = _V5_TABLES + _PLACE_COLUMN + _version_step(5)
#: Version 5 -> 6: a new table (an older file's recency is rebuilt as before: rows and visits kept).
_MIGRATE_V6 = _V6_TABLES + _version_step(6)
#: Version 6 -> 7: a new table, filled from the keys the visit log holds (no row changes).
_MIGRATE_V7 = _V7_TABLES + _COPY_VISIT_KEYS + _version_step(7)
#: Version 7 -> 8: a column no row has yet (an older visit's closure reads NULL, as a localising one's).
_CLOSURE_VISIT = "ALTER TABLE loop_closures ADD COLUMN consolidated_into INTEGER NULL;"
_MIGRATE_V8 = _CLOSURE_VISIT + _version_step(8)
# What version 9 added (docs/design/science.md §11.6, docs/design/service.md §4.2, §4.4): the repair of
# merges made from a stream's own recent trail. `repairs`: each thing a repair changed, committed in one
# transaction with the rows it re-made and the retractions it logged: `split` (a visit re-made as its own
# row `seq`, appended at the end; the memory learned the frame with the visit, so a replay skips the row
# and replays the visit) or `unjoin` (row `seq` given back its own place); `was` is the row it had been
# merged into or joined. A logged closure's `retracts`: this entry withdraws closure `retracts` (a new
# entry: the log's no-update trigger stays).
_V9_TABLES = """
CREATE TABLE repairs (
    id         INTEGER PRIMARY KEY,
    kind       TEXT NOT NULL CHECK (kind IN ('split', 'unjoin')),
    seq        INTEGER NOT NULL UNIQUE REFERENCES observations (seq),
    visit      INTEGER NULL UNIQUE,     -- the visit split (its id in the visit log), for `split`
    was        INTEGER NOT NULL,        -- the row it was consolidated into, or whose place it joined
    created_at TEXT NOT NULL
);
CREATE TRIGGER repairs_no_update BEFORE UPDATE ON repairs
BEGIN SELECT RAISE(ABORT, 'repairs are append-only'); END;
CREATE TRIGGER repairs_no_delete BEFORE DELETE ON repairs
BEGIN SELECT RAISE(ABORT, 'repairs are append-only'); END;
"""
_CLOSURE_RETRACTS = "ALTER TABLE loop_closures ADD COLUMN retracts INTEGER NULL;"
#: Version 8 -> 9: a new table and a column no row has yet (no row changes).
_MIGRATE_V9 = _V9_TABLES + _CLOSURE_RETRACTS + _version_step(9)
#: Version 9 -> 10: a new table, no row changes.
_MIGRATE_V10 = _V10_TABLES + _version_step(10)
#: Version 10 -> 11: columns no row has yet (an older closure's span reads NULL: not recorded).
_CLOSURE_SPAN = ("ALTER TABLE loop_closures ADD COLUMN span INTEGER NULL;"
                 "ALTER TABLE loop_closures ADD COLUMN span_seqs TEXT NULL;")
_MIGRATE_V11 = _CLOSURE_SPAN + _version_step(11)

# What version 12 added (docs/design/science.md §11.8; docs/design/service.md §4.2, §4.4): a joined row
# turned into a visit. `visits.row_seq`: the seq of the row a warm-up join turned into this visit (NULL: a
# consolidated frame), replayed as that row (its memory step, its links, its place joined); `joins.
# observation_id`: the row's, so a snapshot whose last row was joined away is still known as this file's;
# with its `image_sha256`, `label`, `row_created_at` and `metadata` the row's record as acknowledged, so
# `GET .../observations/{seq}` answers for it as before (nothing acknowledged is lost, the visit being pruned
# or not).
# The delete triggers of `observations`, `thumbnails` and `keyframes` let a joined row go, nothing else.
_V12_TABLES = """
ALTER TABLE visits ADD COLUMN row_seq INTEGER NULL;
ALTER TABLE joins ADD COLUMN observation_id TEXT NULL;
ALTER TABLE joins ADD COLUMN image_sha256 TEXT NULL;    -- the row's record, kept when it is deleted:
ALTER TABLE joins ADD COLUMN label TEXT NULL;           -- GET .../observations/{seq} still answers
ALTER TABLE joins ADD COLUMN row_created_at TEXT NULL;
ALTER TABLE joins ADD COLUMN metadata TEXT NULL;
CREATE INDEX visits_learned ON visits (after_seq, id);        -- the replay's order (`MapStore.visits`)
CREATE INDEX visits_row ON visits (row_seq) WHERE row_seq IS NOT NULL;
DROP TRIGGER observations_no_delete;
CREATE TRIGGER observations_no_delete BEFORE DELETE ON observations
WHEN NOT EXISTS (SELECT 1 FROM joins WHERE seq = OLD.seq)
BEGIN SELECT RAISE(ABORT, 'observations are append-only'); END;
DROP TRIGGER thumbnails_no_delete;
CREATE TRIGGER thumbnails_no_delete BEFORE DELETE ON thumbnails
WHEN NOT EXISTS (SELECT 1 FROM joins WHERE seq = OLD.seq)
BEGIN SELECT RAISE(ABORT, 'thumbnails are append-only'); END;
DROP TRIGGER keyframes_no_delete;
CREATE TRIGGER keyframes_no_delete BEFORE DELETE ON keyframes
WHEN NOT EXISTS (SELECT 1 FROM joins WHERE seq = OLD.seq)
BEGIN SELECT RAISE(ABORT, 'keyframes are append-only'); END;
"""
#: Version 11 -> 12: columns no row has yet (an older visit and join read NULL), the delete triggers.
_MIGRATE_V12 = _V12_TABLES + _version_step(12)

# What version 13 added (docs/design/science.md §11.7; docs/design/service.md §4.2): the rows whose frame
# was flat (under `MIN_CONTRAST`), written in the row's transaction, so a recovery and a restored snapshot
# know them as the live map did (a later flat frame is a visit of the flat row its path names, whatever
# its code). A row not here is not known flat (every row of an older file).
_V13_TABLES = """
CREATE TABLE flat (
    seq  INTEGER PRIMARY KEY REFERENCES observations (seq)
);
"""
#: Version 12 -> 13: a new table, no row changes (an older file's rows are not known flat).
_MIGRATE_V13 = _V13_TABLES + _version_step(13)

# What version 14 added (docs/design/science.md §11.8; docs/design/service.md §4.2): a warm-up join that
# keeps its row (`joins.kept` 1): the row is like the old row but not represented by it (another season's
# first frames), so it stays, held, a new appearance of the old row's place; it is neither dropped nor
# deleted, and the delete triggers let a row go only for a join that does not keep it.
_V14_TABLES = """
ALTER TABLE joins ADD COLUMN kept INTEGER NOT NULL DEFAULT 0 CHECK (kept IN (0, 1));
DROP TRIGGER observations_no_delete;
CREATE TRIGGER observations_no_delete BEFORE DELETE ON observations
WHEN NOT EXISTS (SELECT 1 FROM joins WHERE seq = OLD.seq AND kept = 0)
BEGIN SELECT RAISE(ABORT, 'observations are append-only'); END;
DROP TRIGGER thumbnails_no_delete;
CREATE TRIGGER thumbnails_no_delete BEFORE DELETE ON thumbnails
WHEN NOT EXISTS (SELECT 1 FROM joins WHERE seq = OLD.seq AND kept = 0)
BEGIN SELECT RAISE(ABORT, 'thumbnails are append-only'); END;
DROP TRIGGER keyframes_no_delete;
CREATE TRIGGER keyframes_no_delete BEFORE DELETE ON keyframes
WHEN NOT EXISTS (SELECT 1 FROM joins WHERE seq = OLD.seq AND kept = 0)
BEGIN SELECT RAISE(ABORT, 'keyframes are append-only'); END;
"""
#: Version 13 -> 14: a column every older join reads as 0 (none kept its row), the delete triggers.
_MIGRATE_V14 = _V14_TABLES + _version_step(14)

#: The columns of `observations`, in the order every SELECT and INSERT uses.
COLUMNS = ("seq, observation_id, stream, context_prev_seq, label, created_at, image_sha256, "
            "input_sdr, winner_cells, metadata, place")
#: The same for a version 2-4 file opened read-only (no place column: it reads as NULL).
COLUMNS_V4 = COLUMNS.replace("place", "NULL")
#: The same for a version 1 file opened read-only (no metadata column either).
COLUMNS_V1 = COLUMNS_V4.replace("metadata", "NULL")


@dataclass(frozen=True)
class Holds:
    """What a file of one schema version holds, each table or column under its name (the version that
    added it: this module's docstring). Read once, when a store opens the file (`Holds.of`): a reader
    asks whether its table is there, never which version the file is. A file opened for writing is
    migrated first, so it holds everything; one opened read-only holds what its version had."""

    thumbnails: bool  # 2, and a row's metadata
    idempotency_keys: bool  # 2
    loop_closures: bool  # 3
    keyframes: bool  # 4
    closure_verification: bool  # 4
    visits: bool  # 5, and a row's place
    dropped: bool  # 5
    recency: bool  # 6
    visit_keys: bool  # 7 (a version 5-6 file keeps a visit's key in its log)
    stream_states: bool  # 7
    closure_consolidated_into: bool  # 8
    repairs: bool  # 9
    closure_retracts: bool  # 9
    joins: bool  # 10
    closure_span: bool  # 11
    joined_rows: bool  # 12: a joined row turned into a visit (`visits.row_seq`, `joins.observation_id`)
    flat: bool  # 13: the rows whose frame was flat
    kept_joins: bool  # 14: a warm-up join that keeps its row (`joins.kept`)
    row_columns: str  # what `SELECT` reads of `observations` (NULL for a column the file lacks)

    @classmethod
    def of(cls, version: int) -> Holds:
        return cls(thumbnails=version >= 2, idempotency_keys=version >= 2, loop_closures=version >= 3,
                   keyframes=version >= 4, closure_verification=version >= 4, visits=version >= 5,
                   dropped=version >= 5, recency=version >= 6, visit_keys=version >= 7,
                   stream_states=version >= 7, closure_consolidated_into=version >= 8,
                   repairs=version >= 9, closure_retracts=version >= 9, joins=version >= 10,
                   closure_span=version >= 11, joined_rows=version >= 12, flat=version >= 13,
                   kept_joins=version >= 14,
                   row_columns=COLUMNS if version >= 5 else COLUMNS_V4 if version >= 2 else COLUMNS_V1)


def migrate(conn: sqlite3.Connection, meta: MapMeta) -> MapMeta:
    """Bring an open file of an older version (1 to `SCHEMA_VERSION` - 1) to `SCHEMA_VERSION` in one
    transaction (all or nothing); the meta as it then is. A current file is returned as it is."""
    if meta.schema_version >= SCHEMA_VERSION:
        return meta
    # chain[v - 1]: version v -> v + 1
    chain = [_MIGRATE_V2, _MIGRATE_V3, _MIGRATE_V4, _MIGRATE_V5, _MIGRATE_V6, _MIGRATE_V7, _MIGRATE_V8,
             _MIGRATE_V9, _MIGRATE_V10, _MIGRATE_V11, _MIGRATE_V12, _MIGRATE_V13, _MIGRATE_V14]
    steps = "".join(chain[meta.schema_version - 1:])
    try:
        conn.executescript("BEGIN IMMEDIATE;" + steps + "COMMIT;")
    except BaseException:
        if conn.in_transaction:
            conn.execute("ROLLBACK")
        raise
    return dataclasses.replace(meta, schema_version=SCHEMA_VERSION)


class DuplicateObservation(StorageError):  # noqa: N818
    """An `observation_id` that is already stored; nothing was written."""


def cell_dtype_for(n_cells: int) -> str:
    """Winner-cell blob dtype for a memory of `n_cells` cells (docs/design/service.md §4.2).

    uint16 holds cell ids 0…65,535, so it serves up to 65,536 cells; above that uint32.
    """
    if n_cells <= 0:
        raise ValueError(f"n_cells must be positive, got {n_cells}")
    return "uint16" if n_cells <= 1 << 16 else "uint32"


@dataclass(frozen=True)
class MapMeta:
    """What is frozen into a map when it is created (the `meta` table).

    Attributes:
        map_id: the map's identifier.
        params: resolved parameters (`tm`, `slsbh`, `encoder`, `seed`, ...), JSON-able.
        projection_sha256: checksum of the map's sLSBH projection.
        encoder_id: identity of the encoder whose codes the map holds.
        cell_dtype: `uint16` or `uint32` (see `cell_dtype_for`).
        schema_version: layout version of the file.
    """

    map_id: str
    params: dict[str, Any]
    projection_sha256: str
    encoder_id: str
    cell_dtype: str = "uint16"
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self) -> None:
        if self.cell_dtype not in CELL_DTYPES:
            raise ValueError(f"cell_dtype must be one of {CELL_DTYPES}, got {self.cell_dtype!r}")


@dataclass(frozen=True, eq=False)
class NewObservation:
    """A learned observation about to be appended (its `seq` is assigned by `MapStore.append`).

    Attributes:
        stream: the stream whose context the step used.
        image_sha256: SHA-256 of the uploaded image bytes.
        input_sdr: active columns (sorted, distinct, < 65,536).
        winner_cells: the TM's winner cells (sorted, distinct, within the map's cell dtype).
        context_prev_seq: the learned observation whose context this step continued; None = new sequence.
        label: optional client text.
        observation_id: UUID (generated when not given).
        created_at: ISO 8601 UTC (now when not given).
        metadata: the client's small JSON object (stamp, pose, ...), stored as compact JSON.
        thumbnail: a small JPEG of the frame (`thumbnails` table), for maps that keep them.
        key: the post's Idempotency-Key and reply, committed in the row's transaction.
        keyframe: the frame's packed local features (`models.geometry.pack`) and its camera (or None),
            `keyframes` table, for maps with the `keyframes` option.
        resume: its stream's state after the step that a replay cannot rebuild
            (`models.pipeline.resume_state`), `stream_states`.
        closure: the revisit logged with it. place: the row whose place it joined (None: its own place).
        drops: rows its place dropped over its cap, recorded in its transaction (`dropped`).
        touched: rows its step used (the answer's row of the place it joined), at the clock of its seq
            (`recency`).
        joins: (row, old row) the warm-up joins its step made (`joins`, with each row `dropped`,
            reason `joined`; docs/design/science.md §11.8).
        kept: (row, old row) the warm-up joins its step made that keep their row (`joins.kept`; the row
            stays held, an appearance of the old row's place; their places' drops are in `drops`).
        flat: its frame was flat (under `MIN_CONTRAST`, docs/design/science.md §11.7; `flat`).
    """

    stream: str
    image_sha256: str
    input_sdr: np.ndarray
    winner_cells: np.ndarray
    context_prev_seq: int | None = None
    label: str | None = None
    observation_id: str = field(default_factory=lambda: str(uuid.uuid4()))
    created_at: str = field(default_factory=utc_now)
    metadata: dict[str, Any] | None = None
    thumbnail: bytes | None = None
    key: KeyRecord | None = None
    keyframe: tuple[bytes, dict[str, Any] | None] | None = None
    resume: bytes | None = None
    closure: NewClosure | None = None
    place: int | None = None
    drops: tuple[int, ...] = ()
    touched: tuple[int, ...] = ()
    joins: tuple[tuple[int, int], ...] = ()
    kept: tuple[tuple[int, int], ...] = ()
    flat: bool = False


@dataclass(frozen=True, eq=False)
class NewVisit:
    """A learning stream's consolidated frame about to be logged (`visits`, docs/design/science.md §11.8):
    what the replay needs (its code and winner cells, the row its stream continued), the row it was
    consolidated into, and what its reply needs (metadata, the idempotency key and reply).

    Attributes:
        stream: the stream. seq: the stored row it was consolidated into. context_prev_seq: the row the
        stream continued (None: a new sequence). input_sdr, winner_cells: as a row's. metadata: the
        frame's. key: the post's Idempotency-Key and reply. closure: its revisit, logged with it.
        touched: rows its step used (`seq` and the answer's row), at the clock of the seq the store
            would have given it (`MapStore.next_seq`: the live map's clock, `recency`).
        resume, joins, kept, drops: as a row's (`NewObservation`; a visit's drops are those of the places
            its kept joins joined).
    """

    stream: str
    seq: int
    context_prev_seq: int | None
    input_sdr: np.ndarray
    winner_cells: np.ndarray
    metadata: dict[str, Any] | None = None
    created_at: str = field(default_factory=utc_now)
    key: KeyRecord | None = None
    closure: NewClosure | None = None
    touched: tuple[int, ...] = ()
    resume: bytes | None = None
    joins: tuple[tuple[int, int], ...] = ()
    kept: tuple[tuple[int, int], ...] = ()
    drops: tuple[int, ...] = ()


@dataclass(frozen=True, eq=False)
class Visit:
    """A logged visit (`MapStore.visits`): `id` its log order, `after_seq` the last row before it; `row`
    the seq of the row a warm-up join turned into it (replayed as that row, §11.8), None for a
    consolidated frame."""

    id: int
    after_seq: int
    stream: str
    seq: int
    context_prev_seq: int | None
    input_sdr: np.ndarray
    winner_cells: np.ndarray
    created_at: str
    metadata: dict[str, Any] | None = None
    row: int | None = None  # the row a warm-up join turned into this visit (schema 12); None: consolidated

    def as_row(self) -> Observation:
        """The row a warm-up join turned into this visit, as it was learned (its seq `row`, its own
        place; no observation id or image digest: those went with it)."""
        assert self.row is not None
        return Observation(seq=self.row, observation_id="", stream=self.stream,
                           context_prev_seq=self.context_prev_seq, label=None, created_at=self.created_at,
                           image_sha256="", input_sdr=self.input_sdr, winner_cells=self.winner_cells,
                           metadata=self.metadata)


@dataclass(frozen=True)
class NewClosure:
    """A revisit a stream was told of, about to be logged (`loop_closures`; docs/design/science.md §11.6).
    With a learned row it commits in the row's transaction and names it; alone (a localising stream),
    it names no row.

    Attributes:
        stream: the stream. place_seq: the stored row its `place` named. confidence, support: the answer's.
        metadata: the frame's metadata (stamp, pose). key: the post's Idempotency-Key (a repeat logs
        nothing). created_at: ISO 8601 UTC. verification: the place's geometric verification
        (`place.verification`, docs/design/science.md §12) on a map with keyframes, else None.
        span, span_seqs: the answer's span (`place.span`, `place.span_seqs`; docs/design/science.md
        §11.11); None: not known.
    """

    stream: str
    place_seq: int
    confidence: float
    support: int
    metadata: dict[str, Any] | None = None
    key: str | None = None
    created_at: str = field(default_factory=utc_now)
    verification: dict[str, Any] | None = None
    span: int | None = None
    span_seqs: tuple[int, ...] | None = None


@dataclass(frozen=True)
class LoopClosure:
    """One logged loop closure with both rows' identities (`MapStore.closures`).

    Attributes:
        id: its place in the log (pages go `after` it). seq, observation_id: the frame's row (None when
        the stream was localising, or the frame was consolidated). place_*: the row its place named.
        verification: as logged (None: none, or a file before version 4). consolidated_into: for a
        consolidated frame (a visit), the row it was consolidated into (None: it has a row, or it was
        a localising stream's, or it was logged before version 8). retracts: on a retraction entry
        (version 9: a repair withdrew a closure, docs/design/science.md §11.6), the id of the closure it
        withdraws; its pair is that closure's, its confidence and support 0, no verification.
        span, span_seqs: how many places the stream may have been at and their rows
        (docs/design/science.md §11.11; None: logged before version 11, or a retraction).
    """

    id: int
    stream: str
    seq: int | None
    observation_id: str | None
    metadata: dict[str, Any] | None
    place_seq: int
    place_observation_id: str
    place_stream: str
    place_label: str | None
    place_metadata: dict[str, Any] | None
    confidence: float
    support: int
    created_at: str
    verification: dict[str, Any] | None = None
    consolidated_into: int | None = None
    retracts: int | None = None

    span: int | None = None
    span_seqs: tuple[int, ...] | None = None


@dataclass(frozen=True)
class Repair:
    """One logged repair (`MapStore.repairs`, schema version 9, docs/design/science.md §11.6).

    Attributes:
        id: its log order. kind: `split` (visit `visit` re-made as row `seq`) or `unjoin` (row `seq`
        given back its own place). was: the row it had been consolidated into, or whose place it joined.
    """

    id: int
    kind: str
    seq: int
    visit: int | None
    was: int
    created_at: str


@dataclass(frozen=True)
class JoinedRow:
    """The record of a row a warm-up join turned into a visit and deleted (schema 12, docs/design/science.md
    §11.8), as it was acknowledged: `place_seq` the old row whose place it joined."""

    seq: int
    observation_id: str
    stream: str
    label: str | None
    created_at: str
    image_sha256: str
    metadata: dict[str, Any] | None
    place_seq: int


@dataclass(frozen=True, eq=False)
class Observation:
    """A stored observation; arrays are decoded to `storage.base.dtypes.INDEX_DTYPE` (int32), sorted.

    `eq=False` because numpy arrays do not compare to a single bool; compare fields explicitly.
    """

    seq: int
    observation_id: str
    stream: str
    context_prev_seq: int | None
    label: str | None
    created_at: str
    image_sha256: str
    input_sdr: np.ndarray
    winner_cells: np.ndarray
    metadata: dict[str, Any] | None = None
    place: int | None = None  # the row whose place it joined (None: its own, or a row before version 5)


@dataclass(frozen=True)
class KeyRecord:
    """An idempotent post as stored (`idempotency_keys`): its key, what it asked (`fingerprint`) and the
    reply's JSON as first sent."""

    key: str
    fingerprint: str
    reply: str


def encode(values: np.ndarray | Sequence[int], dtype: str, what: str) -> bytes:
    """Validate a sorted set of indices and pack it little-endian.

    Unsorted or duplicated input is refused rather than sorted here: the blob is compared exactly at
    replay, so a caller that produced something else than it stores is a bug worth seeing at once.
    """
    a = np.asarray(values)
    if a.ndim != 1:
        raise ValueError(f"{what} must be 1-D, got shape {a.shape}")
    if a.size == 0:
        return b""
    if a.dtype.kind not in "iu":
        raise ValueError(f"{what} must hold integers, got {a.dtype}")
    hi = np.iinfo(dtype).max
    if int(a[0]) < 0 or int(a.max()) > hi:
        raise ValueError(f"{what} out of range [0, {hi}]")
    if a.size > 1 and not bool(np.all(a[1:] > a[:-1])):
        raise ValueError(f"{what} must be sorted ascending without duplicates")
    return a.astype(np.dtype(dtype).newbyteorder("<"), copy=False).tobytes()


def load_json(text: str | None) -> Any:
    """A JSON column's value (None for NULL); `StoreCorrupt` where the stored text is not JSON (a file
    edited or damaged outside the service: every reader of a row then says so, as for a bad blob)."""
    if text is None:
        return None
    try:
        return json.loads(text)
    except (ValueError, TypeError) as e:
        raise StoreCorrupt(f"a stored JSON value is unreadable ({e}): {str(text)[:40]!r}") from e


def decode(blob: bytes, dtype: str) -> np.ndarray:
    """A stored blob as sorted `INDEX_DTYPE` indices; `StoreCorrupt` when its length does not fit."""
    le = np.dtype(dtype).newbyteorder("<")
    if len(blob) % le.itemsize:
        raise StoreCorrupt(f"blob of {len(blob)} bytes is not a whole number of {dtype}")
    return np.frombuffer(blob, dtype=le).astype(INDEX_DTYPE)



def create_file(path: Path, meta: MapMeta) -> None:
    """Create a new `map.sqlite` at `path` atomically: schema and meta, or no file.

    The schema and meta are written to a temporary file beside `path`, which is closed (so its WAL
    is checkpointed into it), fsynced and renamed: a crash leaves either no map file or a complete
    one, never a file without meta.

    Raises:
        FileExistsError: `path` exists.
        StorageFull: no room to write (SQLite's words or the OS's); nothing is left behind.
    """
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path} exists")
    try:
        fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        if is_full_error(exc):
            raise StorageFull(f"{path}: no room to write ({exc})") from exc
        raise
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        conn = connect(tmp)
        try:
            # A temporary file: atomicity comes from the rename below, not from one transaction
            # (executescript would commit a pending transaction anyway).
            conn.executescript(_SCHEMA + _V2_TABLES + _V3_TABLES + _V4_TABLES + _CLOSURE_VERIFICATION
                               + _V5_TABLES + _PLACE_COLUMN + _V6_TABLES + _V7_TABLES + _CLOSURE_VISIT
                               + _V9_TABLES + _CLOSURE_RETRACTS + _V10_TABLES + _CLOSURE_SPAN
                               + _V12_TABLES + _V13_TABLES + _V14_TABLES)
            with transaction(conn):
                conn.executemany("INSERT INTO meta (key, value) VALUES (?, ?)", [
                    ("schema_version", json.dumps(meta.schema_version)),
                    ("map_id", json.dumps(meta.map_id)),
                    ("params", json.dumps(meta.params, sort_keys=True)),
                    ("projection_sha256", json.dumps(meta.projection_sha256)),
                    ("encoder_id", json.dumps(meta.encoder_id)),
                    ("cell_dtype", json.dumps(meta.cell_dtype)),
                ])
        finally:
            conn.close()
        with tmp.open("rb+") as f:
            os.fsync(f.fileno())
        if path.exists():  # re-check: another creator may have won meanwhile
            raise FileExistsError(f"{path} exists")
        os.replace(tmp, path)
    except BaseException as exc:
        for leftover in (tmp, Path(f"{tmp}-wal"), Path(f"{tmp}-shm")):
            with contextlib.suppress(OSError):
                leftover.unlink()
        # (a new file meets a full disk outside any transaction: at its first PRAGMA, in the schema's
        # script, at the fsync; said as every other write says it)
        if is_full_error(exc) and not isinstance(exc, StorageFull):
            raise StorageFull(f"{path}: no room to write ({exc})") from exc
        raise
    fsync_dir(path.parent)


def read_meta(conn: sqlite3.Connection, path: Path) -> MapMeta:
    """The frozen meta of an open map file; `StoreCorrupt` when it is not a map database."""
    tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    if not {"meta", "observations"} <= tables:
        raise StoreCorrupt(f"{path}: not a map database (tables {sorted(tables)})")
    raw = dict(conn.execute("SELECT key, value FROM meta").fetchall())
    try:
        values = {k: json.loads(v) for k, v in raw.items()}
        return MapMeta(map_id=values["map_id"], params=values["params"],
                       projection_sha256=values["projection_sha256"], encoder_id=values["encoder_id"],
                       cell_dtype=values["cell_dtype"], schema_version=int(values["schema_version"]))
    except (KeyError, ValueError, TypeError) as exc:
        raise StoreCorrupt(f"{path}: unreadable meta: {exc}") from exc
