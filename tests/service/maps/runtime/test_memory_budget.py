"""The process-wide memory budget over all maps (docs/design/service.md §1.8, issue 19 item 1): every
reservation is checked (create, open at start, learn, restore, import), a refusal is a 409 problem with
what is used and asked, maps that do not fit at start stay closed and listed, `GET /v1/memory` shows it."""

from __future__ import annotations

import pytest

from tests.service.helpers import frame, make_client, post

HUGE = 2**40


def budget_of(c) -> dict:
    r = c.get("/v1/memory")
    assert r.status_code == 200, r.text
    return r.json()


def held(c, map_id: str) -> int:
    return next(m["bytes"] for m in budget_of(c)["maps"] if m["map_id"] == map_id)


@pytest.fixture
def sizes(tmp_path):
    """What the encoders, a tiny map (its own projection: seed 1) and a learned row hold."""
    with make_client(tmp_path / "probe", memory_budget_bytes=HUGE) as c:
        assert c.post("/v1/maps", json={"map_id": "a", "seed": 1}).status_code == 201
        b = budget_of(c)
        rt = c.app.state.registry.get("a")
        return {"encoders": b["encoders_bytes"], "map": held(c, "a"), "default": held(c, "default"),
                "row": rt.row_bytes, "tm": rt.tm.size()["bytes"]}


def test_memory_resource_adds_up(tmp_path):
    with make_client(tmp_path / "data", memory_budget_bytes=HUGE) as c:
        assert c.post("/v1/maps", json={"map_id": "a", "seed": 1}).status_code == 201
        b = budget_of(c)
        assert (b["total_bytes"], b["source"]) == (HUGE, "setting")
        assert b["encoders_bytes"] > 0
        assert b["used_bytes"] == b["encoders_bytes"] + sum(m["bytes"] for m in b["maps"])
        tm = max(m["parts"]["tm"] for m in b["maps"] if m["open"])
        assert b["reserve_bytes"] == tm and b["free_bytes"] == HUGE - b["used_bytes"] - tm
        a = next(m for m in b["maps"] if m["map_id"] == "a")
        rt = c.app.state.registry.get("a")
        assert a["open"] and a["parts"]["tm"] == rt.tm.size()["bytes"]  # exact, not an estimate
        assert a["parts"]["projection"] >= rt.hasher.P.nbytes
        assert b["process_rss_bytes"] > 0


def test_maps_with_one_projection_count_it_once(tmp_path):
    with make_client(tmp_path / "data", memory_budget_bytes=HUGE) as c:
        for map_id in ("b", "c"):  # the default seed: the default map's projection
            assert c.post("/v1/maps", json={"map_id": map_id}).status_code == 201
        parts = {m["map_id"]: m["parts"] for m in budget_of(c)["maps"]}
        assert parts["default"]["projection"] > 0
        assert parts["b"]["projection"] == parts["c"]["projection"] == 0
        assert parts["b"]["tm"] == parts["default"]["tm"]


def test_create_beyond_the_budget_is_refused_with_used_and_asked(tmp_path, sizes):
    # Every check keeps room for one recovery's second memory (the largest map's tm) beside what is held.
    tm = sizes["tm"]
    total = sizes["encoders"] + sizes["default"] + sizes["map"] + tm + sizes["map"] // 2
    data = tmp_path / "data"
    with make_client(data, memory_budget_bytes=total) as c:
        assert c.post("/v1/maps", json={"map_id": "a", "seed": 1}).status_code == 201
        used = budget_of(c)["used_bytes"]
        r = c.post("/v1/maps", json={"map_id": "b", "seed": 2})
        assert r.status_code == 409, r.text
        p = r.json()
        assert p["type"] == "urn:cortexloc:problem:memory-budget"
        assert (p["used_bytes"], p["asked_bytes"], p["total_bytes"]) == (used + tm, sizes["map"], total)
        assert p["free_bytes"] == total - used - tm == budget_of(c)["free_bytes"]  # what /v1/memory says
        assert "CORTEXLOC_MEMORY_BUDGET_BYTES" in p["detail"]
        # Nothing of it was made: no map, no directory, nothing held.
        assert c.get("/v1/maps/b").status_code == 404
        assert not (data / "maps" / "b").exists()
        assert budget_of(c)["used_bytes"] == used
        # Deleting a map gives its share back; the room for a second memory (its first recovery builds
        # one beside the runtime's empty one) stays kept.
        assert c.delete("/v1/maps/a").status_code == 204
        c.app.state.registry.budget.total = budget_of(c)["used_bytes"] + sizes["map"] + tm - 1
        r = c.post("/v1/maps", json={"map_id": "b", "seed": 2})
        assert r.status_code == 409 and r.json()["asked_bytes"] == sizes["map"], r.text
        assert not (data / "maps" / "b").exists() and c.get("/v1/maps/b").status_code == 404
        c.app.state.registry.budget.total += 1
        assert c.post("/v1/maps", json={"map_id": "b", "seed": 2}).status_code == 201


