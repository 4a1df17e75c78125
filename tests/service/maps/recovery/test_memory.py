"""The one rebuild path without HTTP (service/maps/recovery/memory.py): a replay checks every row's
winner cells through the pipeline core, and recovery takes the newest snapshot whose replay reproduces
the rows, else replays from the first row (docs/design/service.md §4.4)."""

from __future__ import annotations

import dataclasses
import logging
import re
import zipfile
from pathlib import Path

import pytest

from models.pipeline import memory_state
from service.maps.errors import SnapshotInvalid
from service.maps.recovery import check_memory, rebuild, recover, verify_map
from service.maps.recovery.memory import snapshot_array
from storage import snapshots
from tests.service.helpers import tm_digest
from tests.service.maps.maps_fixtures import registry, route, step
from tests.storage.test_snapshots import npy_header, planted


def recovered(reg, rt):
    """`recover` of the map on its writer."""
    return rt.submit(lambda: recover(rt.store, reg.catalog, rt.map_id, rt.model)).result()


def plant(directory: Path, member: str, data: bytes, compress: int) -> None:
    """The snapshot at `directory` crafted (`planted`): every checksum still verifies."""
    files = (directory / "manifest.json", directory / "memory.npz")
    for path, body in zip(files, planted(*(p.read_bytes() for p in files), member, data, compress),
                          strict=True):
        path.write_bytes(body)
    snapshots.verify(directory)


def test_a_replay_reproduces_every_row_and_names_one_that_differs(tmp_path):
    with registry(tmp_path) as reg:
        rt = reg.get("default")
        for f in route(6):
            step(rt, f)
        rows = list(rt.store.rows())
        fresh = rt.model.fresh(type(rt.tm)(rt.tm.options))
        done = rebuild(fresh.tm, rows, rt.model, stop_at_mismatch=False)
        assert done.mismatches == [] and done.replayed == 6 and tm_digest(done.model.tm) == tm_digest(rt.tm)
        assert done.streams["s"].last_learned_seq == 6 and done.streams["s"].step == 6
        bad = [*rows[:3], dataclasses.replace(rows[3], winner_cells=rows[3].winner_cells[:-1]), *rows[4:]]
        again = rebuild(type(rt.tm)(rt.tm.options), bad, rt.model, stop_at_mismatch=False)
        assert again.mismatches == [4]


def two_snapshots(rt):
    """Six rows learned, a manual snapshot after the second and after the fourth: (older, newer)."""
    frames = route(6)
    taken = []
    for part in (frames[:2], frames[2:4]):
        for f in part:
            step(rt, f)
        taken.append(rt.submit(rt.snapshot, "manual").result())
    for f in frames[4:]:
        step(rt, f)
    return taken


def test_recovery_takes_the_newest_snapshot_that_reproduces_the_rows(tmp_path):
    with registry(tmp_path) as reg:
        rt = reg.get("default")
        older, newer = two_snapshots(rt)
        done, note = recovered(reg, rt)
        assert note["source"] == "snapshot" and note["snapshot_id"] == newer.snapshot_id
        assert note["replayed"] == 2 and tm_digest(done.model.tm) == tm_digest(rt.tm)
        # a damaged newest snapshot is passed over for the older one
        memory = reg.catalog.layout.snapshot_dir(rt.map_id, newer.snapshot_id) / "memory.npz"
        memory.write_bytes(b"not an archive")
        done, note = recovered(reg, rt)
        assert note["snapshot_id"] == older.snapshot_id and note["replayed"] == 4
        assert [s["snapshot_id"] for s in note["skipped_snapshots"]] == [newer.snapshot_id]
        assert tm_digest(done.model.tm) == tm_digest(rt.tm)


#: Crafted members of a memory.npz, and why each is refused.
CRAFTED = pytest.mark.parametrize(("member", "data", "compress", "why"), [
    # a name the memory's writer writes, its header declaring 8 GiB with nothing behind it
    ("streamcond.00.npy", npy_header((2**33,)), zipfile.ZIP_STORED,
     "'streamcond.00.npy' declares uint8(8589934592,), more"),
    # the tester's bomb: a known name, deflated zeros (np.savez stores every member)
    ("streamcond.00.npy", npy_header((2**24,)) + bytes(2**24), zipfile.ZIP_DEFLATED,
     "'streamcond.00.npy' is compressed"),
    ("extra.npy", npy_header((4,)) + bytes(4), zipfile.ZIP_STORED,
     "'extra.npy' is no array of a map's memory"),
], ids=["declared-8GiB", "deflated", "unknown"])


@CRAFTED
def test_a_snapshot_whose_memory_is_refused_is_passed_over_like_a_damaged_one(tmp_path, caplog, member,
                                                                              data, compress, why):
    """A snapshot whose checksums verify but whose memory.npz holds a member declaring more than it holds
    or of a name no memory writes: recovery passes over it for the older one and logs
    why; `cortexloc verify` lists it as bad; a restore to it is refused before anything changes
    (docs/design/service.md §4.4)."""
    with registry(tmp_path) as reg:
        rt = reg.get("default")
        older, newer = two_snapshots(rt)
        plant(rt.snapshot_dir(newer.snapshot_id), member, data, compress)
        with caplog.at_level(logging.WARNING, logger="cortexloc.recovery"):
            done, note = recovered(reg, rt)
        assert note["snapshot_id"] == older.snapshot_id and tm_digest(done.model.tm) == tm_digest(rt.tm)
        [skipped] = note["skipped_snapshots"]
        assert skipped["snapshot_id"] == newer.snapshot_id and why in skipped["reason"]
        assert any(f"snapshot {newer.snapshot_id} passed over" in r.getMessage() and why in r.getMessage()
                   for r in caplog.records)
        check = verify_map(reg.catalog, rt.record)
        assert list(check.snapshots_bad) == [newer.snapshot_id]
        assert why in check.snapshots_bad[newer.snapshot_id]
        before = (rt.store.count(), tm_digest(rt.tm), [s.snapshot_id for s in rt.snapshots()])
        with pytest.raises(SnapshotInvalid, match=re.escape(why)):
            rt.submit(rt.restore, newer.snapshot_id).result()
        assert (rt.store.count(), tm_digest(rt.tm), [s.snapshot_id for s in rt.snapshots()]) == before


def test_every_array_a_map_snapshots_is_one_its_loader_knows(tmp_path):
    """The names the memory's writer writes (`memory_state`, the visit cursor and mark) against the
    loader's rule (`snapshot_array`), on a map with learning and localising streams; a normal snapshot
    passes its checks."""
    with registry(tmp_path) as reg:
        rt = reg.get("default")
        for f in route(4):
            step(rt, f)
        step(rt, route(1, seed=9)[0], learn=False, stream="a.b/localising")
        snap = rt.submit(rt.snapshot, "manual").result()
        names = set(rt.submit(lambda: memory_state(rt.tm, rt.streams)).result())
        assert {n.split(".")[0] for n in names} >= {"stream", "streammeta", "streamloc", "ctx", "presyn"}
        assert all(snapshot_array(n) for n in names)
        check_memory(rt.snapshot_dir(snap.snapshot_id))
        for bad in ("stream.6162.bomb", "streammeta.zz", "streamloc.6162.rows.x", "ctx", "streammeta.61.x"):
            assert not snapshot_array(bad)
