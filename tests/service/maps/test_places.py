"""Places over many passes (docs/design/science.md §11.8, §11.9; docs/design/service.md §4.4): a known
pass is consolidated into visits, other passes of a place are no rivals, a place keeps at most its cap,
and visits come back after a crash, a snapshot and a restore exactly as rows do."""

from __future__ import annotations

import json
import shutil

from service.maps.recovery import VISIT_CURSOR, open_catalog, verify_map
from service.maps.recovery.memory import load_memory
from tests.service.helpers import frame, make_client, post, state_of
from tests.service.maps.recovery.test_recovery import crash
from tests.service.maps.test_loop_closures import LAP, THRESHOLD, drive, revisits


def make(c, map_id: str, **localiser) -> None:
    body = {"map_id": map_id, "revisit_threshold": THRESHOLD, "localiser": localiser}
    assert c.post("/v1/maps", json=body).status_code == 201


def places(c, map_id: str) -> dict:
    return c.get(f"/v1/maps/{map_id}").json()["places"]


def test_a_known_pass_is_consolidated_and_names_the_first_pass_places(tmp_path):
    with make_client(tmp_path / "data") as c:
        make(c, "m")
        lap1 = drive(c, LAP, stream="a", noise=0.0, map_id="m")
        lap2 = drive(c, LAP, stream="b", map_id="m")
        info = places(c, "m")
        joins = c.app.state.registry.get("m").store.joins()
    first = {p: b["seq"] for p, b in zip(LAP, lap1, strict=True)}
    made = [b for b in lap2 if b["seq"] is not None]
    kept = [b for b in lap2 if b["consolidated_into"] is not None]
    assert len(made) <= 0.35 * len(LAP) and len(made) + len(kept) == len(LAP)
    exact = 0
    for p, b in zip(LAP, lap2, strict=True):
        if b["consolidated_into"] is not None:  # the memory learned it; no row; a place of lap 1
            assert b["learned"] and b["observation_id"] is None
            assert b["consolidated_into"] in first.values() and b["place"]["place_id"] in first.values()
            exact += b["consolidated_into"] == b["place"]["place_id"] == first[p]
    # the tiny test encoder's 32-bit codes alias now and then; the rest is the place driven
    assert exact >= 0.9 * len(kept)
    # lap 2's rows made before it knew where it was are joined to lap 1's places, held no more (§11.8)
    assert {row for row, _ in joins} <= {b["seq"] for b in made}
    # ... and turned into visits, gone from map.sqlite (schema 12)
    assert info["appearances"] == info["rows_stored"] == len(LAP) + len(made) - len(joins)
    assert info["visits_logged"] == len(kept) + len(joins) and info["dropped"] == len(joins)
    assert info["places"] <= len(LAP) + len(made) and "least recently" in info["forgetting"]


def test_other_passes_of_a_place_are_no_rivals(tmp_path):
    # every frame a row (consolidate 1): three passes of one place; the localiser still calls revisits
    with make_client(tmp_path / "data") as c:
        for m, n in (("one", 1), ("three", 3)):
            make(c, m, consolidate=1.0)
            passes = [drive(c, LAP, stream=f"p{k}", noise=0.0 if k == 0 else 3.0, map_id=m) for k in range(n)]
            found = drive(c, LAP, stream="q", learn="false", noise=4.0, map_id=m)
            if m == "one":
                once = revisits(found)
                continue
            pass1 = {p: b["seq"] for p, b in zip(LAP, passes[0], strict=True)}
            thrice = revisits(found)
            assert len(thrice) >= 0.9 * len(once) > 0
            for p, b in zip(LAP, found, strict=True):
                if b in thrice:
                    assert b["place"]["place_id"] == pass1[p]  # whichever pass's row matched best
            assert places(c, m)["appearances"] == 3 * len(LAP)


def test_a_place_keeps_its_cap_and_drops_its_least_recently_used_rows(tmp_path):
    with make_client(tmp_path / "data") as c:
        make(c, "m", consolidate=1.0, appearances=2)
        passes = [drive(c, LAP, stream=f"p{k}", noise=0.0 if k == 0 else 3.0, map_id="m") for k in range(4)]
        rt = c.app.state.registry.get("m")
        info = places(c, "m")
        dropped = rt.store.dropped()
        for place in {rt.place_map.place_of(b["seq"]) for b in passes[0]}:
            assert len(rt.place_map.appearances(place)) <= 2
        last = {b["seq"] for b in passes[-1]}
        assert dropped and set(dropped.values()) == {"appearance-cap"} and not last & set(dropped)
        assert info["dropped"] == len(dropped) and info["appearances"] == info["rows_stored"] - len(dropped)
        assert all(m["seq"] not in dropped for m in post(c, frame(LAP[5]), map_id="m", learn="false",
                                                          stream="q", top_k=20).json()["matches"])


