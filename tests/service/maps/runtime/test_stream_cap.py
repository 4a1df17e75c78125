"""The per-map stream cap (docs/design/service.md §1.3, issue 19 item 8): a stream that posted within
CORTEXLOC_STREAM_KEEP_SECONDS is never evicted for a new one; the new one is refused (429 stream-limit,
Retry-After) and every robot keeps its context; idle streams are evicted, and counted in /metrics."""

from __future__ import annotations

import re
import time

from tests.service.helpers import frame, make_client, post, state_of
from tests.service.maps.recovery.test_recovery import crash


def evictions(c, map_id: str = "default") -> float:
    m = re.search(rf'cortexloc_map_stream_evictions\{{map="{map_id}"\}} (\S+)', c.get("/metrics").text)
    assert m, "no stream eviction metric"
    return float(m.group(1))


def test_a_recent_stream_is_not_evicted_for_a_new_one(tmp_path):
    with make_client(tmp_path / "data", max_streams=2, stream_keep_seconds=600) as c:
        now = [1000.0]
        c.app.state.registry.get("default").clock = lambda: now[0]  # the window without waiting for it
        for i, robot in enumerate(("robot1", "robot2")):
            now[0] += 10
            assert post(c, frame(i), stream=robot).status_code == 200
        before = state_of(c)
        for learn in ("true", "false"):
            r = post(c, frame(5), stream="intruder", learn=learn)
            assert r.status_code == 429, r.text
            p = r.json()
            assert p["type"] == "urn:cortexloc:problem:stream-limit"
            assert (p["max_streams"], p["keep_seconds"]) == (2, 600)
            assert int(r.headers["Retry-After"]) == p["retry_after"] == 590  # robot1 posted 10 s ago
        assert state_of(c) == before
        assert c.get("/v1/maps/default").json()["streams"] == ["robot1", "robot2"]
        assert evictions(c) == 0
        # Both robots go on in their sequences.
        now[0] += 300
        assert post(c, frame(2), stream="robot1").json()["sequence"]["step"] == 1
        now[0] += 301  # robot2 idle past the window now; robot1 posted since
        assert post(c, frame(3), stream="intruder").status_code == 200
        assert c.get("/v1/maps/default").json()["streams"] == ["robot1", "intruder"]
        assert evictions(c) == 1
        assert post(c, frame(4), stream="robot1").json()["sequence"]["step"] == 2  # context kept


def test_without_a_window_the_least_recently_used_stream_goes_at_once(tmp_path):
    with make_client(tmp_path / "data", max_streams=2, stream_keep_seconds=0) as c:
        for i, robot in enumerate(("a", "b", "c")):
            assert post(c, frame(i), stream=robot).status_code == 200
        assert c.get("/v1/maps/default").json()["streams"] == ["b", "c"]
        assert evictions(c) == 1


def test_a_restart_holds_no_more_streams_than_the_cap_and_counts_their_conditions(tmp_path):
    """A replay meets every stream that ever learned: the restarted map keeps the `max_streams` most
    recently used, as the live one did, and `GET .../memory` counts each one's condition (docs/design/
    science.md §11.10) in the streams' bytes."""
    data = tmp_path / "data"
    with make_client(data, max_streams=2, stream_keep_seconds=0) as c:
        for i, robot in enumerate(("a", "b", "c", "d")):
            assert post(c, frame(i), stream=robot).status_code == 200
        live = c.get("/v1/maps/default/memory").json()["streams"]
        crash(c)  # no shutdown snapshot: the restart replays every row, of all four streams
    with make_client(data, max_streams=2, stream_keep_seconds=0) as c:
        assert c.get("/v1/maps/default").json()["streams"] == ["c", "d"]
        mem = c.get("/v1/maps/default/memory").json()["streams"]
        rt = c.app.state.registry.get("default")
        conditions = sum(s.condition.state().nbytes for s in rt.streams.values())
    assert mem["count"] == 2 and conditions > 0 and mem["bytes"] > conditions
    assert live["count"] == 2 and live["bytes"] > conditions


def test_streams_over_a_lowered_cap_at_a_restart_are_counted_and_said(tmp_path, caplog):
    """Found by an outside tester: lowering CORTEXLOC_MAX_STREAMS dropped the least recently used learning
    streams at the restart (their contexts reset) with no eviction counted and nothing in the log."""
    data = tmp_path / "data"
    with make_client(data, max_streams=4, stream_keep_seconds=0) as c:
        for i, robot in enumerate(("a", "b", "c", "d")):
            assert post(c, frame(i), stream=robot).status_code == 200
    caplog.clear()
    with make_client(data, max_streams=2, stream_keep_seconds=0) as c:
        assert c.get("/v1/maps/default").json()["streams"] == ["c", "d"]
        assert evictions(c) == 2
    said = [r.getMessage() for r in caplog.records if "CORTEXLOC_MAX_STREAMS=2" in r.getMessage()]
    assert len(said) == 1 and "2 least recently used" in said[0]


def test_streams_over_a_lowered_cap_after_a_tail_served_while_it_replays_are_counted_once(tmp_path, caplog,
                                                                                         monkeypatch):
    """Found in review: a tail long enough to be served while it replays capped the served copies of the
    streams and then the replayed ones again, counting each eviction twice and saying it twice."""
    import service.maps.runtime.recovering as recovering
    from service.maps.runtime import MapRuntime

    monkeypatch.setattr(recovering, "TAIL_BEFORE_SERVING", 2)
    monkeypatch.setattr(MapRuntime, "replay_turn_steps", 1)
    data = tmp_path / "data"
    with make_client(data, max_streams=4, stream_keep_seconds=0, snapshot_every=0) as c:
        for i, robot in enumerate(("a", "b", "c", "d")):
            assert post(c, frame(i), stream=robot).status_code == 200
        assert c.post("/v1/maps/default/snapshots").status_code == 201
        for i, robot in enumerate(("a", "b", "c", "d", "a", "b")):  # the tail: 6 steps after it
            assert post(c, frame(10 + i), stream=robot).status_code == 200
    caplog.clear()
    with make_client(data, max_streams=2, stream_keep_seconds=0, snapshot_every=0) as c:
        for _ in range(6000):  # the tail replays while the map serves
            if c.get("/v1/maps/default").json()["state"] == "ready":
                break
            time.sleep(0.01)
        m = c.get("/v1/maps/default").json()
        assert m["state"] == "ready" and m["streams"] == ["a", "b"], m
        assert evictions(c) == 2
    said = [r.getMessage() for r in caplog.records if "CORTEXLOC_MAX_STREAMS=2" in r.getMessage()]
    assert len(said) == 1, said
