"""A crashed map answers localising frames from its snapshot while the rows after it replay, refuses what
learns with 503 + Retry-After meanwhile, then is the map it was; a crash during that replay recovers
(docs/design/service.md §4.4; issue 40, item 3)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

import service.maps.runtime.recovering as recovering
from service.maps.recovery import memory as recovery_memory
from service.maps.runtime import MapRuntime
from tests.service.helpers import frame, make_client, post, state_of

TAIL = 6  # rows learned after the snapshot


@pytest.fixture(autouse=True)
def short_tails(monkeypatch) -> None:
    """A tail of more than 2 steps replays while the map serves (the service's bound is larger), one
    step per turn of the writer."""
    monkeypatch.setattr(recovering, "TAIL_BEFORE_SERVING", 2)
    monkeypatch.setattr(MapRuntime, "replay_turn_steps", 1)


@contextmanager
def held_replay(turns: int = 0) -> Iterator[threading.Event]:
    """The tail's replay runs `turns` turns, then each turn does nothing until the gate opens (the
    writer keeps taking other work between turns)."""
    gate, left = threading.Event(), [turns]
    replay = getattr(recovery_memory, "Replay", None)  # None: a recovery that replays before serving
    if replay is None:
        yield gate
        return
    real = replay.run

    def run(self, steps=None):
        if steps is not None and not gate.is_set():
            if left[0] <= 0:
                time.sleep(0.002)
                return False
            left[0] -= 1
        return real(self, steps)

    replay.run = run
    try:
        yield gate
    finally:
        gate.set()
        replay.run = real


def map_with_a_tail(data) -> tuple[tuple, dict, list[dict]]:
    """A map whose last snapshot is TAIL rows behind, left as a kill -9 would leave it: (its state, a
    localising probe's reply, the replies of the tail's rows)."""
    with make_client(data, snapshot_every=0) as c:  # no automatic snapshot, none at shutdown
        for p in range(4):
            assert post(c, frame(p), stream="robot").status_code == 200
        assert c.post("/v1/maps/default/snapshots").status_code == 201
        tail = [post(c, frame(10 + p), stream="robot").json() for p in range(TAIL)]
        assert [r["seq"] for r in tail] == list(range(5, 5 + TAIL))
        before = state_of(c)
        probe = post(c, frame(12, noise=3.0), learn="false", stream="probe").json()
        # the probe stream is a localisation stream the snapshot does not hold: forget it as a crash would
    return before, probe, tail


def wait_ready(c, seconds: float = 60.0) -> dict:
    deadline = time.monotonic() + seconds
    while (m := c.get("/v1/maps/default").json())["state"] == "replaying" and time.monotonic() < deadline:
        time.sleep(0.01)
    return m


def test_a_map_with_a_tail_localises_while_it_replays_then_is_the_map_it_was(tmp_path):
    data = tmp_path / "data"
    before, probe, tail = map_with_a_tail(data)
    with held_replay() as gate, make_client(data, snapshot_every=0) as c:
        m = c.get("/v1/maps/default").json()
        assert m["state"] == "replaying", m
        assert m["recovery"]["tail"] == TAIL and m["recovery"]["replayed"] == 0
        # Localising: answered, from the snapshot's memory; the index already holds every stored row.
        r = post(c, frame(12, noise=3.0), learn="false", stream="probe")
        assert r.status_code == 200, r.text
        assert {x["seq"] for x in r.json()["matches"]} == {x["seq"] for x in probe["matches"]}
        # Learning (and a snapshot): 503 to retry later, nothing stored.
        r = post(c, frame(20), stream="robot")
        assert r.status_code == 503 and r.headers["content-type"] == "application/problem+json"
        body = r.json()
        assert body["type"].endswith(":map-unavailable") and body["state"] == "replaying"
        assert int(r.headers["Retry-After"]) >= 1 and body["retry_after"] == int(r.headers["Retry-After"])
        assert body["steps"] == TAIL
        assert c.post("/v1/maps/default/snapshots").status_code == 503
        ready = c.get("/readyz")
        assert ready.status_code == 200 and any("replaying" in w for w in ready.json()["warnings"])
        # Reads of stored rows are served.
        assert c.get(f"/v1/maps/default/observations/{tail[-1]['seq']}").status_code == 200
        assert c.app.state.registry.get("default").store.count() == before[0]
        gate.set()
        m = wait_ready(c)
        assert m["state"] == "ready", m
        rec = m["recovery"]
        assert rec["source"] == "snapshot" and rec["replayed"] == TAIL and rec["replayed_while_serving"]
        assert rec["skipped_snapshots"] == [] and rec["resumed_streams"] == 1
        assert state_of(c) == before  # every row replayed, the memory bit-identical
        nxt = post(c, frame(21), stream="robot")
        assert nxt.status_code == 200
        # the robot's sequence goes on where it was
        assert nxt.json()["sequence"]["step"] == tail[-1]["sequence"]["step"] + 1
        stored = c.app.state.registry.get("default").store.get(nxt.json()["seq"])
        assert stored.context_prev_seq == tail[-1]["seq"]
    verify_clean(data, 4 + TAIL + 1)


def test_a_crash_during_the_tail_replay_recovers(tmp_path):
    data = tmp_path / "data"
    before, _, _ = map_with_a_tail(data)
    with held_replay(turns=TAIL // 2), make_client(data, snapshot_every=0) as c:
        deadline = time.monotonic() + 30
        while c.get("/v1/maps/default").json()["recovery"]["replayed"] < TAIL // 2:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert post(c, frame(3), learn="false", stream="probe").status_code == 200
        # the block ends with the replay half done: closed as a kill -9 leaves it (nothing written)
    with make_client(data, snapshot_every=0) as c:
        m = wait_ready(c)
        assert m["state"] == "ready" and m["recovery"]["replayed"] == TAIL, m
        assert state_of(c) == before
    verify_clean(data, 4 + TAIL)


def verify_clean(data, rows: int) -> None:
    """`cortexloc verify`'s check: a replay from the first row reproduces every stored row."""
    catalog = recovery_memory.open_catalog(data)
    try:
        check = recovery_memory.verify_map(catalog, catalog.get_map("default"))
    finally:
        catalog.close()
    assert check.ok and check.rows == rows, check
