"""MapRuntime without HTTP (service/maps/runtime/runtime.py): the order of learned rows, what a
localisation leaves, a full map, the rebuild after a failed commit, snapshot and restore, PATCH's
threshold (docs/design/service.md §1.2-§1.5, §4.3)."""

from __future__ import annotations

import pytest

from service.maps.config import MapOptions
from service.maps.errors import InsufficientStorage, InvalidConfiguration
from service.maps.recovery import verify_map
from storage.mapstore import StorageFull
from tests.service.helpers import tm_digest
from tests.service.maps.maps_fixtures import registry, route, step


def test_learned_frames_are_rows_in_order_and_a_localisation_stores_nothing(tmp_path):
    with registry(tmp_path) as reg:
        rt = reg.create("flat", MapOptions(memory="none"))  # matches by the code itself: exact places
        frames = route(4)
        assert [step(rt, f).seq for f in frames] == [1, 2, 3, 4]
        assert rt.store.count() == len(rt.index) == 4
        before = (rt.store.count(), tm_digest(rt.tm))
        found = step(rt, frames[2], learn=False, stream="q")
        assert found.seq is None and found.matches[0].seq == 3  # the same place, best
        assert (rt.store.count(), tm_digest(rt.tm)) == before


def test_a_full_map_forgets_the_least_recently_used_place_and_learns(tmp_path):
    # science.md §11.9: the hard cap binds -> the least recently used places go (whole), never map-full
    with registry(tmp_path, max_observations=3) as reg:
        rt = reg.create("flat", MapOptions(memory="none"))
        frames = route(4)
        for f in frames[:3]:
            step(rt, f)
        assert step(rt, frames[3]).seq == 4  # learned, no MapFull
        assert rt.store.count() == 4 and len(rt.index) <= 3 and rt.store.dropped() == {1: "forgotten"}
        places = rt.info().places
        assert places.forgotten == 1 and places.appearances == len(rt.index) and "least recently" in \
            places.forgetting
        # the forgotten row is no answer any more; the others still are
        assert all(m.seq != 1 for m in step(rt, frames[0], learn=False, stream="q").matches)
        assert step(rt, frames[2], learn=False, stream="q2").matches[0].seq == 3
    with registry(tmp_path, max_observations=3) as reg:  # durable: a restart forgets the same rows
        rt = reg.get("flat")
        assert rt.store.dropped() == {1: "forgotten"} and len(rt.index) == 3
        assert all(m.seq != 1 for m in step(rt, frames[0], learn=False, stream="q").matches)


def test_a_failed_commit_leaves_the_memory_the_store_can_replay(tmp_path, monkeypatch):
    with registry(tmp_path) as reg:
        rt = reg.get("default")
        frames = route(6)
        for f in frames[:3]:
            step(rt, f)
        live = tm_digest(rt.tm)

        def full(row, **kw):
            raise StorageFull("disk full")

        monkeypatch.setattr(rt.store, "append", full)
        with pytest.raises(InsufficientStorage):
            step(rt, frames[3])
        # rebuilt from the store: the step that learned is gone, index and links included
        assert rt.state == "ready" and rt.store.count() == len(rt.index) == 3 and tm_digest(rt.tm) == live
        rt.room.clock = lambda: float("inf")  # the probe for room is due (service.maps.runtime.room)
        for f in frames[3:]:
            step(rt, f)
        assert verify_map(reg.catalog, rt.record).mismatches == []


def test_restore_rolls_back_to_the_snapshot_and_keeps_the_present(tmp_path):
    with registry(tmp_path) as reg:
        rt = reg.get("default")
        frames = route(4)
        step(rt, frames[0])
        step(rt, frames[1])
        snap = rt.submit(rt.snapshot, "manual").result()
        at_snapshot = tm_digest(rt.tm)
        step(rt, frames[2])
        step(rt, frames[3])
        restored = rt.submit(rt.restore, snap.snapshot_id).result()
        assert restored.discarded_observations == 2 and rt.store.count() == 2
        assert tm_digest(rt.tm) == at_snapshot
        assert {s.kind for s in rt.snapshots()} == {"manual", "pre-restore"}


def test_the_revisit_threshold_changes_durably_and_only_within_0_1(tmp_path):
    with registry(tmp_path) as reg:
        rt = reg.get("default")
        assert rt.submit(rt.set_revisit_threshold, 0.5).result().revisit_threshold == 0.5
        with pytest.raises(InvalidConfiguration):
            rt.submit(rt.set_revisit_threshold, 1.5).result()
        assert rt.config.revisit_threshold == 0.5
    with registry(tmp_path) as reg:
        assert reg.get("default").config.revisit_threshold == 0.5


def test_the_writer_reads_no_stored_code_back_for_the_own_trail_of_a_drive(tmp_path, monkeypatch):
    """Issue 40, item 1: the own-trail rule asks for the code of a row the writer committed moments
    before; it is kept from the commit (`CODES_KEPT`) instead of read back from SQLite each frame, and
    the answers are those of a writer that reads it back."""
    def drive(reg, reads: list[int]) -> list:
        rt = reg.get("default")
        real = rt.store.code  # (a row's code, or a joined row's from its visit)

        def code(seq):
            reads.append(seq)
            return real(seq)

        monkeypatch.setattr(rt.store, "code", code)
        frames = route(6)
        out = [step(rt, f) for f in frames + frames]  # the route twice: the second lap revisits
        return [(r.seq, r.consolidated_into, [m.seq for m in r.matches], r.place) for r in out]

    reads: list[int] = []
    with registry(tmp_path / "a") as reg:
        kept = drive(reg, reads)
    assert reads == []
    with registry(tmp_path / "b") as reg:  # every code read back, as before
        monkeypatch.setattr("service.maps.runtime.writer.CODES_KEPT", 0)
        again: list[int] = []
        assert drive(reg, again) == kept and again
