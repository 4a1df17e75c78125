"""The one rebuild path without HTTP (service/maps/recovery/memory.py): a replay checks every row's
winner cells through the pipeline core, and recovery takes the newest snapshot whose replay reproduces
the rows, else replays from the first row (docs/design/service.md §4.4)."""

from __future__ import annotations

import dataclasses

from service.maps.recovery import rebuild, recover
from tests.service.helpers import tm_digest
from tests.service.maps.maps_fixtures import registry, route, step


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


def test_recovery_takes_the_newest_snapshot_that_reproduces_the_rows(tmp_path):
    with registry(tmp_path) as reg:
        rt = reg.get("default")
        frames = route(6)
        for f in frames[:2]:
            step(rt, f)
        older = rt.submit(rt.snapshot, "manual").result()
        for f in frames[2:4]:
            step(rt, f)
        newer = rt.submit(rt.snapshot, "manual").result()
        for f in frames[4:]:
            step(rt, f)
        done, note = rt.submit(lambda: recover(rt.store, reg.catalog, rt.map_id, rt.model)).result()
        assert note["source"] == "snapshot" and note["snapshot_id"] == newer.snapshot_id
        assert note["replayed"] == 2 and tm_digest(done.model.tm) == tm_digest(rt.tm)
        # a damaged newest snapshot is passed over for the older one
        memory = reg.catalog.layout.snapshot_dir(rt.map_id, newer.snapshot_id) / "memory.npz"
        memory.write_bytes(b"not an archive")
        done, note = rt.submit(lambda: recover(rt.store, reg.catalog, rt.map_id, rt.model)).result()
        assert note["snapshot_id"] == older.snapshot_id and note["replayed"] == 4
        assert [s["snapshot_id"] for s in note["skipped_snapshots"]] == [newer.snapshot_id]
        assert tm_digest(done.model.tm) == tm_digest(rt.tm)
