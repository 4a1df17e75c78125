"""A map driven pass after pass does not multiply its places (issue 36; docs/design/science.md §11.7,
§11.8): a flat frame is stored once per place at most, and the rows a restarted drive made while it
warmed up are joined to the places its confident path then names, durably (recovery, snapshots,
`verify`)."""

from __future__ import annotations

import json
import sqlite3

import cv2
import numpy as np

from service.maps.recovery import open_catalog, verify_map
from tests.service.helpers import frame, make_client, post, state_of
from tests.service.maps.test_loop_closures import LAP, THRESHOLD
from tests.service.maps.test_places import crash, places, shape

TUNNEL = range(12, 15)  # the places of LAP where the route is in a tunnel: near-black frames


def tunnel_frame(place: int) -> bytes:
    """A near-black frame (contrast ~0: no information, §11.7), a few levels of sensor noise."""
    img = 6.0 + np.random.default_rng(500 + place).normal(0, 0.8, (96, 128, 3))
    ok, buf = cv2.imencode(".png", np.clip(img, 0, 255).astype(np.uint8))
    assert ok
    return buf.tobytes()


def view(p: int) -> bytes:
    return tunnel_frame(p) if p in TUNNEL else frame(p)


def drive(c, stream: str = "robot", places: list[int] = LAP) -> list[dict]:
    return [post(c, view(p), stream=stream, learn="true", top_k=0).json() for p in places]


def restart(c, stream: str = "robot") -> None:
    """A new drive: the stream's sequence and search start again (a new warm-up)."""
    assert c.post(f"/v1/maps/default/streams/{stream}/reset").status_code == 200


def setup(c) -> None:
    assert c.patch("/v1/maps/default", json={"revisit_threshold": THRESHOLD}).status_code == 200


def two_drives(c, second: list[int] = LAP) -> tuple[list[dict], list[dict]]:
    """A first drive over LAP, the drive restarted, and a second over `second`: their replies."""
    setup(c)
    first = drive(c)
    restart(c)
    return first, drive(c, places=second)


def test_a_flat_frame_is_stored_once_per_place_not_on_every_pass(tmp_path):
    with make_client(tmp_path / "data") as c:
        setup(c)
        passes = []
        for _ in range(4):
            passes.append(drive(c))
            restart(c)
    flat = [i for i, p in enumerate(LAP) if p in TUNNEL]
    assert all(passes[0][i]["seq"] is not None for i in flat)  # the first pass stores the tunnel
    for later in passes[1:]:  # later passes: visits of its rows, no new place (before: a row each)
        assert [later[i]["seq"] for i in flat] == [None] * len(flat)
        assert all(later[i]["consolidated_into"] is not None for i in flat)
        assert all(later[i]["place"]["low_information"] for i in flat)


def flat_rows(c) -> list[int]:
    rt = c.app.state.registry.get("default")
    return [int(r) for r in np.flatnonzero(rt.place_map.flat)]


def test_a_rows_flatness_survives_a_restart_a_crash_and_a_snapshot_restore(tmp_path):
    """Which rows were flat is stored with them (schema 13, `flat`): the map rebuilt on a restart, after
    a kill -9, and from a snapshot knows its tunnel's rows as flat, as the live map did (before: a
    rebuilt map knew none, so its flat frames would not be visits of them)."""
    data = tmp_path / "data"
    with make_client(data, snapshot_every=0) as c:
        setup(c)
        first = drive(c)
        tunnel = sorted(first[i]["seq"] for i, p in enumerate(LAP) if p in TUNNEL)
        assert flat_rows(c) == tunnel
        snap = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
    with make_client(data, snapshot_every=0) as c:  # a restart
        assert flat_rows(c) == tunnel
        restart(c)
        second = drive(c, places=[p + 100 for p in LAP[:5]] + list(TUNNEL))  # new places, a tunnel
        later = sorted(b["seq"] for b in second[5:] if b["seq"] is not None)
        assert later  # (unsure on new places: the tunnel made rows again)
        crash(c)
    with make_client(data, snapshot_every=0) as c:  # a kill -9: the rows after it replayed
        assert flat_rows(c) == sorted(tunnel + later)
        assert c.post(f"/v1/maps/default/snapshots/{snap}/restore").status_code == 200
        assert flat_rows(c) == tunnel