def answers(bodies: list[dict]) -> list[tuple]:
    return [(b["seq"], b["consolidated_into"], b["sequence"]["step"],
             None if b["place"] is None else (b["place"]["place_id"], b["place"]["seq"])) for b in bodies]


def shape(c) -> tuple:
    rt = c.app.state.registry.get("default")
    info = places(c, "default")
    return (*state_of(c), info["places"], info["appearances"], info["visits_logged"],
            rt.place_map.graph.place.tolist(), rt.place_map.graph.next.tolist())


def twin_and_crashed(tmp_path, drive_: list[tuple], crash_at: int) -> tuple[list, list, tuple, dict]:
    """`drive_` ((stream, places, noise) parts) on a map that never crashed and on one that crashed as a
    kill -9 leaves it after the first `crash_at` parts. Returns (the twin's replies, the crashed one's,
    whether its final `shape` is the twin's, its recovery note)."""
    def run(c, part) -> list:
        return [b for stream, places_, noise in part for b in drive(c, places_, stream=stream, noise=noise)]

    with make_client(tmp_path / "twin", snapshot_every=7) as c:
        c.patch("/v1/maps/default", json={"revisit_threshold": THRESHOLD})
        expected = run(c, drive_)
        twin = shape(c)
    data = tmp_path / "crashed"
    with make_client(data, snapshot_every=7) as c:
        c.patch("/v1/maps/default", json={"revisit_threshold": THRESHOLD})
        got = run(c, drive_[:crash_at])
        crash(c)  # what the steps after the last snapshot did: only the store has it
    with make_client(data, snapshot_every=7) as c:
        note = c.get("/v1/maps/default").json()["recovery"]
        got += run(c, drive_[crash_at:])
        same = shape(c) == twin
    return expected, got, same, note


def test_a_crash_after_acknowledged_visits_comes_back_as_if_nothing_happened(tmp_path):
    expected, got, same, note = twin_and_crashed(
        tmp_path, [("a", LAP, 0.0), ("b", LAP, 3.0), ("c", LAP[:20], 2.0)], 2)
    assert any(b["consolidated_into"] for b in got[:2 * len(LAP)])  # visits before the crash
    assert note["source"] == "snapshot" and note["visits_replayed"] > 0
    assert same and answers(got) == answers(expected)


def test_a_snapshot_and_a_restore_carry_the_visits_and_a_repeated_post_is_one_visit(tmp_path):
    with make_client(tmp_path / "data") as c:
        c.patch("/v1/maps/default", json={"revisit_threshold": THRESHOLD})
        drive(c, LAP, stream="a", noise=0.0)
        drive(c, LAP[:15], stream="b")
        at_snapshot = shape(c)
        snap = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        later = drive(c, LAP[15:], stream="b")
        assert shape(c) != at_snapshot and any(b["consolidated_into"] for b in later)
        assert c.post(f"/v1/maps/default/snapshots/{snap}/restore").status_code == 200
        assert shape(c)[:-2] == at_snapshot[:-2]  # the TM, rows, places and visits as they were
        # an idempotent consolidated post: the retry is answered from the visit, nothing twice
        drive(c, LAP[15:25], stream="b")
        headers = {"Content-Type": "image/png", "Idempotency-Key": "visit-key-0001"}
        body = frame(LAP[25], noise=3.0)
        first = c.post("/v1/maps/default/observations", content=body, headers=headers,
                       params={"stream": "b", "learn": "true", "top_k": 0})
        assert first.json()["consolidated_into"] is not None
        n = places(c, "default")["visits_logged"]
        again = c.post("/v1/maps/default/observations", content=body, headers=headers,
                       params={"stream": "b", "learn": "true", "top_k": 0})
        assert again.json() == first.json() and places(c, "default")["visits_logged"] == n
    with make_client(tmp_path / "data") as c:  # and after a restart
        again = c.post("/v1/maps/default/observations", content=body, headers=headers,
                       params={"stream": "b", "learn": "true", "top_k": 0})
        assert again.json() == first.json() and places(c, "default")["visits_logged"] == n


