"""A map whose storage refuses writes or cannot be opened (service/maps/runtime/recovering.py, writer.py;
docs/design/service.md §4.4): `read-only` (it localises, what learns is refused as such, nothing half
stored) or `failed` `unopenable`, never `database-corrupt` for a permission."""

from __future__ import annotations

import sqlite3

import pytest

from service.maps.config import MapOptions
from service.maps.errors import MapReadOnly, MapUnavailable
from tests.service.helpers import tm_digest
from tests.service.maps.maps_fixtures import registry, route, step
from tests.storage.test_mapstore_faults import unwritable


def test_a_commit_the_store_refuses_as_read_only_is_map_read_only_and_learns_nothing(tmp_path):
    with registry(tmp_path) as reg:
        rt = reg.create("flat", MapOptions(memory="none"))  # matches by the code itself: exact places
        frames = route(5)
        for f in frames[:3]:
            step(rt, f)
        live, count = tm_digest(rt.tm), rt.store.count()
        # SQLite refuses the write as for a file it opened read-only (SQLITE_READONLY)
        rt.store._db().execute("PRAGMA query_only = ON")
        with pytest.raises(MapReadOnly, match=r"read-only: its storage .*map.sqlite. refuses writes"):
            step(rt, frames[3])
        assert (rt.state, rt.state_reason) == ("read-only", "storage-read-only")
        assert rt.store.count() == len(rt.index) == count and tm_digest(rt.tm) == live
        assert step(rt, frames[1], learn=False, stream="q").matches[0].seq == 2  # it still localises
        with pytest.raises(MapReadOnly):  # refused up front now: no step, no rebuild
            step(rt, frames[4])
        assert rt.store.count() == count and tm_digest(rt.tm) == live


def test_a_map_file_read_only_at_start_is_read_only_not_ready(tmp_path):
    with registry(tmp_path) as reg:
        rt = reg.create("flat", MapOptions(memory="none"))
        for f in route(3):
            step(rt, f)
    db = tmp_path / "maps" / "flat" / "map.sqlite"
    with unwritable(db), registry(tmp_path) as reg:
        rt = reg.get("flat")
        assert (rt.state, rt.state_reason) == ("read-only", "storage-read-only")
        assert step(rt, route(3)[1], learn=False, stream="q").matches[0].seq == 2
        with pytest.raises(MapReadOnly):
            step(rt, route(4, seed=1)[0])
        assert rt.store.count() == 3


def test_a_map_file_sqlite_cannot_open_is_failed_unopenable_not_corrupt(tmp_path, monkeypatch):
    with registry(tmp_path) as reg:
        step(reg.get("default"), route(1)[0])
    real = sqlite3.connect

    def cannot_open(database, *args, **kwargs):  # SQLite's own CANTOPEN for the map's file alone
        if str(database).endswith("map.sqlite"):
            return real("file:/nonexistent-dir/map.sqlite?mode=ro", uri=True)
        return real(database, *args, **kwargs)

    monkeypatch.setattr(sqlite3, "connect", cannot_open)
    with registry(tmp_path) as reg:
        rt = reg.get("default")
        assert (rt.state, rt.state_reason) == ("failed", "unopenable")
        with pytest.raises(MapUnavailable, match=r"could not be opened .* nothing says it is damaged"):
            rt.require_ready(learns=False)


def test_a_map_opened_with_no_room_for_its_shm_is_failed_disk_full_even_where_the_catalog_is_full(
        tmp_path, monkeypatch):
    """SQLite makes a WAL database's -shm file at its open; on a full disk that is SQLITE_IOERR_SHMSIZE,
    which called a healthy map corrupt (an operator deletes a corrupt map). Its state cannot be written to
    a full catalog either: it is served as failed all the same, and the file is untouched."""
    from storage.catalog import Catalog
    from storage.mapstore import StorageFull

    with registry(tmp_path) as reg:
        step(reg.get("default"), route(1)[0])
    db = tmp_path / "maps" / "default" / "map.sqlite"
    before = db.read_bytes()
    real = sqlite3.connect

    def no_room_for_the_shm(database, *args, **kwargs):
        conn = real(database, *args, **kwargs)
        if str(database).endswith("map.sqlite"):
            err = sqlite3.OperationalError("disk I/O error")
            err.sqlite_errorname = "SQLITE_IOERR_SHMSIZE"
            conn.close()
            raise err
        return conn

    def catalog_full(self, *args, **kwargs):
        raise StorageFull("catalog.sqlite: database or disk is full")

    monkeypatch.setattr(sqlite3, "connect", no_room_for_the_shm)
    monkeypatch.setattr(Catalog, "set_state", catalog_full)
    with registry(tmp_path) as reg:
        rt = reg.get("default")
        assert (rt.state, rt.state_reason) == ("failed", "disk-full")
    monkeypatch.undo()
    assert db.read_bytes() == before
    with registry(tmp_path) as reg:  # room made: a restart opens it whole
        assert reg.get("default").state == "ready" and reg.get("default").store.count() == 1