def test_warm_up_rows_are_joined_to_the_places_the_confident_path_names(tmp_path):
    with make_client(tmp_path / "data") as c:
        first, second = two_drives(c)
        rows = {b["seq"]: p for p, b in zip(LAP, first, strict=True)}
        rt = c.app.state.registry.get("default")
        joins = rt.store.joins()
        warm = [b["seq"] for b in second[:3]]
        assert all(s is not None for s in warm)  # no answer yet: each warm-up frame made a row
        assert {row for row, _ in joins} >= set(warm)  # ... and each was joined (before: none)
        dropped = rt.store.dropped()
        for row, old in joins:
            assert old in rows and abs(rows[old] - LAP[[b["seq"] for b in second].index(row)]) <= 1
            assert rt.place_map.place_of(row) == rt.place_map.place_of(old)
            assert dropped[row] == "joined" and rt.place_map.used[row] < 0  # held no more
        assert c.get("/v1/maps/default").json()["places"]["places"] == len(LAP)


def test_a_drive_restarted_anywhere_on_known_ground_adds_no_place(tmp_path):
    """A drive that starts part-way along the route (a node restarted where the robot stands): its first
    frame ranks the row of its place first, so the confident path covers it and its warm-up row is
    joined like the rest (before, the first frame's winner cells, least-used ones without context,
    matched only other first frames: it named row 1, and each drive started away from the route's start
    left its first row as a new place, an outside tester's 80 places became 85 in 5 drives)."""
    with make_client(tmp_path / "data") as c:
        setup(c)
        first = drive(c)
        rows = {p: b["seq"] for p, b in zip(LAP, first, strict=True)}
        # drives of 12 frames starting before the first drive's last 20 moves (the robot's short-term
        # memory, whose rows are no loop candidates and take no join, §11.6)
        for start in (4, 9, 2):
            restart(c)
            second = drive(c, places=LAP[start:start + 12])
            top = post(c, view(LAP[start]), stream="probe", learn="false", top_k=1).json()["matches"]
            assert c.post("/v1/maps/default/streams/probe/reset").status_code == 200
            assert top[0]["seq"] == rows[LAP[start]] and top[0]["score"] > 0.9, top  # a new stream's first
            assert second[0]["seq"] is not None  # no answer yet: a warm-up row ...
            assert c.get(f"/v1/maps/default/observations/{second[0]['seq']}").json()["joined_to"] == \
                rows[LAP[start]]  # ... joined to its place's row
        assert c.get("/v1/maps/default").json()["places"]["places"] == len(LAP)


def test_a_posed_drive_restarted_on_known_ground_joins_every_warm_up_row(tmp_path):
    """With poses the short-term memory is the last `short_term_metres` (20 m) of path: at a frame every
    10 m, 2 rows. The warm-up rows are the stream's newest rows whether or not still in it (before, a
    posed drive's first warm-up rows fell out of it before the path found its place and stayed places
    of their own: an outside tester's second drive left 2 of its 4)."""
    def posed(stream: str, places: list[int], y: float) -> list[dict]:
        return [post(c, view(p), stream=stream, learn="true", top_k=0, metadata=json.dumps(
            {"stamp": 1000.0 + p, "pose": {"x": 10.0 * p, "y": y, "yaw": 0.0}})).json() for p in places]

    with make_client(tmp_path / "data") as c:
        setup(c)
        rows = {p: b["seq"] for p, b in zip(LAP, posed("a", LAP, 0.0), strict=True)}
        second = posed("b", LAP[16:], 3.0)  # another robot, 3 m to the side, from place 16 (past the tunnel)
        warm = [(p, b["seq"]) for p, b in zip(LAP[16:], second, strict=True) if b["seq"] is not None]
        assert len(warm) >= 3, second  # it made rows before it knew where it was
        for p, seq in warm:
            assert c.get(f"/v1/maps/default/observations/{seq}").json()["joined_to"] == rows[p], (p, seq)
        assert c.get("/v1/maps/default").json()["places"]["places"] == len(LAP)


