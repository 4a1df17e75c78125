"""A map driven pass after pass does not multiply its places (issue 36; docs/design/science.md §11.7,
§11.8): a flat frame is stored once per place at most, and the rows a restarted drive made while it
warmed up are joined to the places its confident path then names, durably (recovery, snapshots,
`verify`)."""

from __future__ import annotations

import sqlite3

import cv2
import numpy as np

from service.maps.recovery import open_catalog, verify_map
from tests.service.helpers import frame, make_client, post
from tests.service.test_loop_closures import LAP, THRESHOLD
from tests.service.test_places import crash, shape

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
    # the first pass stores the tunnel once: its first frame a row, the same view after it a rehearsal
    # of that row (the stream has not moved by appearance, §11.6)
    assert passes[0][flat[0]]["seq"] is not None
    assert [passes[0][i]["consolidated_into"] for i in flat[1:]] == [passes[0][flat[0]]["seq"]] * 2
    for later in passes[1:]:  # later passes: visits of its rows, no new place (before: a row each)
        assert [later[i]["seq"] for i in flat] == [None] * len(flat)
        assert all(later[i]["consolidated_into"] is not None for i in flat)
        assert all(later[i]["place"]["low_information"] for i in flat)


def test_warm_up_rows_are_joined_to_the_places_the_confident_path_names(tmp_path):
    with make_client(tmp_path / "data") as c:
        first, second = two_drives(c)
        rows = {b["seq"]: p for p, b in zip(LAP, first, strict=True) if b["seq"] is not None}
        rt = c.app.state.registry.get("default")
        joins = rt.store.joins()
        warm = [b["seq"] for b in second[:3]]
        assert all(s is not None for s in warm)  # no answer yet: each warm-up frame made a row
        assert {row for row, _ in joins} >= set(warm)  # ... and each was joined (before: none)
        dropped = rt.store.dropped()
        for row, old in joins:
            assert old in rows and abs(rows[old] - LAP[[b["seq"] for b in second].index(row)]) <= 1
            assert rt.localisation.place_of(row) == rt.localisation.place_of(old)
            assert dropped[row] == "joined" and rt.localisation.used[row] < 0  # held no more
        # the first drive's places (the tunnel once: its first frame's row) and no more
        assert c.get("/v1/maps/default").json()["places"]["places"] == len(rows) == len(LAP) - 2


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
        assert all(rt.localisation.used[b["seq"]] >= 0 for b in warm)  # held, places of their own
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
    assert verify_map(catalog, catalog.get_map("default")).ok
    conn = sqlite3.connect(catalog.layout.map_db("default"))
    conn.execute("DELETE FROM dropped WHERE seq = ?", (row,))  # a join whose row is still held
    conn.commit()
    conn.close()
    check = verify_map(catalog, catalog.get_map("default"))
    assert not check.ok and any(f"join of row {row}" in p for p in check.problems)
