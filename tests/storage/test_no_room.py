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


def test_a_whole_map_or_catalog_on_a_disk_with_no_room_for_its_shm_is_full_not_corrupt(tmp_path):
    """In a child under a file-size limit of 16 KiB, below the 32 KiB -shm file a WAL database needs when
    it is opened (SQLITE_IOERR_SHMSIZE, as on a full disk): a healthy map file and the catalog are
    StorageFull, never StoreCorrupt (the map was called corrupt at a restart on a full disk, and an
    operator deletes a corrupt map); a new map file is StorageFull and leaves nothing. The files are
    unchanged, and with the limit lifted they open whole."""
    pytest.importorskip("resource", reason="needs POSIX resource limits")
    code = textwrap.dedent(f"""
        import hashlib, os, resource
        from pathlib import Path
        from storage._common import StorageFull
        from storage.catalog import Catalog
        from storage.mapschema import MapMeta, create_file
        from storage.mapstore import MapStore
        root = Path({str(tmp_path)!r})
        meta = MapMeta(map_id="m", params={{}}, projection_sha256="0" * 64, encoder_id="e")
        MapStore.create(root / "map.sqlite", meta).close()
        Catalog.open(root / "catalog.sqlite").close()
        def digests():
            return [hashlib.sha256((root / n).read_bytes()).hexdigest()
                    for n in ("map.sqlite", "catalog.sqlite")]
        before = digests()
        resource.setrlimit(resource.RLIMIT_FSIZE, (16 * 1024, resource.RLIM_INFINITY))
        said = []
        for open_it in (lambda: MapStore.open(root / "map.sqlite"),
                        lambda: Catalog.open(root / "catalog.sqlite"),
                        lambda: create_file(root / "new.sqlite", meta)):
            try:
                open_it().close()
                said.append("opened")
            except StorageFull as e:
                said.append("full" if "no room" in str(e) else str(e))
            except Exception as e:
                said.append(type(e).__name__)
        left = [n for n in os.listdir(root) if n.startswith(("new.", ".new."))]
        print(" ".join(said), digests() == before, left == [])
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).resolve().parents[2])
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["full", "full", "full", "True", "True"]
    from storage.catalog import Catalog
    from storage.mapstore import MapStore

    store = MapStore.open(tmp_path / "map.sqlite")
    assert store.quick_check() and store.count() == 0
    store.close()
    Catalog.open(tmp_path / "catalog.sqlite").close()