#: A map whose consolidation takes only a frame its stored code matches (`consolidate` 0.99): on the
#: tests' encoder (codes of a few dozen bits) a frame of LAP with pixel noise is then another condition
#: of its place, like its row (far above `join_kept`) and not represented by it, whatever bit the noise
#: flips; the same noisy frame again is represented by the row it made.
KEPT_MAP = {"map_id": "kept", "localiser": {"consolidate": 0.99}}
OTHERWISE = 60.0


def kept_drive(c, noisy: int = 0, places: list[int] = LAP) -> list[dict]:
    """A drive of "kept" restarted at `places`' start, its first `noisy` frames in other conditions (the
    same noise each drive)."""
    assert c.post("/v1/maps/kept/streams/robot/reset").status_code == 200
    return [post(c, frame(p, noise=OTHERWISE) if i < noisy else view(p), map_id="kept", stream="robot",
                 learn="true", top_k=0).json() for i, p in enumerate(places)]


def kept_joins(c) -> list[tuple[int, int]]:
    rt = c.app.state.registry.get("kept")
    return [(row, old) for row, old in rt.store.joins() if rt.place_map.used[row] >= 0]


def kept_shape(c) -> tuple:
    rt = c.app.state.registry.get("kept")
    info = places(c, "kept")
    return (*state_of(c, "kept"), info["places"], info["appearances"], rt.place_map.graph.place.tolist(),
            rt.place_map.used.tolist())


def new_kept_map(c) -> dict[int, int]:
    """The map, and its first drive over LAP: row -> place."""
    assert c.post("/v1/maps", json=KEPT_MAP).status_code == 201
    assert c.patch("/v1/maps/kept", json={"revisit_threshold": THRESHOLD}).status_code == 200
    return {b["seq"]: p for p, b in zip(LAP, kept_drive(c), strict=True)}


def test_a_warm_up_row_seen_otherwise_is_kept_as_an_appearance_and_the_next_drive_adds_none(tmp_path):
    """A warm-up row the path explains but its old row does not represent (another season's first frames)
    was a place of its own, and each later drive in those conditions made another (an outside soak: a
    winter lap repeated exactly, 8-14 rows a pass). It is joined and kept (schema 14, docs/design/
    science.md §11.8): an appearance of the old row's place, held and on disk, durable over a crash, and
    the next drive in those conditions is represented by it."""
    data = tmp_path / "data"
    with make_client(data, snapshot_every=0) as c:
        rows = new_kept_map(c)
        second = kept_drive(c, noisy=4)
        rt = c.app.state.registry.get("kept")
        kept = kept_joins(c)
        seqs = [b["seq"] for b in second]
        assert {row for row, _ in kept} == {s for s in seqs[:4] if s is not None}, rt.store.joins()
        dropped = rt.store.dropped()
        for row, old in kept:
            assert abs(rows[old] - LAP[seqs.index(row)]) <= 1  # the place the path stood on then
            assert rt.place_map.place_of(row) == rt.place_map.place_of(old) and row not in dropped
            assert c.get(f"/v1/maps/kept/observations/{row}").json()["joined_to"] is None  # held
        info = places(c, "kept")
        assert (info["places"], info["appearances"]) == (len(LAP), len(LAP) + len(kept))
        kept_drive(c, noisy=4)  # the same conditions again: its warm-up is represented, not kept again
        assert kept_joins(c) == kept
        assert (places(c, "kept")["places"], places(c, "kept")["appearances"]) == \
            (info["places"], info["appearances"])
        before = kept_shape(c)
        crash(c)
    with make_client(data, snapshot_every=0) as c:
        assert kept_shape(c) == before and kept_joins(c) == kept  # the kept joins were replayed
    catalog = open_catalog(data)
    check = verify_map(catalog, catalog.get_map("kept"))
    assert check.ok, check
    conn = sqlite3.connect(catalog.layout.map_db("kept"))
    conn.execute("INSERT INTO dropped (seq, reason, after_seq, created_at) VALUES (?, 'joined', 0, 'x')",
                 (kept[0][0],))  # a kept join whose row is dropped as a join that does not keep it
    conn.commit()
    conn.close()
    check = verify_map(catalog, catalog.get_map("kept"))
    assert not check.ok and any(f"kept join of row {kept[0][0]}" in p for p in check.problems)