def test_maps_that_do_not_fit_at_start_stay_closed_and_listed(tmp_path, sizes):
    data = tmp_path / "data"
    with make_client(data, memory_budget_bytes=HUGE) as c:
        for i, map_id in enumerate(("a", "b")):
            assert c.post("/v1/maps", json={"map_id": map_id, "seed": i + 1}).status_code == 201
            assert post(c, frame(i), map_id=map_id).status_code == 200
    total = sizes["encoders"] + sizes["default"] + sizes["map"] + sizes["tm"] + sizes["map"] // 2
    with make_client(data, memory_budget_bytes=total) as c:
        states = {m["map_id"]: (m["state"], m["state_reason"]) for m in c.get("/v1/maps").json()["maps"]}
        assert states == {"default": ("ready", None), "a": ("ready", None), "b": ("failed", "memory-budget")}
        r = post(c, frame(1), map_id="b")
        assert r.status_code == 503 and r.json()["state_reason"] == "memory-budget"
        # the remedy, as for every failed map with one (an outside tester saw the reason only)
        assert "CORTEXLOC_MEMORY_BUDGET_BYTES" in r.json()["detail"] and "restart" in r.json()["detail"]
        assert post(c, frame(0), map_id="a", learn="false", stream="other").json()["matches"][0]["seq"] == 1
        ready = c.get("/readyz")
        assert ready.status_code == 200, ready.text
        b = budget_of(c)
        closed = [m for m in b["maps"] if not m["open"]]
        assert [(m["map_id"], m["reason"]) for m in closed] == [("b", "memory-budget")]
        assert closed[0]["bytes"] == sizes["map"] + sizes["row"]
        assert b["used_bytes"] <= total
        # Its share freed (a deleted map), it opens at the next start.
        assert c.delete("/v1/maps/a").status_code == 204
    with make_client(data, memory_budget_bytes=total) as c:
        assert c.get("/v1/maps/b").json()["state"] == "ready"


def test_learning_stops_at_the_budget_and_localisation_goes_on(tmp_path, sizes):
    # Room for the default map's second memory (kept for its recovery), then for three rows.
    total = sizes["encoders"] + sizes["default"] + sizes["tm"] + 3 * sizes["row"]
    with make_client(tmp_path / "data", memory_budget_bytes=total) as c:
        for i in range(3):
            assert post(c, frame(i)).status_code == 200
        r = post(c, frame(3))
        assert r.status_code == 409, r.text
        assert r.json()["type"] == "urn:cortexloc:problem:memory-budget"
        assert r.json()["asked_bytes"] == sizes["row"]
        assert c.get("/v1/maps/default").json()["observations"] == 3
        assert post(c, frame(1), learn="false").json()["matches"][0]["seq"] == 2


def test_restore_is_checked_against_the_budget(tmp_path, sizes):
    # A restore builds the new memory beside the old one (in the room kept for a recovery's second
    # memory) and the new index beside the old.
    tm, row = sizes["tm"], sizes["row"]
    total = sizes["encoders"] + sizes["default"] + tm + 6 * row
    with make_client(tmp_path / "data", memory_budget_bytes=total) as c:
        budget = c.app.state.registry.budget
        assert post(c, frame(0)).status_code == 200
        one = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        for i in (1, 2):
            assert post(c, frame(i)).status_code == 200
        assert c.post(f"/v1/maps/default/snapshots/{one}/restore").status_code == 200
        assert budget_of(c)["used_bytes"] == total - tm - 5 * row  # the restored rows, exactly
        three = next(s["snapshot_id"] for s in c.get("/v1/maps/default/snapshots").json()["snapshots"]
                     if s["kind"] == "pre-restore")
        budget.total = total - 3 * row  # room for the old and new memory, not for the two rows more
        r = c.post(f"/v1/maps/default/snapshots/{three}/restore")
        assert r.status_code == 409, r.text
        assert r.json()["type"] == "urn:cortexloc:problem:memory-budget"
        assert r.json()["asked_bytes"] == 2 * row
        budget.total = total - tm // 2  # no room for a second memory beside the old index
        r = c.post(f"/v1/maps/default/snapshots/{three}/restore")
        assert r.status_code == 409 and r.json()["asked_bytes"] == row
        assert c.get("/v1/maps/default").json()["observations"] == 1  # unchanged
        assert budget_of(c)["used_bytes"] == total - tm - 5 * row  # nothing left held
        budget.total = total
        assert c.post(f"/v1/maps/default/snapshots/{three}/restore").status_code == 200