def test_a_read_only_map_answers_a_localising_revisit_and_says_it_is_read_only_once(tmp_path, caplog):
    """A localising revisit would log its loop closure, which a read-only store refuses: the robot still
    gets its answer (it learned nothing), the closure is not logged, and the log says read-only once."""
    frames = route(30)
    with registry(tmp_path) as reg:
        rt = reg.create("flat", MapOptions(memory="none"))
        for f in frames:
            step(rt, f)
        # the same route localised on the writable map: which frames are revisits
        control = [(p := step(rt, f, learn=False, stream="q").place) is not None and p.revisit
                   for f in frames[:15]]
        closures = rt.store.last_closure_id()
    assert sum(control) >= 5
    db = tmp_path / "maps" / "flat" / "map.sqlite"
    caplog.set_level("ERROR", logger="cortexloc.runtime")
    with unwritable(db), registry(tmp_path) as reg:
        rt = reg.get("flat")
        assert (rt.state, rt.state_reason) == ("read-only", "storage-read-only")
        answers = [step(rt, f, learn=False, stream="q").place for f in frames[:15]]
        assert [p is not None and p.revisit for p in answers] == control
        assert (rt.state, rt.state_reason) == ("read-only", "storage-read-only")
        assert rt.store.last_closure_id() == closures  # the closures were not logged
    said = [r for r in caplog.records if "refuses writes" in r.getMessage()]
    assert len(said) == 1, [r.getMessage() for r in said]


def mapped(reg, n: int = 30):
    """A map that matches by the code itself (exact places) with a route of `n` places learned: the map,
    the route and its loop-closure log's last id."""
    rt = reg.create("flat", MapOptions(memory="none"))
    frames = route(n)
    for f in frames:
        step(rt, f)
    return rt, frames, rt.store.last_closure_id()


def test_a_store_refusing_a_localising_revisits_closure_makes_the_map_read_only_once(tmp_path, caplog):
    with registry(tmp_path) as reg:
        rt, frames, closures = mapped(reg)
        rt.store._db().execute("PRAGMA query_only = ON")  # SQLITE_READONLY from here, as an immutable file
        caplog.set_level("ERROR", logger="cortexloc.runtime")
        results = [step(rt, f, learn=False, stream="q") for f in frames[:15]]
        answers = [r.place for r in results]
        assert sum(p is not None and p.revisit for p in answers) >= 5  # answered, revisits and all
        assert (rt.state, rt.state_reason) == ("read-only", "storage-read-only")
        assert rt.store.last_closure_id() == closures
        assert all(r.loop_closure_id is None for r in results)  # no reply names an entry not logged
        assert len([r for r in caplog.records if "refuses writes" in r.getMessage()]) == 1


def test_a_full_disk_answers_a_localising_revisit_without_its_closure_and_logs_again_once_room_is_made(
        tmp_path, caplog, monkeypatch):
    """A localisation stores nothing but its revisits' closures: with no room to write, the robot still gets
    its answer (before: 507 exactly when it recognised its place), `loop_closure_id` null, said once; the
    map stays ready and logs closures again once there is room."""
    from storage.mapstore import StorageFull

    with registry(tmp_path) as reg:
        rt, frames, closures = mapped(reg)

        def full(closure):  # as the store raises it for SQLITE_FULL / ENOSPC (storage._common.is_full_error)
            raise StorageFull("database or disk is full")

        monkeypatch.setattr(rt.store, "add_closure", full)
        caplog.set_level("ERROR", logger="cortexloc.runtime")
        results = [step(rt, f, learn=False, stream="q") for f in frames[:15]]
        told = [r for r in results if r.place is not None and r.place.revisit]
        assert len(told) >= 5 and all(r.loop_closure_id is None for r in results)
        assert rt.store.last_closure_id() == closures and rt.state == "ready"
        assert len([r for r in caplog.records if "no room to log loop closures" in r.getMessage()]) == 1
        monkeypatch.undo()  # room made
        again = [step(rt, f, learn=False, stream="q2") for f in frames[:15]]
        ids = [r.loop_closure_id for r in again if r.place is not None and r.place.revisit]
        assert ids and all(i is not None for i in ids) and rt.store.last_closure_id() == ids[-1]