def test_a_map_restored_from_a_snapshot_taken_before_a_kept_join(tmp_path):
    data = tmp_path / "data"
    with make_client(data, snapshot_every=0) as c:
        new_kept_map(c)
        warm = kept_drive(c, noisy=4, places=LAP[:4])  # warm-up rows, not joined yet
        rt = c.app.state.registry.get("kept")
        assert rt.store.joins() == []
        at_snapshot = kept_shape(c)
        snap = c.post("/v1/maps/kept/snapshots").json()["snapshot_id"]
        for p in LAP[4:]:
            post(c, view(p), map_id="kept", stream="robot", learn="true", top_k=0)
        assert {row for row, _ in kept_joins(c)} == {b["seq"] for b in warm}
        assert c.post(f"/v1/maps/kept/snapshots/{snap}/restore").status_code == 200
        rt = c.app.state.registry.get("kept")
        assert rt.store.joins() == [] and kept_shape(c) == at_snapshot
        assert rt.place_map.graph.alone(np.array([b["seq"] for b in warm])).all()  # places of their own
        kept_drive(c, noisy=4)  # the map goes on, and keeps its next warm-up
        assert kept_joins(c)
    catalog = open_catalog(data)
    check = verify_map(catalog, catalog.get_map("kept"))
    assert check.ok, check


def test_the_joins_come_back_after_a_crash(tmp_path):
    data = tmp_path / "data"
    with make_client(data, snapshot_every=0) as c:
        two_drives(c)
        assert c.app.state.registry.get("default").store.joins()
        before = shape(c)
        crash(c)
    with make_client(data, snapshot_every=0) as c:
        assert shape(c) == before  # places, rows held, links: the joins were replayed


def test_a_map_restored_from_a_snapshot_taken_between_a_warm_up_and_its_join(tmp_path):
    data = tmp_path / "data"
    with make_client(data) as c:
        _, warm = two_drives(c, second=LAP[:3])  # warm-up rows, not joined yet
        rt = c.app.state.registry.get("default")
        assert rt.store.joins() == []
        at_snapshot = shape(c)
        snap = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        drive(c, places=LAP[3:])
        assert {row for row, _ in rt.store.joins()} >= {b["seq"] for b in warm}
        assert c.post(f"/v1/maps/default/snapshots/{snap}/restore").status_code == 200
        rt = c.app.state.registry.get("default")
        assert rt.store.joins() == [] and shape(c)[:-2] == at_snapshot[:-2]
        assert all(rt.place_map.used[b["seq"]] >= 0 for b in warm)  # held, places of their own
        restart(c)
        drive(c)  # the map goes on, and joins again
        assert rt.store.joins()
    check = verify_map(open_catalog(data), open_catalog(data).get_map("default"))
    assert check.ok, check


def test_verify_checks_the_joins(tmp_path):
    data = tmp_path / "data"
    with make_client(data) as c:
        two_drives(c)
        row, _ = c.app.state.registry.get("default").store.joins()[0]
    catalog = open_catalog(data)
    ticks: list[tuple[int, int]] = []
    assert verify_map(catalog, catalog.get_map("default"),
                      progress=lambda n, total: ticks.append((n, total))).ok
    # the progress's total is what the replay steps, joined rows included (an outside tester saw 24/22)
    assert ticks[-1][0] == ticks[-1][1] and {total for _, total in ticks} == {ticks[-1][1]}
    conn = sqlite3.connect(catalog.layout.map_db("default"))
    conn.execute("DELETE FROM dropped WHERE seq = ?", (row,))  # a join whose row is still held
    conn.commit()
    conn.close()
    check = verify_map(catalog, catalog.get_map("default"))
    assert not check.ok and any(f"join of row {row}" in p for p in check.problems)


