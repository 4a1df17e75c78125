"""A full disk costs a map one recovery, not one per learning post (service/maps/runtime/room.py,
writer.py; docs/design/service.md §4.3): after the first commit that finds no room, learning is refused
before its step (507, the memory untouched) while localising frames are answered, until a probe finds
room again; then the map learns with no restart. A file made immutable under the open store is said as
read-only from its first refused post."""

from __future__ import annotations

import pytest

from service.maps.config import MapOptions
from service.maps.errors import InsufficientStorage, MapReadOnly
from service.maps.recovery import verify_map
from service.maps.runtime.room import ROOM_RECHECK_SECONDS
from storage.mapstore import MapStore, StorageFull
from tests.service.helpers import tm_digest
from tests.service.maps.maps_fixtures import registry, route, step


def counting_recoveries(rt) -> list[int]:
    """The map's rebuilds from its store, counted (each replays the rows after its snapshot)."""
    done: list[int] = []
    real = rt.recover

    def recover(**kw):
        done.append(1)
        return real(**kw)

    rt.recover = recover
    return done


def full_disk(monkeypatch, room: list[bool]) -> None:
    """Every store of the map (the one a recovery reopens too) has no room for a row (SQLITE_FULL, as the
    store raises it), and its probe finds room only while `room[0]`."""

    def no_room(self, row, **kw):
        raise StorageFull("database or disk is full")

    monkeypatch.setattr(MapStore, "append", no_room)
    monkeypatch.setattr(MapStore, "has_room", lambda self, nbytes: room[0])


def test_a_full_disk_costs_one_recovery_localising_is_answered_and_learning_resumes_once_room_is_made(
        tmp_path, monkeypatch):
    now = [0.0]
    with registry(tmp_path) as reg:
        rt = reg.create("flat", MapOptions(memory="none"))  # matches by the code itself: exact places
        rt.room.clock = lambda: now[0]
        frames = route(12)
        for f in frames[:3]:
            step(rt, f)
        live, count = tm_digest(rt.tm), rt.store.count()
        recoveries = counting_recoveries(rt)
        room = [False]
        full_disk(monkeypatch, room)
        for f in frames[3:9]:
            with pytest.raises(InsufficientStorage, match="no room to write"):
                step(rt, f)
            # ready throughout: a localising frame is answered between the refused posts
            assert rt.state == "ready" and rt.no_room is not None
            assert step(rt, frames[1], learn=False, stream="q").matches[0].seq == 2
            now[0] += ROOM_RECHECK_SECONDS * 0.7  # probes fall due among the posts: they find no room
        assert recoveries == [1]  # the first refused commit's rebuild, no other
        assert rt.store.count() == len(rt.index) == count and tm_digest(rt.tm) == live
        monkeypatch.undo()  # room made (the real probe, on a disk with room); it waits for its turn
        now[0] += ROOM_RECHECK_SECONDS
        assert step(rt, frames[9]).seq == count + 1  # learns again, no restart, no rebuild
        assert step(rt, frames[10]).seq == count + 2
        assert recoveries == [1] and rt.no_room is None and rt.state == "ready"
        assert verify_map(reg.catalog, rt.record).mismatches == []


def test_a_full_disk_is_refused_before_the_step_without_a_probe_until_one_is_due(tmp_path, monkeypatch):
    now = [0.0]
    probes = []
    with registry(tmp_path) as reg:
        rt = reg.create("flat", MapOptions(memory="none"))
        rt.room.clock = lambda: now[0]
        frames = route(6)
        step(rt, frames[0])
        room = [False]
        full_disk(monkeypatch, room)
        monkeypatch.setattr(MapStore, "has_room", lambda self, nbytes: probes.append(nbytes) or room[0])
        with pytest.raises(InsufficientStorage):
            step(rt, frames[1])
        assert rt.room.refused() is not None  # an up-front answer, before the post's encoding
        for f in frames[2:5]:  # within the wait: no probe at all
            with pytest.raises(InsufficientStorage):
                step(rt, f)
        assert probes == []
        now[0] += ROOM_RECHECK_SECONDS
        assert rt.room.refused() is None  # a probe is due: the post goes on to it
        with pytest.raises(InsufficientStorage):
            step(rt, frames[5])
        assert len(probes) == 1


def test_a_probe_that_finds_room_the_commit_does_not_waits_longer_before_the_next(tmp_path, monkeypatch):
    """A probe file fits where map.sqlite does not (a file-size limit): each such trial costs a rebuild,
    so the trials grow rarer, never once per post."""
    now = [0.0]
    with registry(tmp_path) as reg:
        rt = reg.create("flat", MapOptions(memory="none"))
        rt.room.clock = lambda: now[0]
        frames = route(40)
        step(rt, frames[0])
        recoveries = counting_recoveries(rt)
        full_disk(monkeypatch, [True])  # the probe always finds room; the commit never does
        for f in frames[1:]:  # a post a second for 39 s
            with pytest.raises(InsufficientStorage):
                step(rt, f)
            now[0] += 1.0
        # trials after 5, then 10, then 20 s: 3 rebuilds besides the first, not 39
        assert len(recoveries) == 4


def test_a_file_made_immutable_under_the_open_store_is_read_only_from_its_first_refused_post(
        tmp_path, monkeypatch):
    """chattr +i on map.sqlite while the map is open: the open connection's write fails as a disk I/O
    error (SQLITE_IOERR_WRITE, no room in storage's words), and the reopen finds the file read-only. The
    first post is answered as the later ones are: read-only (503), not 507."""
    with registry(tmp_path) as reg:
        rt = reg.create("flat", MapOptions(memory="none"))
        frames = route(4)
        for f in frames[:2]:
            step(rt, f)
        count = rt.store.count()

        def io_error(self, row, **kw):
            raise StorageFull("disk I/O error")

        monkeypatch.setattr(MapStore, "append", io_error)
        monkeypatch.setattr(MapStore, "writable", property(lambda self: False))  # what the OS says now
        with pytest.raises(MapReadOnly):
            step(rt, frames[2])
        assert (rt.state, rt.state_reason) == ("read-only", "storage-read-only")
        with pytest.raises(MapReadOnly):  # refused up front, as before
            step(rt, frames[3])
        assert rt.store.count() == count and rt.no_room is None
        assert step(rt, frames[1], learn=False, stream="q").matches[0].seq == 2


def test_a_prune_that_finds_no_room_after_a_snapshot_leaves_the_committed_post_answered(tmp_path,
                                                                                      monkeypatch):
    # A review: the snapshot took the disk's last room, the visit log's prune after it failed, and the
    # post whose row was already committed was answered 507 "nothing was learned".
    from tests.service.helpers import frame, make_client, post

    def full(self, *a, **kw):
        raise StorageFull("database or disk is full")

    monkeypatch.setattr(MapStore, "prune_visits", full)
    with make_client(tmp_path / "data", snapshot_every=1) as c:
        r = post(c, frame(1), top_k=0)
        assert r.status_code == 200, r.text
        seq = r.json()["seq"]
        assert c.get(f"/v1/maps/default/observations/{seq}").status_code == 200
        assert c.get("/v1/maps/default").json()["state"] == "ready"
