"""A map file the OS or the disk will not give as asked (storage/_common.py `connect`, storage/mapstore/
store.py `open`): a damaged page is `StoreCorrupt` from any read, a file that cannot be opened is
`StoreUnopenable` (never corrupt), a write to a file held read-only is `StoreReadOnly`; no sqlite3 error
reaches the caller for any of them."""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from storage.mapstore import MapMeta, MapStore, NewObservation, StoreCorrupt, StoreReadOnly, StoreUnopenable


@contextmanager
def unwritable(path: Path) -> Iterator[None]:
    """`path` read-only for this process, for real: `chmod 0444`, or as root (which permissions do not
    stop) `chattr +i`; skips where neither holds."""
    if os.geteuid() != 0:
        mode = path.stat().st_mode
        os.chmod(path, 0o444)
        try:
            yield
        finally:
            os.chmod(path, mode)
        return
    if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(path)],
                                                        capture_output=True).returncode != 0:
        pytest.skip("root ignores permissions, and chattr +i is not available here")
    try:
        yield
    finally:
        subprocess.run(["chattr", "-i", str(path)], check=True)


def filled(path: Path, meta: MapMeta, row_factory: Callable[..., NewObservation], n: int = 60) -> None:
    with MapStore.create(path, meta) as s:
        s.append_many([row_factory(i) for i in range(n)])


def test_a_malformed_page_is_store_corrupt_from_a_read_not_a_sqlite3_error(tmp_path, meta, row_factory):
    db = tmp_path / "map.sqlite"
    filled(db, meta, row_factory)
    with MapStore.open(db, readonly=True) as s:
        assert s.count_after(0) == 60
    conn = sqlite3.connect(db)
    root = conn.execute("SELECT rootpage FROM sqlite_master WHERE name = 'observations'").fetchone()[0]
    size = conn.execute("PRAGMA page_size").fetchone()[0]
    conn.close()
    with open(db, "r+b") as f:  # what the probe did: random bytes over a page (here the observations')
        f.seek((root - 1) * size)
        f.write(os.urandom(size))
    with MapStore.open(db, readonly=True) as s, pytest.raises(StoreCorrupt, match="malformed"):
        s.count_after(0)


def test_a_file_sqlite_cannot_open_is_unopenable_with_the_os_words_not_corrupt(tmp_path, meta, row_factory,
                                                                                  monkeypatch):
    db = tmp_path / "map.sqlite"
    filled(db, meta, row_factory, 1)
    real = sqlite3.connect

    def cannot_open(*args, **kwargs):  # SQLite's own CANTOPEN, as for a file it may not read
        return real("file:/nonexistent-dir/map.sqlite?mode=ro", uri=True)

    monkeypatch.setattr(sqlite3, "connect", cannot_open)
    with pytest.raises(StoreUnopenable, match="unable to open database file") as e:
        MapStore.open(db)
    assert not isinstance(e.value, StoreCorrupt)


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads a file whatever its permissions")
def test_a_file_without_permissions_is_unopenable(tmp_path, meta, row_factory):
    db = tmp_path / "map.sqlite"
    filled(db, meta, row_factory, 1)
    os.chmod(db, 0)
    try:
        with pytest.raises(StoreUnopenable, match="Permission denied"):
            MapStore.open(db)
    finally:
        os.chmod(db, 0o644)


def test_a_write_to_a_file_held_read_only_is_store_read_only_and_commits_nothing(tmp_path, meta,
                                                                                 row_factory):
    db = tmp_path / "map.sqlite"
    filled(db, meta, row_factory, 3)
    with MapStore.open(db) as s:
        assert s.writable
    with unwritable(db), MapStore.open(db) as s:  # SQLite opens it read-only without a word
        assert not s.writable
        with pytest.raises(StoreReadOnly, match="readonly"):
            s.append(row_factory(3))
        assert s.count() == 3 and s.last_seq() == 3
    with MapStore.open(db, readonly=True) as s:
        assert s.count() == 3


@pytest.mark.parametrize("readonly", [False, True])
def test_a_file_that_is_no_database_is_store_corrupt_naming_the_file(tmp_path, readonly):
    db = tmp_path / "map.sqlite"
    db.write_bytes(b"not a database at all " * 400)  # read first by connect (read-write) or read_meta
    with pytest.raises(StoreCorrupt, match="is not a database") as e:
        MapStore.open(db, readonly=readonly)
    assert str(e.value).startswith(f"{db}: ")


def test_a_text_cell_that_is_not_utf8_is_store_corrupt(tmp_path, meta, row_factory):
    """An outside probe flipped bits in a map file: SQLite's page checks passed, and a text cell no longer
    decoded, which reached `cortexloc verify` and the server as a bare UnicodeDecodeError."""
    db = tmp_path / "map.sqlite"
    filled(db, meta, row_factory, 3)
    conn = sqlite3.connect(db, isolation_level=None)
    conn.execute("CREATE TABLE spare (x)")
    conn.execute("PRAGMA writable_schema = ON")  # the bytes of a flipped name in the schema, as stored
    conn.execute("UPDATE sqlite_master SET name = CAST(x'739d' AS TEXT) WHERE name = 'spare'")
    conn.close()
    with pytest.raises(StoreCorrupt, match="not UTF-8"):
        MapStore.open(db, readonly=True)


def test_a_row_whose_text_is_not_utf8_is_store_corrupt(tmp_path, meta, row_factory):
    """(From review.) The common case: a flipped byte in a row's text cell, which Python's sqlite3 says as
    an OperationalError with no SQLite code."""
    db = tmp_path / "map.sqlite"
    filled(db, meta, row_factory, 5)
    with MapStore.open(db, readonly=True) as s:
        oid = s.observation_id(3)
    raw = db.read_bytes()
    assert oid is not None and oid.encode() in raw
    flipped = oid.encode()[:-2] + b"\x9d" + oid.encode()[-1:]  # one byte, in the row and its index alike
    db.write_bytes(raw.replace(oid.encode(), flipped))
    with MapStore.open(db, readonly=True) as s, pytest.raises(StoreCorrupt, match="not UTF-8"):
        list(s.rows())
