"""Group commit (service/maps/runtime/durability.py, docs/design/service.md §4.3): a learned row is
acknowledged only once an fsync that started after its commit returned; the rows committed meanwhile
share one fsync. The SIGKILL test of the deferred commits is tests/storage/test_mapstore.py
(test_group_commit_loses_nothing_acknowledged_at_a_sigkill)."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from service.maps.runtime.durability import GroupCommit
from tests.service.helpers import frame, make_client, post


def _until(cond, seconds: float = 30.0) -> bool:
    deadline = time.monotonic() + seconds
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.01)
    return cond()


def test_every_request_waiting_during_a_sync_shares_the_next_one() -> None:
    gate, calls = threading.Event(), []

    def sync() -> None:
        calls.append(1)
        gate.wait(30)

    commits = GroupCommit(sync, "sync-test")
    try:
        first = commits.durable()
        assert _until(lambda: len(calls) == 1)  # the first sync runs, held
        later = [commits.durable() for _ in range(5)]
        assert commits.waiting == 5 and not first.done() and not any(f.done() for f in later)
        gate.set()
        first.result(timeout=30)
        for f in later:
            f.result(timeout=30)
        assert len(calls) == 2 and commits.syncs == 2  # one fsync for the five that waited
    finally:
        gate.set()
        commits.close()
    # Asked after close (a map deleted while the request waited): the last sync covered its row.
    assert commits.durable().result(timeout=30) is None and len(calls) == 3


def test_a_failed_sync_acknowledges_none_of_its_group_and_close_serves_the_waiting() -> None:
    fail = [True]

    def sync() -> None:
        if fail[0]:
            raise OSError(5, "Input/output error")

    commits = GroupCommit(sync, "sync-test")
    with pytest.raises(OSError, match="Input/output"):
        commits.durable().result(timeout=30)
    fail[0] = False
    waiting = commits.durable()
    commits.close()
    assert waiting.result(timeout=30) is None


def test_a_learned_row_is_acknowledged_only_after_its_group_is_synced(tmp_path) -> None:
    with make_client(tmp_path / "d") as c:
        rt = c.app.state.registry.get("default")
        assert post(c, frame(0), stream="warm").status_code == 200  # every lazy start-up done
        gate, real, syncs = threading.Event(), rt.store.sync, rt._commits.syncs

        def held() -> None:
            gate.wait(30)
            real()

        rt.store.sync = held
        asked, durable = [], rt._commits.durable

        def counted():
            asked.append(1)
            return durable()

        rt._commits.durable = counted
        try:
            with ThreadPoolExecutor(6) as ex:
                futs = [ex.submit(post, c, frame(p), stream=f"s{p}") for p in range(1, 7)]
                # Every row is committed (visible, in the WAL) while the first fsync is held...
                assert _until(lambda: rt.store.count() == 7)
                # ...every request waits for its sync (those after the held one's group for the next)...
                assert _until(lambda: len(asked) == 6)
                time.sleep(0.2)
                assert not any(f.done() for f in futs)  # ...but none is acknowledged
                gate.set()
                replies = [f.result(timeout=60) for f in futs]
        finally:
            gate.set()
            rt.store.sync = real
            del rt._commits.durable
        assert [r.status_code for r in replies] == [200] * 6
        assert all(r.json()["timings_ms"]["sync"] >= 0 for r in replies)
        # the six rows needed two fsyncs (the held one's group, then every request waiting), not six; a
        # third where the warm-up's was still being counted when `syncs` was read
        assert rt._commits.syncs - syncs <= 3 < 6


def test_a_replayed_reply_waits_for_the_sync_of_its_row(tmp_path) -> None:
    """A retry (same Idempotency-Key) that finds the first post's row committed but not yet synced is
    answered only once that row is durable, like the first."""
    with make_client(tmp_path / "d") as c:
        rt = c.app.state.registry.get("default")
        assert post(c, frame(0), stream="warm").status_code == 200
        gate, real = threading.Event(), rt.store.sync

        def held() -> None:
            gate.wait(30)
            real()

        def keyed():
            return c.post("/v1/maps/default/observations", content=frame(1), params={"stream": "k"},
                          headers={"Content-Type": "image/png", "Idempotency-Key": "retry-0001"})

        rt.store.sync = held
        try:
            with ThreadPoolExecutor(2) as ex:
                first = ex.submit(keyed)
                assert _until(lambda: rt.store.count() == 2)  # committed, its sync held
                retry = ex.submit(keyed)
                time.sleep(0.5)
                assert not first.done() and not retry.done()
                gate.set()
                a, b = first.result(timeout=60), retry.result(timeout=60)
        finally:
            gate.set()
            rt.store.sync = real
        assert a.status_code == b.status_code == 200 and a.json()["seq"] == b.json()["seq"]
        assert rt.store.count() == 2  # learned once


def test_a_map_deleted_while_a_learned_row_waits_for_its_sync_answers_no_500(tmp_path) -> None:
    """A DELETE (or a shutdown) that lands between a learned row's commit and its request's wait for
    the sync closes the group commit under the request: the close's last sync covered the row, so the
    request is answered as if the delete came just after it (which it did), never a 500."""
    with make_client(tmp_path / "d") as c:
        assert c.post("/v1/maps", json={"map_id": "m"}).status_code == 201
        assert post(c, frame(0), map_id="m", stream="s").status_code == 200
        reg = c.app.state.registry
        rt = reg.get("m")
        real = rt._commits.durable

        def delete_first():
            reg.delete("m")  # the map goes after the writer committed the row, before the wait
            return real()

        rt._commits.durable = delete_first
        r = post(c, frame(1), map_id="m", stream="s")
        assert r.status_code == 200, r.text
        assert r.json()["seq"] > 0
        assert c.get("/v1/maps/m").status_code == 404
        # and the service goes on: a new map of the same name learns
        assert c.post("/v1/maps", json={"map_id": "m"}).status_code == 201
        assert post(c, frame(2), map_id="m", stream="s").status_code == 200