def test_the_default_is_a_share_of_the_smaller_of_host_and_cgroup(tmp_path):
    from service.maps.runtime import budget as map_budget

    host, source = map_budget.memory_limit(cgroup_files=())
    assert source == "host" and host > 0
    v2 = tmp_path / "memory.max"
    v2.write_text("max\n")
    assert map_budget.memory_limit([v2]) == (host, "host")
    v2.write_text(f"{2**30}\n")
    assert map_budget.memory_limit([v2, tmp_path / "absent"]) == (2**30, "cgroup")
    v1 = tmp_path / "memory.limit_in_bytes"
    v1.write_text("9223372036854771712\n")  # v1's "no limit"
    assert map_budget.memory_limit([tmp_path / "absent", v1]) == (host, "host")
    total, why = map_budget.default_total()
    assert total == int(map_budget.DEFAULT_SHARE * map_budget.memory_limit()[0]) and "x" in why


def test_import_is_checked_against_the_maps_already_there(tmp_path, sizes, monkeypatch):
    from typer.testing import CliRunner

    from service.cli import app as cli_app

    with make_client(tmp_path / "source", memory_budget_bytes=HUGE) as c:
        assert c.post("/v1/maps", json={"map_id": "lab", "seed": 1}).status_code == 201
        assert post(c, frame(0), map_id="lab").status_code == 200
        sid = c.post("/v1/maps/lab/snapshots").json()["snapshot_id"]
        tar = tmp_path / "lab.tar"
        tar.write_bytes(c.get(f"/v1/maps/lab/snapshots/{sid}/download").content)
    data = tmp_path / "data"
    with make_client(data):  # a data directory holding `default`
        pass
    # Room for the imported map alone, not beside `default` (offline: no encoders are counted).
    monkeypatch.setenv("CORTEXLOC_MEMORY_BUDGET_BYTES", str(sizes["map"] + sizes["map"] // 2))
    r = CliRunner().invoke(cli_app, ["import", str(tar), "--data-dir", str(data)])
    assert r.exit_code == 1 and "CORTEXLOC_MEMORY_BUDGET_BYTES" in r.output, r.output
    assert not (data / "maps" / "lab").exists()
    monkeypatch.setenv("CORTEXLOC_MEMORY_BUDGET_BYTES", str(3 * sizes["map"]))
    r = CliRunner().invoke(cli_app, ["import", str(tar), "--data-dir", str(data)])
    assert r.exit_code == 0, r.output


SMALL = {"map_id": "small", "seed": 3, "tm": {"columnDimensions": 64, "cellsPerColumn": 4},
         "slsbh": {"k": 32}}


def test_a_fresh_start_one_byte_short_is_ready_with_default_closed(tmp_path, sizes):
    # Issue 34 item 4: the default map needs its share and, while its first recovery runs, a second memory.
    edge = sizes["encoders"] + sizes["default"] + sizes["tm"]
    with make_client(tmp_path / "exact", memory_budget_bytes=edge) as c:
        assert c.get("/v1/maps/default").json()["state"] == "ready"
        assert budget_of(c)["used_bytes"] == edge - sizes["tm"]
    data = tmp_path / "short"
    with make_client(data, memory_budget_bytes=edge - 1) as c:
        # Ready, the default made on disk and closed, saying why; a map that fits can still be made.
        ready = c.get("/readyz")
        assert ready.status_code == 200, ready.text
        m = c.get("/v1/maps/default").json()
        assert (m["state"], m["state_reason"]) == ("failed", "memory-budget")
        closed = [(x["map_id"], x["open"], x["bytes"]) for x in budget_of(c)["maps"]]
        assert closed == [("default", False, sizes["default"] + sizes["tm"])]
        assert post(c, frame(0)).status_code == 503
        assert c.post("/v1/maps", json=SMALL).status_code == 201
        assert c.delete("/v1/maps/small").status_code == 204
    with make_client(data, memory_budget_bytes=edge) as c:  # it opens where it fits
        assert c.get("/v1/maps/default").json()["state"] == "ready"
        assert post(c, frame(0)).status_code == 409  # no room for a row beside the second memory


def test_a_map_that_learned_within_the_budget_reopens_under_it(tmp_path, sizes):
    # One accounting for learning and the next start: a row is taken only while the map could reopen.
    total = sizes["encoders"] + sizes["default"] + sizes["tm"] + 3 * sizes["row"]
    data = tmp_path / "data"
    with make_client(data, memory_budget_bytes=total) as c:
        assert [post(c, frame(i)).status_code for i in range(4)] == [200, 200, 200, 409]
        assert budget_of(c)["used_bytes"] == total - sizes["tm"]
    with make_client(data, memory_budget_bytes=total) as c:  # exactly enough
        m = c.get("/v1/maps/default").json()
        assert (m["state"], m["observations"]) == ("ready", 3)
        assert post(c, frame(0), learn="false", stream="other").json()["matches"][0]["seq"] == 1
    with make_client(data, memory_budget_bytes=total - 1) as c:  # one byte short
        assert c.get("/readyz").status_code == 200
        m = c.get("/v1/maps/default").json()
        assert (m["state"], m["state_reason"]) == ("failed", "memory-budget")
