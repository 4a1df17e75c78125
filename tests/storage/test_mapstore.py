"""map.sqlite: schema, exact round trip, seq rules, durability settings, checks, and a SIGKILL mid-stream."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from storage.mapstore import (
    DuplicateObservation,
    MapMeta,
    MapStore,
    NewObservation,
    Observation,
    StoreCorrupt,
    cell_dtype_for,
)

REPO = Path(__file__).resolve().parents[2]
RowFactory = Callable[..., NewObservation]


def same(stored: Observation, sent: NewObservation) -> None:
    """Every field equal, arrays exactly."""
    assert stored.observation_id == sent.observation_id
    assert stored.stream == sent.stream
    assert stored.context_prev_seq == sent.context_prev_seq
    assert stored.label == sent.label
    assert stored.created_at == sent.created_at
    assert stored.image_sha256 == sent.image_sha256
    np.testing.assert_array_equal(stored.input_sdr, sent.input_sdr)
    np.testing.assert_array_equal(stored.winner_cells, sent.winner_cells)


def test_schema_is_the_spec(store: MapStore) -> None:
    conn = sqlite3.connect(store.path)
    cols = {r[1]: (r[2], r[3], r[5]) for r in conn.execute("PRAGMA table_info(observations)")}
    assert list(cols) == ["seq", "observation_id", "stream", "context_prev_seq", "label", "created_at",
                          "image_sha256", "input_sdr", "winner_cells", "metadata", "place"]
    assert cols["metadata"] == ("TEXT", 0, 0)  # nullable
    assert cols["seq"] == ("INTEGER", 0, 1)  # INTEGER PRIMARY KEY: the rowid itself
    assert cols["context_prev_seq"][1] == 0 and cols["label"][1] == 0  # nullable
    assert cols["input_sdr"][0] == cols["winner_cells"][0] == "BLOB"
    unique = [r for r in conn.execute("PRAGMA index_list(observations)") if r[2]]
    assert any(conn.execute(f"PRAGMA index_info({r[1]!r})").fetchone()[2] == "observation_id" for r in unique)
    meta = dict(conn.execute("SELECT key, value FROM meta"))
    assert set(meta) == {"schema_version", "map_id", "params", "projection_sha256", "encoder_id",
                         "cell_dtype"}
    conn.close()


def test_round_trip_exact(store: MapStore, row_factory: RowFactory) -> None:
    sent = [row_factory(1), row_factory(2, prev=1, label="pose 1.0 2.0"), row_factory(3, stream="cam-2")]
    seqs = [store.append(r) for r in sent]
    assert seqs == [1, 2, 3]
    stored = list(store.rows())
    assert [r.seq for r in stored] == seqs
    for got, want in zip(stored, sent, strict=True):
        same(got, want)
        assert got.winner_cells.dtype == np.int32
    same(store.get(2), sent[1])
    assert store.get(99) is None
    assert [r.seq for r in store.rows(after_seq=1)] == [2, 3]
    assert sorted(store.get_many([3, 1, 42])) == [1, 3]
    assert store.count() == 3 and store.last_seq() == 3
    # The blobs are the documented little-endian uint16 bytes.
    conn = sqlite3.connect(store.path)
    blob, cells = conn.execute("SELECT input_sdr, winner_cells FROM observations WHERE seq = 1").fetchone()
    assert blob == np.asarray(sent[0].input_sdr, dtype="<u2").tobytes()
    assert cells == np.asarray(sent[0].winner_cells, dtype="<u2").tobytes()
    conn.close()


def test_uint32_cells_above_65536(tmp_path: Path, meta: MapMeta, row_factory: RowFactory) -> None:
    assert cell_dtype_for(65_536) == "uint16" and cell_dtype_for(65_537) == "uint32"
    m = MapMeta(meta.map_id, meta.params, meta.projection_sha256, meta.encoder_id, "uint32")
    with MapStore.create(tmp_path / "big.sqlite", m) as s:
        row = row_factory(5, n_cells=1 << 20)
        assert int(row.winner_cells.max()) > 65_535
        s.append(row)
        same(s.get(1), row)
    with MapStore.create(tmp_path / "small.sqlite", meta) as s, pytest.raises(ValueError, match="range"):
        s.append(row)


def test_bad_rows_are_refused_and_consume_nothing(store: MapStore, row_factory: RowFactory) -> None:
    good = row_factory(1)
    for bad in (
        NewObservation("s", "x", np.array([3, 1]), good.winner_cells),            # unsorted
        NewObservation("s", "x", np.array([1, 1]), good.winner_cells),            # duplicate
        NewObservation("s", "x", np.array([-1, 2]), good.winner_cells),           # negative
        NewObservation("s", "x", good.input_sdr, np.array([70_000])),             # beyond uint16
        NewObservation("s", "x", good.input_sdr, np.array([[1, 2]])),             # not 1-D
        NewObservation("s", "x", good.input_sdr, np.array([0.5])),                # not integers
        NewObservation("s", "x", good.input_sdr, good.winner_cells, context_prev_seq=1),  # not earlier
    ):
        with pytest.raises(ValueError):
            store.append(bad)
    assert store.append(good) == 1
    with pytest.raises(DuplicateObservation):
        store.append(row_factory(1))
    assert store.append(row_factory(2)) == 2  # the failed append used no seq
    assert store.count() == 2


def test_empty_sets_round_trip(store: MapStore) -> None:
    row = NewObservation("s", "x", np.zeros(0, np.int64), np.zeros(0, np.int64))
    seq = store.append(row)
    got = store.get(seq)
    assert got.input_sdr.size == 0 and got.winner_cells.size == 0


def test_a_reader_sees_the_file_as_of_its_first_read_while_the_writer_commits(
        store: MapStore, row_factory: RowFactory) -> None:
    """`MapStore.reader`: a long read (a repair's listing) on its own connection, in one read transaction."""
    store.append(row_factory(1))
    with store.reader() as reader:
        assert reader.get(1) is not None and reader.get(2) is None  # its first read: the moment it sees
        assert store.append(row_factory(2, prev=1)) == 2  # the writer is not held by it
        assert store.get(2) is not None and reader.get(2) is None
        assert sorted(reader.get_many([1, 2])) == [1]
    with store.reader() as reader:
        assert reader.get(2) is not None
    assert store.append(row_factory(3, prev=2)) == 3 and store.count() == 3


def test_observations_are_append_only(store: MapStore, row_factory: RowFactory) -> None:
    store.append(row_factory(1))
    conn = sqlite3.connect(store.path)
    with pytest.raises(sqlite3.IntegrityError, match="append-only"):
        conn.execute("UPDATE observations SET label = 'x'")
    with pytest.raises(sqlite3.IntegrityError, match="append-only"):
        conn.execute("DELETE FROM observations")
    with pytest.raises(sqlite3.IntegrityError, match="frozen"):
        conn.execute("UPDATE meta SET value = '2' WHERE key = 'schema_version'")
    conn.close()
    assert store.count() == 1


def test_seq_increasing_and_never_reused(tmp_path: Path, meta: MapMeta, row_factory: RowFactory) -> None:
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as s:
        assert [s.append(row_factory(i)) for i in range(1, 4)] == [1, 2, 3]
        assert s.append_many([row_factory(4), row_factory(5)]) == [4, 5]  # group commit
        s.backup_to(tmp_path / "at5.sqlite")
        s.append_many([row_factory(6), row_factory(7)])
        high_water = s.last_seq()
    with MapStore.open(path) as s:
        assert s.next_seq() == 8
        assert s.append(row_factory(8)) == 8
    # A restore puts the older file back; with the catalog's high-water mark the seqs go on above it.
    MapStore.install_copy(tmp_path / "at5.sqlite", path)
    assert not Path(f"{path}-wal").exists()
    with MapStore.open(path, seq_floor=high_water + 1) as s:
        assert s.last_seq() == 5 and s.count() == 5
        assert s.append(row_factory(9)) == 9
        s.raise_seq_floor(3)  # never lowers
        assert s.append(row_factory(10)) == 10
        s.raise_seq_floor(20)
        assert s.append(row_factory(11)) == 21
        assert [r.seq for r in s.rows()] == [1, 2, 3, 4, 5, 9, 10, 21]
        assert s.durability()["journal_mode"] == "wal"  # the DELETE-mode copy is back in WAL


def test_durability_settings(store: MapStore, row_factory: RowFactory) -> None:
    assert store.durability() == {"journal_mode": "wal", "synchronous": 2}  # 2 = FULL
    store.append(row_factory(1))
    assert store.wal_bytes() > 0 and store.db_bytes() > 0
    other = sqlite3.connect(store.path)  # journal_mode is a property of the file
    assert other.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    other.close()


def test_checks_and_corruption(tmp_path: Path, store: MapStore, row_factory: RowFactory) -> None:
    for i in range(1, 50):
        store.append(row_factory(i))
    assert store.quick_check() and store.integrity_check()
    garbage = tmp_path / "garbage.sqlite"
    garbage.write_bytes(os.urandom(8192))
    with pytest.raises(StoreCorrupt):
        MapStore.open(garbage)
    empty = tmp_path / "other.sqlite"
    sqlite3.connect(empty).execute("CREATE TABLE t (x)").connection.close()
    with pytest.raises(StoreCorrupt, match="not a map database"):
        MapStore.open(empty)
    with pytest.raises(FileNotFoundError):
        MapStore.open(tmp_path / "missing.sqlite")
    with pytest.raises(FileExistsError):
        MapStore.create(store.path, store.meta)


def test_quick_check_detects_damage(tmp_path: Path, meta: MapMeta, row_factory: RowFactory) -> None:
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as s:
        s.append_many([row_factory(i) for i in range(1, 400)])
    data = bytearray(path.read_bytes())
    page = 4096
    # Falsify the "fragmented free bytes" count in the header of every table leaf page (type 0x0D):
    # rows still read, so the store opens, but the page accounting no longer adds up.
    damaged = 0
    for p in range(1, len(data) // page):
        if data[p * page] == 0x0D:
            data[p * page + 7] = (data[p * page + 7] + 17) % 256
            damaged += 1
    assert damaged
    path.write_bytes(bytes(data))
    with MapStore.open(path) as s:
        assert s.count() == 399
        assert not s.quick_check()
        assert not s.integrity_check()


def test_backup_is_self_contained(tmp_path: Path, store: MapStore, row_factory: RowFactory) -> None:
    store.append(row_factory(1))
    size = store.backup_to(tmp_path / "copy.sqlite")
    assert size == (tmp_path / "copy.sqlite").stat().st_size
    assert not Path(f"{tmp_path / 'copy.sqlite'}-wal").exists()
    ro = sqlite3.connect(f"file:{tmp_path / 'copy.sqlite'}?mode=ro", uri=True)
    assert ro.execute("PRAGMA journal_mode").fetchone()[0] == "delete"
    assert ro.execute("SELECT observation_id FROM observations").fetchall() == [("obs-00000001",)]
    ro.close()
    with pytest.raises(FileExistsError):
        store.backup_to(tmp_path / "copy.sqlite")


_WRITER = textwrap.dedent("""
    import importlib.util
    import sys

    # The rows come from the tests' own conftest, so the parent can recompute every one of them.
    spec = importlib.util.spec_from_file_location("storage_rows", sys.argv[2])
    rows = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(rows)
    from storage.mapstore import MapStore

    store = MapStore.open(sys.argv[1])
    group = int(sys.argv[3])  # 0: each append durable; else groups committed without fsync, then one sync
    i = store.last_seq()
    while True:
        acks = []
        for _ in range(max(group, 1)):
            i += 1
            row = rows.make_row(i)
            acks.append((store.append(row, durable=not group), row.observation_id))
        if group:
            store.sync()
        # Printed only after append (or the group's sync) returned: this is the acknowledgement.
        for seq, oid in acks:
            print(seq, oid, flush=True)
""")


def _run_and_kill(path: Path, acks_wanted: int, group: int = 0) -> list[tuple[int, str]]:
    """Start a writer (`group`: see _WRITER), read its acknowledgements, SIGKILL it while it is still
    appending."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    conftest = Path(__file__).with_name("conftest.py")
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(path), str(conftest), str(group)],
                            stdout=subprocess.PIPE, env=env, cwd=REPO)
    acks: list[tuple[int, str]] = []
    deadline = time.monotonic() + 10
    assert proc.stdout is not None
    while len(acks) < acks_wanted and time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        seq, oid = line.split()
        acks.append((int(seq), oid.decode()))
    os.kill(proc.pid, signal.SIGKILL)  # mid-stream: the writer is inside its append loop
    # Lines already in the pipe, or read ahead into the BufferedReader by readline(), were printed after
    # their commit: acknowledged too. Read them through the buffer (communicate() with a timeout reads
    # the raw fd and would skip what readline() buffered); the pipe closes with the killed writer.
    rest = proc.stdout.read()
    proc.wait(timeout=10)
    acks += [(int(a), b.decode()) for a, b in (ln.split() for ln in rest.splitlines() if ln.strip())]
    assert proc.returncode == -signal.SIGKILL
    return acks


def test_sigkill_mid_stream_loses_nothing_acknowledged(tmp_path: Path, meta: MapMeta,
                                                       row_factory: RowFactory) -> None:
    path = tmp_path / "map.sqlite"
    MapStore.create(path, meta).close()
    acked: list[tuple[int, str]] = []
    for round_ in range(3):
        acks = _run_and_kill(path, acks_wanted=60 + 37 * round_)
        assert acks, "the writer acknowledged nothing"
        acked += acks
        with MapStore.open(path) as s:
            assert s.integrity_check()
            rows = {r.seq: r for r in s.rows()}
            for seq, oid in acked:
                assert rows[seq].observation_id == oid
                same(rows[seq], row_factory(seq))
            # Nothing unsent appears: seqs are 1..n, and beyond the acknowledged rows at most the one
            # commit that finished but was not printed yet when the kill came.
            assert sorted(rows) == list(range(1, len(rows) + 1))
            assert len(acked) <= len(rows) <= len(acked) + 1
            for seq in rows:
                same(rows[seq], row_factory(seq))
            acked = [(seq, r.observation_id) for seq, r in rows.items()]
    with MapStore.open(path) as s:
        assert s.append(row_factory(len(acked) + 1)) == len(acked) + 1


def test_group_commit_loses_nothing_acknowledged_at_a_sigkill(tmp_path: Path, meta: MapMeta,
                                                               row_factory: RowFactory) -> None:
    """Rows committed without their fsync (`durable=False`) and acknowledged after the group's `sync`
    are all there after a SIGKILL mid-stream; what was committed but not yet acknowledged may be."""
    path = tmp_path / "map.sqlite"
    MapStore.create(path, meta).close()
    acked: list[tuple[int, str]] = []
    for round_ in range(2):
        acked += _run_and_kill(path, acks_wanted=50 + 35 * round_, group=5)
        with MapStore.open(path) as s:
            assert s.integrity_check()
            rows = {r.seq: r for r in s.rows()}
            assert sorted(rows) == list(range(1, len(rows) + 1))
            for seq, oid in acked:
                assert rows[seq].observation_id == oid
                same(rows[seq], row_factory(seq))
            acked = [(seq, r.observation_id) for seq, r in rows.items()]


def test_sync_fsyncs_the_wal_and_its_directory_entry(store: MapStore, row_factory: RowFactory,
                                                     monkeypatch) -> None:
    """The group commit's fsync: the WAL file the deferred commits went to (its directory once per WAL
    file); the connection is back to synchronous=FULL after a deferred commit."""
    from storage.mapstore import copies  # where the store syncs

    synced: list[int] = []
    dirs: list[Path] = []
    real_fsync = os.fsync
    monkeypatch.setattr(copies.os, "fsync", lambda fd: (synced.append(os.fstat(fd).st_ino), real_fsync(fd)))
    monkeypatch.setattr(copies, "fsync_dir", lambda d: dirs.append(Path(d)))
    assert store.append(row_factory(1), durable=False) == 1
    assert store.durability()["synchronous"] == 2  # FULL again for every other commit
    assert synced == []  # committed, visible, not synced by us yet
    assert store.get(1).observation_id == row_factory(1).observation_id
    store.sync()
    wal = Path(f"{store.path}-wal")
    assert synced == [wal.stat().st_ino] and dirs == [store.path.parent]
    store.append(row_factory(2), durable=False)
    store.sync()
    assert len(synced) == 2 and len(dirs) == 1  # the directory entry of this WAL file is on disk already
    store.close()
    store.sync()  # closed: SQLite checkpointed and synced on close, nothing to do
    assert len(synced) == 2


def test_a_migration_without_room_is_a_full_disk_not_corruption(tmp_path: Path, meta: MapMeta,
                                                                  monkeypatch) -> None:
    """Found by review: SQLITE_FULL during the v1 -> v2 migration was reported as a corrupt database, so
    the map was failed as `database-corrupt` although its file is whole (the migration is one transaction)."""
    from storage import mapstore
    from storage.mapstore import store  # where the store opens (and migrates) a file

    MapStore.create(tmp_path / "map.sqlite", meta).close()

    def no_room(conn, m):
        exc = sqlite3.OperationalError("database or disk is full")
        exc.sqlite_errorname = "SQLITE_FULL"
        raise exc

    monkeypatch.setattr(store, "migrate", no_room)
    with pytest.raises(mapstore.StorageFull):
        MapStore.open(tmp_path / "map.sqlite")
    monkeypatch.undo()
    MapStore.open(tmp_path / "map.sqlite").close()  # the file is whole