def test_map_sqlite_does_not_grow_drive_after_drive(tmp_path):
    """A joined warm-up row is turned into a visit of the old row it joined and deleted in the join's
    transaction (schema 12, docs/design/science.md §11.8): drive after restarted drive, the rows in
    map.sqlite stay the first drive's (before: its warm-up's rows stayed, joined but on disk, each drive)."""
    data = tmp_path / "data"
    with make_client(data) as c:
        setup(c)
        drive(c)
        rt = c.app.state.registry.get("default")
        rows, counts = rt.store.count(), []
        for _ in range(4):
            restart(c)
            drive(c)
            counts.append(rt.store.count())
        joins = rt.store.joins()
        assert len(joins) >= 8 and counts == [rows] * 4
        assert all(rt.store.get(row) is None and rt.store.joined_to(row) == old for row, old in joins)
        assert {v.row for v in rt.store.visits() if v.row is not None} == {row for row, _ in joins}
        before = shape(c)
    with make_client(data) as c:  # a restart rebuilds the same map from the rows and the visits
        assert shape(c) == before
    check = verify_map(open_catalog(data), open_catalog(data).get_map("default"))
    assert check.ok, check


def test_a_joined_row_still_answers_as_it_was_acknowledged(tmp_path):
    """Nothing acknowledged is lost: a warm-up row the join turned into a visit and deleted (schema 12)
    answers `GET .../observations/{seq}` with its record as posted (id, digest, metadata), without its
    thumbnail, after a restart too; a seq never handed out is still a 404."""
    data = tmp_path / "data"
    with make_client(data) as c:
        setup(c)
        drive(c)
        restart(c)
        meta = json.dumps({"run": 2})
        second = [post(c, view(p), stream="robot", learn="true", top_k=0, metadata=meta).json() for p in LAP]
        rt = c.app.state.registry.get("default")
        gone = [row for row, _ in rt.store.joins() if rt.store.get(row) is None]
        assert gone
        told = {r["seq"]: r for r in second if r["seq"] is not None}
    with make_client(data) as c:
        store = c.app.state.registry.get("default").store
        for seq in gone:
            got = c.get(f"/v1/maps/default/observations/{seq}")
            assert got.status_code == 200, got.text
            body = got.json()
            assert body["observation_id"] == told[seq]["observation_id"] and body["stream"] == "robot"
            assert body["metadata"]["run"] == 2 and body["has_thumbnail"] is False
            assert len(body["image_sha256"]) == 64
            thumb = c.get(f"/v1/maps/default/observations/{seq}/thumbnail")
            assert thumb.status_code == 404 and "thumbnail" in thumb.text
            assert body["joined_to"] == store.joined_to(seq) and body["joined_to"] < seq
        missing = c.get("/v1/maps/default/observations/99999")
        assert missing.status_code == 404 and missing.headers["content-type"] == "application/problem+json"