def test_consolidated_frames_hold_no_index_bytes_of_the_memory_budget(tmp_path):
    with make_client(tmp_path / "data") as c:
        c.patch("/v1/maps/default", json={"revisit_threshold": THRESHOLD})
        drive(c, LAP, stream="a", noise=0.0)
        lap2 = drive(c, LAP, stream="b")
        rt = c.app.state.registry.get("default")
        held = next(m for m in c.get("/v1/memory").json()["maps"] if m["map_id"] == "default")
    assert any(b["consolidated_into"] for b in lap2)
    assert held["parts"]["index"] == len(rt.index) * rt.row_bytes  # a reservation per row made, not per frame


def _pruned_map(data) -> tuple:
    """A map whose visit log was pruned (`visits=1`: all but the newest, once a snapshot covers them),
    closed as a kill -9 leaves it. Returns (its state, the last visit id pruned, its snapshots folder)."""
    with make_client(data, snapshot_every=5, visits=1) as c:
        c.patch("/v1/maps/default", json={"revisit_threshold": THRESHOLD})
        drive(c, LAP, stream="a", noise=0.0)
        assert any(b["consolidated_into"] for b in drive(c, LAP, stream="b"))
        rt = c.app.state.registry.get("default")
        pruned = rt.store.visits_pruned_through()
        assert pruned > 0 and rt.store.visit_stats()[0] == 1
        crash(c)
        return state_of(c), pruned, c.app.state.registry.layout.snapshots_dir("default")


def test_with_every_snapshot_gone_a_pruned_visit_log_is_no_complete_replay(tmp_path):
    """Pruned visits taught the memory; the replay from the first row cannot repeat them (their rows'
    winner cells still match, so a mismatch count of 0 proves nothing). Recovery serves every row and
    says the memory is incomplete, in the note and in /readyz (docs/design/service.md §4.4)."""
    before, pruned, snaps = _pruned_map(tmp_path / "d")
    for d in snaps.iterdir():  # every snapshot unusable (a damaged disk, deleted by hand, ...)
        shutil.rmtree(d)
    with make_client(tmp_path / "d", snapshot_every=5, visits=1) as c:
        note = c.get("/v1/maps/default").json()["recovery"]
        assert note["source"] == "replay" and note["complete"] is False
        assert note["visits_pruned_through"] == pruned
        after = state_of(c)
        assert after[:2] == before[:2] and after[3] == before[3]  # every acknowledged row is served
        ready = c.get("/readyz").json()
        assert "recovery" in json.dumps(ready)


def test_recovery_starts_at_a_snapshot_that_covers_the_pruned_visits(tmp_path):
    before, _, _ = _pruned_map(tmp_path / "d")
    with make_client(tmp_path / "d", snapshot_every=5, visits=1) as c:
        note = c.get("/v1/maps/default").json()["recovery"]
        assert note["source"] == "snapshot" and "complete" not in note
        assert state_of(c) == before


def test_verify_starts_at_the_earliest_snapshot_that_covers_the_pruned_visits(tmp_path):
    """`cortexloc verify` on a healthy map whose visit log was pruned: a replay from the first row would
    miss those visits and flag rows after them; the check starts at the earliest usable snapshot that
    covers them and says so, and with none left it reports that the memory cannot be replayed."""
    _, pruned, snaps = _pruned_map(tmp_path / "d")
    catalog = open_catalog(tmp_path / "d")
    try:
        record = catalog.get_map("default")
        covering = [r.snapshot_id for r in reversed(catalog.list_snapshots("default"))
                    if int(load_memory(catalog.snapshot_dir(r))[VISIT_CURSOR]) >= pruned]
        check = verify_map(catalog, record)
        assert check.ok and check.mismatches == [] and check.start == covering[0]
        for d in snaps.iterdir():
            shutil.rmtree(d)
        check = verify_map(catalog, record)
        assert not check.ok and check.start is None and any("pruned" in p for p in check.problems)
    finally:
        catalog.close()


def test_after_a_crash_the_cap_drops_the_rows_the_map_that_did_not_crash_drops(tmp_path):
    """Per-row recency (what the appearance cap and forgetting read, docs/design/science.md §11.9) is the
    live map's after a recovery: a step that joins or consolidates into a place uses the answer's row,
    which neither the rows nor the visits say; the store's `recency` does. Without it the recovered map
    drops other appearances than the one that never crashed."""
    parts = [("p0", LAP, 0.0), ("p1", LAP, 3.0), ("p2", LAP, 2.0), ("p3", LAP, 4.0)]

    def run(c, part) -> None:
        for stream, places_, noise in part:
            drive(c, places_, stream=stream, noise=noise, map_id="m")

    def state(c) -> tuple:
        rt = c.app.state.registry.get("m")
        return sorted(rt.store.dropped().items()), rt.place_map.used[:len(rt.place_map.graph)].tolist()

    with make_client(tmp_path / "twin", snapshot_every=7) as c:
        make(c, "m", consolidate=1.0, appearances=2)
        run(c, parts[:2])
        run(c, parts[2:])
        twin = state(c)
    with make_client(tmp_path / "crashed", snapshot_every=7) as c:
        make(c, "m", consolidate=1.0, appearances=2)
        run(c, parts[:2])
        live = state(c)
        crash(c)
    with make_client(tmp_path / "crashed", snapshot_every=7) as c:
        assert state(c) == live
        run(c, parts[2:])
        assert state(c) == twin and twin[0]


