"""Recovery that never strands a map, snapshots that survive a moved data directory, readiness that
sees a broken catalog or a failed snapshot, and a full disk during snapshots (issue 11: 1, 5, 6, 7)."""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import json
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from service.maps.runtime import MapRuntime
from tests.service.helpers import frame, make_client, post, state_of, tm_digest


def crash(c) -> None:
    """Leave the client as a kill -9 would, as far as the data directory can tell: no shutdown
    snapshot (the rows are committed; nothing else is written on the way out)."""
    for rt in c.app.state.registry.maps.values():
        if isinstance(rt, MapRuntime):  # a failed map takes no snapshot
            rt.settings = dataclasses.replace(rt.settings, snapshot_every=0)


def snapshot_dirs(data: Path, map_id: str = "default") -> list[Path]:
    """The map's snapshot directories, newest first (ids sort by creation time)."""
    return sorted((p for p in (data / "maps" / map_id / "snapshots").iterdir() if not p.name.startswith(".")),
                  reverse=True)


def rewrite_memory(snap: Path, change) -> None:
    """Change a snapshot's memory.npz and fix its manifest, so it verifies and still is wrong."""
    with np.load(snap / "memory.npz", allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    change(arrays)
    with (snap / "memory.npz").open("wb") as f:
        np.savez(f, allow_pickle=False, **arrays)
    manifest = json.loads((snap / "manifest.json").read_text())
    body = (snap / "memory.npz").read_bytes()
    manifest["files"]["memory.npz"] = {"bytes": len(body), "sha256": hashlib.sha256(body).hexdigest()}
    (snap / "manifest.json").write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")


def other_generator(arrays: dict) -> None:
    arrays["rng"] = arrays["rng"] + np.uint64(1)  # the tie-breaks of every later step differ


# ------------------------------------------------------------------------------------------ item 1


def test_a_snapshot_right_after_a_switch_back_to_mapping_recovers_the_stream(tmp_path):
    """The issue's sequence, scaled: learned frames elsewhere, then on `w` learn, localise, learn x4
    with the automatic snapshot landing on the first frame after the switch; then a crash."""
    data = tmp_path / "data"
    with make_client(data, snapshot_every=4) as c:
        post(c, frame(0), stream="a")
        post(c, frame(1), stream="b")
        assert post(c, frame(2), stream="w").json()["seq"] == 3
        post(c, frame(3), stream="w", learn="false")
        replies = [post(c, frame(p), stream="w").json() for p in (4, 5, 6, 7)]
        assert [r["seq"] for r in replies] == [4, 5, 6, 7]
        assert [s["seq"] for s in c.get("/v1/maps/default/snapshots").json()["snapshots"]] == [4]
        before = state_of(c)
        crash(c)
    with make_client(data, snapshot_every=4) as c:
        m = c.get("/v1/maps/default").json()
        assert m["state"] == "ready", m
        assert m["recovery"]["source"] == "snapshot" and m["recovery"]["snapshot_seq"] == 4
        assert m["recovery"]["skipped_snapshots"] == []
        assert state_of(c) == before
        nxt = post(c, frame(8), stream="w").json()
        assert nxt["sequence"]["step"] == replies[-1]["sequence"]["step"] + 1
        assert c.app.state.registry.get("default").store.get(nxt["seq"]).context_prev_seq == 7


def test_step_counts_continue_after_a_recovery_from_an_automatic_snapshot(tmp_path):
    data = tmp_path / "data"
    for round_ in range(3):  # the error grew by one per recovery
        with make_client(data, snapshot_every=3) as c:
            steps = [post(c, frame(10 * round_ + p), stream="a").json()["sequence"]["step"] for p in range(3)]
            assert steps == [3 * round_, 3 * round_ + 1, 3 * round_ + 2]
            crash(c)


def test_recovery_passes_over_bad_snapshots_to_an_older_one_then_to_a_full_replay(tmp_path):
    data = tmp_path / "data"
    with make_client(data, snapshot_every=2) as c:
        for p in (0, 1, 2, 3, 0, 1, 2):
            post(c, frame(p))
        before = state_of(c)
        probe = post(c, frame(2, noise=3.0), learn="false", stream="probe").json()["matches"]
        crash(c)
    newest, middle, oldest = snapshot_dirs(data)  # seqs 6, 4, 2
    raw = bytearray((newest / "memory.npz").read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (newest / "memory.npz").write_bytes(bytes(raw))  # fails its checksum
    rewrite_memory(middle, other_generator)  # verifies, but the replay after it diverges
    with make_client(data, snapshot_every=0) as c:
        m = c.get("/v1/maps/default").json()
        assert m["state"] == "ready", m
        rec = m["recovery"]
        assert rec["source"] == "snapshot" and rec["snapshot_id"] == oldest.name
        assert [s["snapshot_id"] for s in rec["skipped_snapshots"]] == [newest.name, middle.name]
        assert "checksum" in rec["skipped_snapshots"][0]["reason"]
        assert "diverged at seq 5" in rec["skipped_snapshots"][1]["reason"]
        ready = c.get("/readyz")
        assert ready.status_code == 200 and any("passing over 2 snapshot(s)" in w
                                                for w in ready.json()["warnings"])
        assert state_of(c) == before
        assert post(c, frame(2, noise=3.0), learn="false", stream="probe").json()["matches"] == probe
    rewrite_memory(oldest, other_generator)
    with make_client(data, snapshot_every=0) as c:
        rec = c.get("/v1/maps/default").json()["recovery"]
        assert rec["source"] == "replay" and rec["mismatches"] == 0 and len(rec["skipped_snapshots"]) == 3
        assert state_of(c) == before


def test_a_replay_that_does_not_reproduce_a_row_still_serves_and_says_which(tmp_path):
    data = tmp_path / "data"
    with make_client(data) as c:
        for p in range(5):
            post(c, frame(p))
        crash(c)
    corrupt_winner_cells(data / "maps" / "default" / "map.sqlite", seq=3)
    with make_client(data) as c:
        m = c.get("/v1/maps/default").json()
        assert m["state"] == "ready" and m["recovery"]["source"] == "replay"
        assert m["recovery"]["mismatches"] == 1 and m["recovery"]["mismatched_seqs"] == [3]
        assert "1 row(s) not reproduced" in " ".join(c.get("/readyz").json()["warnings"])
        assert post(c, frame(6)).status_code == 200


def corrupt_winner_cells(db: Path, seq: int) -> None:
    """Replace one row's stored winner cells by other valid cells, as bit rot or a bad edit would."""
    conn = sqlite3.connect(db, isolation_level=None)
    try:
        trigger = conn.execute("SELECT sql FROM sqlite_master WHERE name = 'observations_no_update'"
                               ).fetchone()[0]
        blob = conn.execute("SELECT winner_cells FROM observations WHERE seq = ?", (seq,)).fetchone()[0]
        changed = bytearray(blob)
        changed[0] ^= 0x01  # the first cell's index, off by one
        conn.execute("BEGIN")
        conn.execute("DROP TRIGGER observations_no_update")  # the store refuses edits: around it
        conn.execute("UPDATE observations SET winner_cells = ? WHERE seq = ?", (bytes(changed), seq))
        conn.execute(trigger)
        conn.execute("COMMIT")
    finally:
        conn.close()


# ------------------------------------------------------------------------------------------ item 5


def test_readyz_is_not_ready_when_the_catalog_is_garbage(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    (data / "catalog.sqlite").write_bytes(b"this is not a database\n" * 200)
    with make_client(data) as c:
        assert c.get("/v1/maps").status_code == 503
        r = c.get("/readyz")
        assert r.status_code == 503, r.text
        assert r.json()["checks"]["catalog"]["status"] == "fail"
        assert "not a database" in r.json()["checks"]["catalog"]["error"]
    with make_client(tmp_path / "fresh") as c:
        assert c.get("/readyz").json()["checks"]["catalog"]["status"] == "pass"


# ------------------------------------------------------------------------------------------ item 6


def disk_full(monkeypatch) -> None:
    """Every snapshot file write fails with ENOSPC (the snapshot writer's own path to the disk)."""
    from storage import snapshots

    def full(path, write):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(snapshots, "atomic_write", full)


def test_a_full_disk_during_an_automatic_snapshot_acknowledges_the_durable_row(tmp_path, monkeypatch):
    with make_client(tmp_path / "data", snapshot_every=2) as c:
        post(c, frame(0))
        disk_full(monkeypatch)
        r = post(c, frame(1))  # seq 2: committed and learned, then the snapshot fails
        assert r.status_code == 200, r.text
        assert r.json()["seq"] == 2
        rt = c.app.state.registry.get("default")
        assert rt.store.count() == 2 and len(rt.index) == 2
        ready = c.get("/readyz")
        assert ready.status_code == 200
        maps = ready.json()["checks"]["maps"]
        assert maps["status"] == "warn" and maps["maps"]["default"]["snapshot_error"]["seq"] == 2
        assert "automatic snapshot failed at seq 2" in maps["warning"]
        assert 'cortexloc_map_snapshot_failures{map="default"} 1.0' in c.get("/metrics").text
        manual = c.post("/v1/maps/default/snapshots")
        assert manual.status_code == 507 and manual.json()["type"].endswith("insufficient-storage")
        assert not [p for p in rt.layout.snapshots_dir(rt.map_id).iterdir()]  # nothing half-written is left
        monkeypatch.undo()
        post(c, frame(2))
        assert post(c, frame(3)).json()["seq"] == 4  # the next automatic snapshot succeeds...
        assert "snapshot_error" not in c.get("/readyz").json()["checks"]["maps"]["maps"]["default"]
        assert c.post("/v1/maps/default/snapshots").status_code == 201


# ------------------------------------------------------------------------------------------ item 7


def test_a_moved_data_directory_keeps_its_snapshots(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    with make_client(a, snapshot_every=2) as c:
        for p in range(5):
            post(c, frame(p))
        sid = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        before = state_of(c)
        crash(c)
    paths = [r[0] for r in sqlite3.connect(a / "catalog.sqlite").execute("SELECT path FROM snapshots")]
    assert paths and not [p for p in paths if p.startswith("/")]
    a.rename(b)
    with make_client(b, snapshot_every=0) as c:
        rec = c.get("/v1/maps/default").json()["recovery"]
        assert rec["source"] == "snapshot" and rec["snapshot_id"] == sid and rec["skipped_snapshots"] == []
        assert state_of(c) == before
        assert c.get(f"/v1/maps/default/snapshots/{sid}/download").status_code == 200
        assert c.post(f"/v1/maps/default/snapshots/{sid}/restore").status_code == 200


def test_a_copied_data_directory_never_reads_the_originals_snapshots(tmp_path):
    """Also for a catalog written by a version that stored absolute paths."""
    a, b = tmp_path / "a", tmp_path / "b"
    with make_client(a) as c:
        for p in range(4):
            post(c, frame(p))
        sid = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        crash(c)
    conn = sqlite3.connect(a / "catalog.sqlite")
    conn.execute("UPDATE snapshots SET path = ? WHERE snapshot_id = ?",
                 (str(a / "maps" / "default" / "snapshots" / sid), sid))
    conn.commit()
    conn.close()
    shutil.copytree(a, b)
    rewrite_memory(a / "maps" / "default" / "snapshots" / sid, other_generator)  # the original changes
    with make_client(b) as c:
        rec = c.get("/v1/maps/default").json()["recovery"]
        assert rec["source"] == "snapshot" and rec["skipped_snapshots"] == []
        tar = c.get(f"/v1/maps/default/snapshots/{sid}/download")
        assert tar.status_code == 200
        own = (b / "maps" / "default" / "snapshots" / sid / "memory.npz").read_bytes()
        assert own in tar.content  # this directory's file, not the original's
    paths = [r[0] for r in sqlite3.connect(b / "catalog.sqlite").execute("SELECT path FROM snapshots")]
    assert paths == [f"maps/default/snapshots/{sid}"]  # migrated to a relative path on open


def test_crashes_at_random_points_of_random_drives_come_back_as_if_nothing_happened(tmp_path):
    """Variants beyond the issue's sequence: three streams mapping, localising and resetting at random,
    an automatic snapshot every 3 rows, a crash after a random frame. The recovered map must continue
    as the uncrashed one does: same TM arrays, same step counts, same stored winner cells."""
    rng = np.random.default_rng(11)
    for trial in range(4):
        drive = [(str(rng.choice(["a", "b", "c"])), bool(rng.random() < 0.7), bool(rng.random() < 0.05),
                  int(rng.integers(0, 6))) for _ in range(24)]
        # The crash lands one or two frames after a frame whose row takes an automatic snapshot.
        learned = np.cumsum([learn for _, learn, _, _ in drive])
        at_snapshot = [i for i in range(4, 20) if drive[i][1] and learned[i] % 3 == 0]
        cut = int(rng.choice(at_snapshot)) + int(rng.integers(1, 3))

        def run(c, frames) -> list:
            out = []
            for stream, learn, reset, place in frames:
                if reset:
                    c.post(f"/v1/maps/default/streams/{stream}/reset")
                body = post(c, frame(place), stream=stream, learn=str(learn).lower(), top_k=0).json()
                out.append((body["seq"], body["sequence"]["step"] if learn else None))
            return out

        with make_client(tmp_path / f"twin{trial}", snapshot_every=3) as c:
            expected = run(c, drive)
            twin = state_of(c)
        data = tmp_path / f"crashed{trial}"
        with make_client(data, snapshot_every=3) as c:
            got = run(c, drive[:cut])
            crash(c)
        with make_client(data, snapshot_every=3) as c:
            m = c.get("/v1/maps/default").json()
            assert m["state"] == "ready" and m["recovery"]["skipped_snapshots"] == [], (trial, m)
            got += run(c, drive[cut:])
            assert state_of(c) == twin, (trial, cut, drive)
        # A localising stream comes back as of the last snapshot (its frames are not rows): only learned
        # steps compare.
        assert got == expected, (trial, cut, drive)


@pytest.mark.parametrize("snapshot_every", [0, 3], ids=["replayed", "restored-from-a-snapshot"])
def test_a_reset_answered_before_a_crash_holds_after_it(tmp_path, snapshot_every):
    """Found from outside: a stream reset answered 200, then a kill -9, and after the restart the stream
    went on with its old sequence (step 6, not 0): no row records a reset, and the stream's stored state
    was its last learned step's. Whether the stream's rows are replayed or its state comes from a
    snapshot taken with its last row, the restart resumes it reset, as a map never killed does."""
    def drive(c) -> None:
        for i in range(6):
            assert post(c, frame(i % 4), stream="F").status_code == 200
        assert c.post("/v1/maps/default/streams/F/reset").json()["had_context"] is True

    with make_client(tmp_path / "twin", snapshot_every=snapshot_every) as c:
        drive(c)
        expected = post(c, frame(5), stream="F").json()
        twin = state_of(c)
    data = tmp_path / "crashed"
    with make_client(data, snapshot_every=snapshot_every) as c:
        drive(c)
        crash(c)
    with make_client(data, snapshot_every=snapshot_every) as c:
        got = post(c, frame(5), stream="F").json()
        assert got["sequence"]["step"] == 0 == expected["sequence"]["step"]
        assert got["place"] == expected["place"] and got["seq"] == expected["seq"]
        assert state_of(c) == twin


def test_a_reset_that_cannot_be_stored_is_refused_and_changes_nothing(tmp_path, monkeypatch):
    from storage.mapstore import StorageFull

    with make_client(tmp_path / "data", snapshot_every=0) as c:
        for i in range(3):
            assert post(c, frame(i), stream="F").status_code == 200
        rt = c.app.state.registry.get("default")

        def full(*args, **kwargs):
            raise StorageFull("database or disk is full")

        monkeypatch.setattr(rt.store, "save_stream_state", full)
        r = c.post("/v1/maps/default/streams/F/reset")
        assert r.status_code == 507 and r.json()["type"].endswith("insufficient-storage"), r.text
        # a localising robot (the ROS node resets its stream as it starts) still resets on a full disk:
        # its frames are no rows, so its reset needs no write
        for i in range(2):
            assert post(c, frame(i), stream="L", learn="false").status_code == 200
        assert c.post("/v1/maps/default/streams/L/reset").json()["had_context"] is True
        monkeypatch.undo()
        assert post(c, frame(3), stream="F").json()["sequence"]["step"] == 3  # not reset


# ------------------------------------------------------------------ a failure between the step and the commit


def test_a_failure_between_the_tm_step_and_the_commit_leaves_no_row_replay_cannot_reproduce(tmp_path,
                                                                                             monkeypatch):
    """The TM learns in the step, before the commit; anything failing in between (here the localiser)
    must not leave a learned step the store does not hold, or every later row would be stored with winner
    cells that no replay reproduces (found by review: 6 mismatches after 6 more frames)."""
    with make_client(tmp_path / "data", snapshot_every=0) as c:
        for i in range(3):
            assert post(c, frame(i)).status_code == 200
        rt = c.app.state.registry.get("default")
        real, calls = rt.place_map.step, []

        def fails_once(*args, **kwargs):
            calls.append(1)
            if len(calls) == 1:
                raise RuntimeError("injected after the TM step")
            return real(*args, **kwargs)

        monkeypatch.setattr(rt.place_map, "step", fails_once)
        r = post(c, frame(3))
        assert r.status_code == 500 and rt.store.count() == 3  # nothing stored, and the map still serves
        monkeypatch.undo()  # the rebuilt map has new links; the old ones get their step back
        for i in range(4, 10):
            assert post(c, frame(i)).status_code == 200
        live = tm_digest(rt.tm)
    with make_client(tmp_path / "data", snapshot_every=0) as c:  # no snapshot: replay from the first row
        rt = c.app.state.registry.get("default")
        assert rt.recovery["source"] == "replay" and rt.recovery["mismatches"] == 0
        assert tm_digest(rt.tm) == live


def test_a_read_that_meets_a_closed_store_is_a_503_to_retry(tmp_path):
    """Found by review: a read in a request thread while a restore has the store closed was a 500."""
    with make_client(tmp_path / "data", snapshot_every=0) as c:
        assert post(c, frame(0)).status_code == 200
        rt = c.app.state.registry.get("default")
        rt.store.close()  # what a restore does between closing the old store and opening the snapshot's
        r = c.get("/v1/maps/default/observations/1")
        assert r.status_code == 503 and r.json()["type"].endswith("map-unavailable")
        assert r.headers["retry-after"] == "1"


# ------------------------------------------------------------ the row cap lowered (outside tester, probe_ops)


def learn(c, places) -> None:
    for p in places:
        assert post(c, frame(p), stream="a").status_code == 200


def test_a_restore_of_a_snapshot_over_the_row_cap_is_refused_before_anything_changes(tmp_path):
    """Found by an outside tester: it answered 500 after the store was replaced, the map left `ready`
    with an empty index (matching nothing) and learning on top of it."""
    data = tmp_path / "data"
    with make_client(data, snapshot_every=0) as c:
        learn(c, range(10))
        s10 = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        learn(c, range(10, 30))
        s30 = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        assert c.post(f"/v1/maps/default/snapshots/{s10}/restore").status_code == 200
    with make_client(data, snapshot_every=0, max_observations=20) as c:  # the cap lowered since
        before, listing = state_of(c), c.get("/v1/maps/default/snapshots").json()
        r = c.post(f"/v1/maps/default/snapshots/{s30}/restore")
        assert r.status_code == 409 and r.json()["type"].endswith(":map-full"), r.text
        assert (r.json()["rows_held"], r.json()["max_observations"]) == (30, 20)
        assert "CORTEXLOC_MAX_OBSERVATIONS" in r.json()["detail"] and "nothing changed" in r.json()["detail"]
        assert state_of(c) == before and c.get("/v1/maps/default/snapshots").json() == listing
        m = c.get("/v1/maps/default").json()
        assert (m["state"], m["observations"]) == ("ready", 10)


def test_a_failure_while_installing_a_recovered_map_leaves_it_failed_not_ready(tmp_path, monkeypatch):
    """The second line of defence: whatever fails once the recovered memory is being swapped in, the
    map is never `ready` on a half-installed memory."""
    with make_client(tmp_path / "data", snapshot_every=0) as c:
        learn(c, range(3))
        sid = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        learn(c, range(3, 5))
        rt = c.app.state.registry.get("default")

        def broken() -> None:
            raise RuntimeError("index rebuild failed")

        monkeypatch.setattr(rt, "_rebuild_index", broken)
        with pytest.raises(RuntimeError, match="index rebuild failed"):
            rt.submit(rt.restore, sid).result()
        assert (rt.state, rt.state_reason) == ("failed", "install-failed")
        m = c.get("/v1/maps/default").json()
        assert (m["state"], m["state_reason"]) == ("failed", "install-failed")
        assert post(c, frame(9), stream="a").status_code == 503
        # a keyed post too: refused with the map's state, even where the failed reopen left the old store
        # closed (before: 503 "store is closed" with Retry-After, to be retried for ever)
        rt.store.close()
        keyed = c.post("/v1/maps/default/observations", content=frame(9), params={"stream": "a"},
                       headers={"Content-Type": "image/png", "Idempotency-Key": "key-after-a-failed-install"})
        assert keyed.status_code == 503 and keyed.json()["type"].endswith("map-unavailable"), keyed.text
        assert "failed" in keyed.json()["detail"] and "closed" not in keyed.json()["detail"], keyed.text


def test_a_map_over_a_lowered_row_cap_fails_at_start_saying_which_setting_and_what_to_do(tmp_path, caplog):
    """Found by an outside tester: the map came up `failed` (`open-failed`) with only a traceback in the
    log. Its reason now names the setting, the rows held, the cap and the remedy; nothing is forgotten."""
    data = tmp_path / "data"
    with make_client(data, snapshot_every=0) as c:
        learn(c, range(30))
    caplog.clear()
    with make_client(data, snapshot_every=0, max_observations=20) as c:
        m = c.get("/v1/maps/default").json()
        assert m["state"] == "failed"
        reason = m["state_reason"]
        assert all(s in reason for s in ("CORTEXLOC_MAX_OBSERVATIONS=20", "holds 30 rows", "at least 30"))
        assert c.get("/readyz").json()["checks"]["maps"]["maps"]["default"]["state_reason"] == reason
        assert post(c, frame(0), stream="a").status_code == 503
        # every other call is 503 too (§4.4): a PATCH was stored and read by the map once repaired, its
        # memory shown empty and a stream reset answered (an outside probe)
        for r in (c.patch("/v1/maps/default", json={"revisit_threshold": 0.5}),
                  c.get("/v1/maps/default/memory"), c.post("/v1/maps/default/streams/a/reset")):
            assert r.status_code == 503 and r.json()["type"].endswith("map-unavailable"), r.text
    said = [r for r in caplog.records if r.levelname == "ERROR" and "default" in r.getMessage()]
    assert len(said) == 1 and reason in said[0].getMessage() and said[0].exc_info is None
    with make_client(data, snapshot_every=0) as c:  # the setting raised back: every row is there
        m = c.get("/v1/maps/default").json()
        assert (m["state"], m["observations"]) == ("ready", 30)
        assert m["revisit_threshold"] != 0.5