def test_the_listing_keeps_a_row_a_join_took_away_so_pages_only_grow(tmp_path):
    """A follower pages through the map's rows while a restarted drive learns: a warm-up join then turns
    rows it has read into visits. Within the epoch, the pages read again hold every row read before (the
    joined ones with `joined_to`, the held ones with null), in seq order, and page by page the same as in
    one read; before, the listing held rows only and the joined ones vanished."""
    data = tmp_path / "data"
    with make_client(data) as c:
        setup(c)
        drive(c)
        restart(c)
        seen, epochs = set(), set()
        for p in LAP:  # the second drive's warm-up rows, then the join; the follower reads after each frame
            post(c, view(p), stream="robot", learn="true", top_k=0)
            page = c.get("/v1/maps/default/observations", params={"limit": 500}).json()
            seen |= {o["seq"] for o in page["observations"]}
            epochs.add(page["epoch"])
        rt = c.app.state.registry.get("default")
        joined = {row: old for row, old in rt.store.joins() if rt.store.get(row) is None}
        assert joined and set(joined) <= seen  # the follower had read the rows the join took away
        again = c.get("/v1/maps/default/observations", params={"limit": 500}).json()
        assert {again["epoch"]} == epochs
        seqs = [o["seq"] for o in again["observations"]]
        assert seqs == sorted(seqs) and seen <= set(seqs)
        for o in again["observations"]:
            assert o["joined_to"] == joined.get(o["seq"]), o
        pages, after = [], 0
        while after is not None:
            page = c.get("/v1/maps/default/observations", params={"after_seq": after, "limit": 3}).json()
            pages += page["observations"]
            after = page["next_after_seq"]
        assert pages == again["observations"]


def recovers_from(data, snap: str, before: tuple) -> None:
    """After a kill -9: the map comes back from snapshot `snap`, as it was (`shape` `before`)."""
    with make_client(data, snapshot_every=0) as c:
        assert shape(c) == before
        note = c.get("/v1/maps/default").json()["recovery"]
        assert note["source"] == "snapshot" and note["snapshot_id"] == snap, note


def test_a_crash_after_the_join_recovers_from_a_snapshot_taken_before_it(tmp_path):
    """The snapshot holds the warm-up rows' learning; the join after it turns them into visits and
    deletes them; a kill -9 then: the recovery starts at the snapshot and does not replay those visits
    again (their rows are at or before its seq), and gives the map the crash left."""
    data = tmp_path / "data"
    with make_client(data, snapshot_every=0) as c:
        _, warm = two_drives(c, second=LAP[:3])
        snap = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        drive(c, places=LAP[3:])
        rt = c.app.state.registry.get("default")
        assert all(rt.store.get(b["seq"]) is None for b in warm)  # joined away after the snapshot
        before = shape(c)
        crash(c)
    recovers_from(data, snap, before)


def test_a_snapshot_whose_last_row_was_joined_away_is_still_the_maps(tmp_path):
    """A snapshot's last row may be a warm-up row joined away before it was taken: the recovery still
    knows the snapshot as this file's (by the join's record of the row's observation id), and replays
    the rows and joins after it."""
    data = tmp_path / "data"
    with make_client(data, snapshot_every=0) as c:
        two_drives(c)
        rt = c.app.state.registry.get("default")
        last = rt.store.last_seq()
        assert rt.store.get(last) is None and rt.store.joined_to(last) is not None
        snap = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        restart(c)
        drive(c)  # a third drive: its warm-up rows and joins are after the snapshot
        before = shape(c)
        crash(c)
    recovers_from(data, snap, before)
    check = verify_map(open_catalog(data), open_catalog(data).get_map("default"))
    assert check.ok, check


def test_a_parked_robot_rehearses_its_row_and_a_repair_lists_no_merge(tmp_path):
    """A robot with poses that parks: the frames of its stop are visits of the row it made on arriving
    (a rehearsal, §11.6; before: a row per frame), and a repair, which lists visits into a stream's own
    recent rows, does not take a rehearsal for a merge."""
    def at(p: int, x: float, t: int) -> dict:
        meta = json.dumps({"stamp": float(t), "pose": {"x": x, "y": 0.0}})
        return post(c, view(p), stream="robot", learn="true", top_k=0, metadata=meta).json()

    with make_client(tmp_path / "data") as c:
        setup(c)
        [at(p, 2.0 * p, p) for p in LAP[:10]]
        stop = [at(10, 20.0 + 0.01 * k, 10 + k) for k in range(20)]
        arrived = stop[0]["seq"]
        assert arrived is not None and [b["consolidated_into"] for b in stop[1:]] == [arrived] * 19
        listed = c.get("/v1/maps/default/repair").json()
        assert listed["splits"] == [] and listed["unjoins"] == [] and listed["retractions"] == []
