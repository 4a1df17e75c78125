"""`map.sqlite`: one map's frozen metadata and its append-only observations (docs/design/service.md §4.2,
§4.3).

One SQLite file per map, so maps never contend for SQLite's single writer and a map moves between
servers as one directory. The file is the system of record: the in-memory TM and index are rebuilt
from it (snapshot + replay, §4.4), so a row, once committed, is never changed or removed — triggers
refuse UPDATE and DELETE on `observations`, and a restore replaces the whole file instead
(`MapStore.install_copy`). The one exception (schema 12): a warm-up join turns the row it joins into a
visit, which replays it, and deletes the row in the same transaction (docs/design/science.md §11.8).

Sequence numbers: `seq` is assigned here, strictly increasing and never reused. SQLite's own choice
(max(rowid)+1) would reuse seqs after a restore rolls the file back, so the caller passes the
catalog's high-water mark as `seq_floor` and the next seq is `max(last_seq, seq_floor) + 1`.

`MapStore` (store.py: the connection, its lifecycle, what the file holds) composes one module per family
of tables: observations.py (rows, their seqs, thumbnails, idempotency keys), visits.py (visits, joins,
dropped rows), streams.py (stream states, recency), closures.py (the loop-closure log, repairs),
keyframes.py, copies.py (sync, checks, sizes, backup, install). The schema, the row types and what each
version holds are `storage.mapschema`'s alone.
"""

from storage._common import StorageError, StorageFull, StoreClosed, StoreReadOnly, StoreUnopenable
from storage.mapschema import (
    CELL_DTYPES,
    INPUT_DTYPE,
    SCHEMA_VERSION,
    DuplicateObservation,
    KeyRecord,
    LoopClosure,
    MapMeta,
    NewClosure,
    NewObservation,
    NewVisit,
    Observation,
    Repair,
    StoreCorrupt,
    Visit,
    cell_dtype_for,
)
from storage.mapstore.store import MapStore

__all__ = [
    "CELL_DTYPES",
    "INPUT_DTYPE",
    "SCHEMA_VERSION",
    "DuplicateObservation",
    "KeyRecord",
    "LoopClosure",
    "MapMeta",
    "MapStore",
    "NewClosure",
    "NewObservation",
    "NewVisit",
    "Observation",
    "Repair",
    "StorageError",
    "StorageFull",
    "StoreClosed",
    "StoreCorrupt",
    "StoreReadOnly",
    "StoreUnopenable",
    "Visit",
    "cell_dtype_for",
]