def test_retry_keys_of_consolidated_posts_outlive_the_pruned_visit_log(tmp_path):
    """Issue 34 item 6: a consolidated post's Idempotency-Key replays for the keys' window
    (CORTEXLOC_IDEMPOTENCY_KEYS), not only while its visit is logged (`visits=1` prunes all but one)."""
    def keyed(c, p: int, i: int):
        headers = {"Content-Type": "image/png", "Idempotency-Key": f"lap-b-key-{i:04d}"}
        return c.post("/v1/maps/default/observations", content=frame(p, noise=3.0), headers=headers,
                      params={"stream": "b", "learn": "true", "top_k": 0})

    data = tmp_path / "data"
    with make_client(data, snapshot_every=5, visits=1) as c:
        c.patch("/v1/maps/default", json={"revisit_threshold": THRESHOLD})
        drive(c, LAP, stream="a", noise=0.0)
        first = {i: keyed(c, p, i).json() for i, p in enumerate(LAP)}
        kept = [i for i, b in first.items() if b["consolidated_into"] is not None]
        rt = c.app.state.registry.get("default")
        assert len(kept) > 5 and rt.store.visits_pruned_through() > 0  # their visits were pruned
        before = state_of(c), places(c, "default")["visits_logged"]
        for i in kept:
            assert keyed(c, LAP[i], i).json() == first[i]
        assert (state_of(c), places(c, "default")["visits_logged"]) == before  # nothing learned again
    with make_client(data, snapshot_every=5, visits=1) as c:  # and after a restart
        assert all(keyed(c, LAP[i], i).json() == first[i] for i in kept)
        assert state_of(c) == before[0]


def test_a_learning_stream_resumes_its_place_after_a_crash_mid_pass(tmp_path):
    """Issue 34 item 7: kill -9 in the middle of a known pass. The stream's localiser state is not in its
    rows; it is kept with each learned step, so the stream carries on where it was, as after SIGTERM,
    instead of warming up again and making rows its uncrashed twin consolidates."""
    expected, got, same, note = twin_and_crashed(
        tmp_path, [("a", LAP, 0.0), ("b", LAP[:17], 3.0), ("b", LAP[17:], 3.0)], 2)
    assert note["source"] == "snapshot" and note["resumed_streams"] == 1
    made = sum(b["seq"] is not None for b in got) - sum(b["seq"] is not None for b in expected)
    assert made == 0  # no duplicate rows against the twin (5 before issue 34)
    assert same and answers(got) == answers(expected)


def test_the_consolidation_gate_and_the_forgetting_batch_are_options_of_the_map(tmp_path):
    """`localiser.unsure_fraction` and `localiser.forget_percent` (issue 38 item 3) are map options:
    checked like the others, shown in the map's `params`, the forgetting rule stated with the map's
    batch; a map that does not set them shows their defaults (0.5, the threshold's half; 1 %)."""
    with make_client(tmp_path / "data") as c:
        make(c, "m", unsure_fraction=0.75, forget_percent=5)
        shown = c.get("/v1/maps/m").json()
        make(c, "plain")
        plain = c.get("/v1/maps/plain").json()
        bad = c.post("/v1/maps", json={"map_id": "bad", "localiser": {"forget_percent": 101}})
    assert (shown["params"]["localiser"]["unsure_fraction"], shown["params"]["localiser"]["forget_percent"]) \
        == (0.75, 5)
    assert "at least 5% of max_rows" in shown["places"]["forgetting"]
    assert (plain["params"]["localiser"]["unsure_fraction"], plain["params"]["localiser"]["forget_percent"]) \
        == (0.5, 1)
    assert "at least 1% of max_rows" in plain["places"]["forgetting"]
    assert bad.status_code == 422 and bad.json()["errors"][0]["name"] == "localiser.forget_percent"
