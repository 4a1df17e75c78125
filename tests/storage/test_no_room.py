"""No room to write is storage's answer, not a bug (storage._common.is_full_error): the disk full, a quota
used up, the file-size limit reached all come back as StorageFull, and what was committed stays."""

from __future__ import annotations

import errno
import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from storage._common import is_full_error


def test_a_file_size_limit_is_no_room_and_what_was_committed_stays(tmp_path):
    # In a child: `ulimit -f` of 256 KiB (Python ignores SIGXFSZ, so the write fails with EFBIG, which
    # SQLite reports as SQLITE_IOERR_WRITE). Before: a plain sqlite3.OperationalError, answered 500.
    pytest.importorskip("resource", reason="needs POSIX resource limits")
    code = textwrap.dedent(f"""
        import resource, sqlite3
        from storage._common import StorageFull, connect, transaction
        conn = connect({str(tmp_path / "x.sqlite")!r})
        conn.execute("CREATE TABLE t (b BLOB)")
        resource.setrlimit(resource.RLIMIT_FSIZE, (256 * 1024, resource.RLIM_INFINITY))
        done = 0
        try:
            for _ in range(1000):
                with transaction(conn):
                    conn.execute("INSERT INTO t VALUES (zeroblob(16384))")
                done += 1
        except StorageFull:
            print("full", done, conn.execute("SELECT count(*) FROM t").fetchone()[0])
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).resolve().parents[2])
    assert out.returncode == 0, out.stderr[-2000:]
    kind, done, rows = out.stdout.split()
    assert kind == "full" and 0 < int(done) == int(rows)  # every committed row kept, the failed one not


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EDQUOT, errno.EFBIG])
def test_no_room_errnos(code):
    assert is_full_error(OSError(code, "no room"))


def test_other_errors_are_not_no_room():
    assert not is_full_error(OSError(errno.EACCES, "denied"))
    assert not is_full_error(sqlite3.IntegrityError("UNIQUE constraint failed"))
    assert not is_full_error(ValueError("x"))


def test_a_map_file_created_on_a_full_disk_is_storage_full_and_leaves_nothing(tmp_path, monkeypatch):
    """A new file meets a full disk outside any transaction (its first PRAGMA, the schema's script): before,
    a plain sqlite3.OperationalError, which the service answered 500."""
    import storage.mapschema as mapschema
    from storage._common import StorageFull

    real = mapschema.connect

    def capped(path, **kw):  # the file may not grow past one page: SQLite's own SQLITE_FULL
        conn = real(path, **kw)
        conn.execute("PRAGMA max_page_count = 1")
        return conn

    monkeypatch.setattr(mapschema, "connect", capped)
    meta = mapschema.MapMeta(map_id="m", params={}, projection_sha256="0" * 64, encoder_id="e",
                             cell_dtype="uint16")
    with pytest.raises(StorageFull, match="database or disk is full"):
        mapschema.create_file(tmp_path / "map.sqlite", meta)
    assert list(tmp_path.iterdir()) == []


def test_the_room_probe_says_no_room_where_the_os_refuses_the_write_and_leaves_no_file(tmp_path):
    # In a child under a file-size limit of 64 KiB: a probe of more is refused (EFBIG), one of less fits.
    pytest.importorskip("resource", reason="needs POSIX resource limits")
    code = textwrap.dedent(f"""
        import os, resource
        from storage.mapschema import MapMeta
        from storage.mapstore import MapStore
        store = MapStore.create({str(tmp_path / "map.sqlite")!r},
                                MapMeta(map_id="m", params={{}}, projection_sha256="0" * 64, encoder_id="e"))
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, resource.RLIM_INFINITY))
        print(store.has_room(1 << 20), store.has_room(4096), sorted(os.listdir({str(tmp_path)!r})))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).resolve().parents[2])
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split(" ", 2)[:2] == ["False", "True"]
    assert ".room-probe" not in out.stdout and "map.sqlite" in out.stdout
