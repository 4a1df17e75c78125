"""Idempotency-Keys without HTTP (service/maps/runtime/idempotency.py): a repeated key answers the first
reply and steps nothing; another request under the same key is refused; a learned post's reply is in
its row's transaction, a localisation's in the bounded memory cache (docs/design/service.md §1.2)."""

from __future__ import annotations

import functools
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from service.maps.errors import IdempotencyKeyReused
from service.maps.runtime import idempotency
from storage.mapschema import KeyRecord
from tests.service.helpers import frame, make_client
from tests.service.helpers import post as post_frame
from tests.service.maps.maps_fixtures import registry, route


def post(key: str, body: str = "a") -> idempotency.IdempotentPost:
    return idempotency.IdempotentPost(key, idempotency.fingerprint(body, learn=True),
                                      seal=lambda r: f'{{"seq": {r.seq}}}')


def once(rt, p, features, learn=True):
    y = rt.hasher.project(features[None, :])[0]
    apply = functools.partial(rt.apply, y, "0" * 64, learn=learn, stream="s", top_k=1, label=None, post=p)
    return rt.submit(idempotency.apply_once, rt.store, rt.keys, p, learn, apply).result()


def test_a_repeated_key_is_answered_with_the_first_reply_and_learns_once(tmp_path):
    with registry(tmp_path) as reg:
        rt = reg.get("default")
        f = route(2)
        first = once(rt, post("key-00000001"), f[0])
        again = once(rt, post("key-00000001"), f[1])  # the same key: the first reply, nothing stepped
        assert (first.replayed, again.replayed) == (False, True) and again.body == first.body == '{"seq": 1}'
        assert rt.store.count() == 1
        with pytest.raises(IdempotencyKeyReused):
            once(rt, post("key-00000001", body="another image"), f[1])
    with registry(tmp_path) as reg:  # the learned reply is on disk with its row
        rt = reg.get("default")
        assert once(rt, post("key-00000001"), f[1]).replayed and rt.store.count() == 1


def test_a_localisations_reply_is_kept_in_memory_only():
    cache = idempotency.KeyCache(2)
    for i in range(3):
        cache.put(KeyRecord(f"key-{i:08d}", "fp", "{}"))
    assert cache.get("key-00000000") is None and cache.get("key-00000002") is not None  # bounded, LRU
    cache.clear()
    assert cache.get("key-00000002") is None


def test_keyed_posts_queued_behind_a_restore_learn_on_the_restored_store(tmp_path):
    """Found by an outside tester: a keyed post queued behind a restore was bound to the store the
    restore closes (503 naming maps/<id>/map.sqlite); it must read the store when it runs."""
    with make_client(tmp_path / "d", snapshot_every=0) as c:
        rt = c.app.state.registry.get("default")
        assert post_frame(c, frame(0)).status_code == 200
        sid = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        gate = threading.Event()
        rt.submit(gate.wait, 30)  # the writer held: what follows queues behind it
        try:
            restore = rt.submit(rt.restore, sid)
            with ThreadPoolExecutor(3) as ex:
                keyed = [ex.submit(c.post, "/v1/maps/default/observations", content=frame(i),
                                   params={"stream": f"k{i}"}, headers={"Content-Type": "image/png",
                                                                        "Idempotency-Key": f"queued-{i:04d}"})
                         for i in range(1, 4)]
                deadline = time.monotonic() + 30  # every post queued behind the restore
                while rt._writer._work_queue.qsize() < 4 and time.monotonic() < deadline:
                    time.sleep(0.01)
                assert rt._writer._work_queue.qsize() == 4
                gate.set()
                restore.result(timeout=60)
                replies = [f.result(timeout=60) for f in keyed]
        finally:
            gate.set()
        assert [r.status_code for r in replies] == [200] * 3, [r.text for r in replies]
        assert rt.store.count() == 4


def test_a_store_closed_under_a_request_names_no_file(tmp_path):
    with make_client(tmp_path / "d", snapshot_every=0) as c:
        assert post_frame(c, frame(0)).status_code == 200
        c.app.state.registry.get("default").store.close()  # as a restore does before the snapshot's opens
        r = c.get("/v1/maps/default/observations/1")
        assert r.status_code == 503 and "map.sqlite" not in r.json()["detail"]
        assert "/" not in r.json()["detail"].replace("/v1", "")


@pytest.mark.parametrize("keyed", [False, True])
def test_a_post_whose_row_a_restore_rolled_back_before_its_fsync_is_not_acknowledged(tmp_path, keyed):
    """Found by an outside probe: a learning post stepped before a restore but made durable after it was
    answered 200 with a seq the restore had discarded. It is 409 `map-restored` now, the map holds
    nothing of it, and posting it again (under the same key too: the restore forgot the keys) learns it."""
    with make_client(tmp_path / "d", snapshot_every=0) as c:
        rt = c.app.state.registry.get("default")
        assert post_frame(c, frame(0)).status_code == 200
        sid = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        syncing, gate, sync = threading.Event(), threading.Event(), rt._commits._sync

        def held() -> None:  # the group commit's fsync of the next row waits for the restore
            syncing.set()
            assert gate.wait(30)
            sync()

        headers = {"Content-Type": "image/png", **({"Idempotency-Key": "rolled-back-0001"} if keyed else {})}

        def send():
            return c.post("/v1/maps/default/observations", content=frame(1), params={"stream": "r"},
                          headers=headers)

        rt._commits._sync = held
        try:
            with ThreadPoolExecutor(1) as ex:
                posted = ex.submit(send)
                assert syncing.wait(30)  # its row is stepped and committed, not yet acknowledged
                rt._commits._sync = sync
                rt.submit(rt.restore, sid).result(timeout=60)  # the restore finishes first
                gate.set()
                r = posted.result(timeout=60)
        finally:
            rt._commits._sync = sync
            gate.set()
        assert r.status_code == 409, r.text
        assert r.json()["type"].endswith(":map-restored") and r.json()["map_id"] == "default"
        assert rt.store.count() == 1
        again = send()
        assert again.status_code == 200 and again.headers.get("Idempotent-Replayed") is None, again.text
        assert rt.store.count() == 2


def _hold_first_sync(rt) -> tuple[threading.Event, threading.Event]:
    """The map's next group-commit fsync waits for the returned gate; the first event says it began."""
    syncing, gate, sync = threading.Event(), threading.Event(), rt._commits._sync

    def held() -> None:
        rt._commits._sync = sync  # only this one is held
        syncing.set()
        assert gate.wait(30)
        sync()

    rt._commits._sync = held
    return syncing, gate


def test_a_retry_waiting_for_a_rolled_back_reply_learns_on_the_restored_map(tmp_path):
    """(From review.) A keyed post's retry found the stored reply before the restore and replayed it
    after: 200 naming a seq the restore discarded. It now looks again on the restored store and, not
    finding it there, learns the frame; the first post is then 409 (its reply is not the one stored)."""
    with make_client(tmp_path / "d", snapshot_every=0) as c:
        rt = c.app.state.registry.get("default")
        assert post_frame(c, frame(0)).status_code == 200
        sid = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]

        def send():
            return c.post("/v1/maps/default/observations", content=frame(1), params={"stream": "r"},
                          headers={"Content-Type": "image/png", "Idempotency-Key": "retry-of-a-post-01"})

        syncing, gate = _hold_first_sync(rt)
        try:
            with ThreadPoolExecutor(2) as ex:
                first = ex.submit(send)
                assert syncing.wait(30)  # its row is stepped and committed, its fsync held
                retry = ex.submit(send)  # the client's retry (a timeout, a lost connection)
                deadline = time.monotonic() + 30
                while rt._commits.waiting < 1:  # the retry found the reply and waits for its fsync
                    assert time.monotonic() < deadline
                    time.sleep(0.01)
                assert c.post(f"/v1/maps/default/snapshots/{sid}/restore").status_code == 200
                gate.set()
                r1, r2 = first.result(timeout=60), retry.result(timeout=60)
        finally:
            gate.set()
        assert r2.status_code == 200 and r2.headers.get("Idempotent-Replayed") is None, r2.text
        assert rt.store.observation_id(r2.json()["seq"]) == r2.json()["observation_id"]
        assert r1.status_code == 409 and r1.json()["type"].endswith(":map-restored"), r1.text
        assert rt.store.count() == 2
        again = send()  # the key now names the retry's row
        assert again.status_code == 200 and again.json()["seq"] == r2.json()["seq"]


@pytest.mark.parametrize("keyed", [False, True])
def test_a_restore_to_a_snapshot_that_holds_the_row_acknowledges_it(tmp_path, keyed):
    """(From review.) A snapshot taken after the row was stepped, before its fsync, holds it: restoring
    it keeps the row, and the post is 200, not 409 (posted again as told, it was learned twice)."""
    with make_client(tmp_path / "d", snapshot_every=0) as c:
        rt = c.app.state.registry.get("default")
        assert post_frame(c, frame(0)).status_code == 200
        headers = {"Content-Type": "image/png", **({"Idempotency-Key": "kept-by-restore1"} if keyed else {})}
        syncing, gate = _hold_first_sync(rt)
        try:
            with ThreadPoolExecutor(1) as ex:
                posted = ex.submit(c.post, "/v1/maps/default/observations", content=frame(1),
                                   params={"stream": "r"}, headers=headers)
                assert syncing.wait(30)
                sid = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]  # holds the row
                assert c.post(f"/v1/maps/default/snapshots/{sid}/restore").status_code == 200
                gate.set()
                r = posted.result(timeout=60)
        finally:
            gate.set()
        assert r.status_code == 200, r.text
        assert rt.store.count() == 2
        assert rt.store.observation_id(r.json()["seq"]) == r.json()["observation_id"]


def test_a_keyed_post_held_by_the_restored_map_is_acknowledged_after_its_key_was_pruned(tmp_path):
    """(From a second review.) The store keeps the newest `idempotency_keys` keys: another post learned on
    the restored map can prune this post's key before its check, though its row is held. It is found by
    its row then (200); a 409 made the client's resend with the same key learn the frame twice."""
    with make_client(tmp_path / "d", snapshot_every=0, idempotency_keys=1) as c:
        rt = c.app.state.registry.get("default")
        assert post_frame(c, frame(0)).status_code == 200

        def send(n: int, key: str):
            return c.post("/v1/maps/default/observations", content=frame(n), params={"stream": f"s{n}"},
                          headers={"Content-Type": "image/png", "Idempotency-Key": key})

        syncing, gate = _hold_first_sync(rt)
        try:
            with ThreadPoolExecutor(2) as ex:
                a = ex.submit(send, 1, "post-a-000001")
                assert syncing.wait(30)
                sid = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]  # holds a's row and key
                assert c.post(f"/v1/maps/default/snapshots/{sid}/restore").status_code == 200
                b = ex.submit(send, 2, "post-b-000001")  # learned on the restored map: a's key pruned
                deadline = time.monotonic() + 30
                while rt.store.count() < 3:
                    assert time.monotonic() < deadline
                    time.sleep(0.01)
                gate.set()
                ra, rb = a.result(timeout=60), b.result(timeout=60)
        finally:
            gate.set()
        assert rb.status_code == 200 and ra.status_code == 200, ra.text
        assert rt.store.observation_id(ra.json()["seq"]) == ra.json()["observation_id"]
        assert rt.store.count() == 3


def test_a_post_made_durable_while_a_restore_replaces_the_file_waits_for_it(tmp_path, monkeypatch):
    """(From a second review.) The restore's count was raised only once the snapshot's file was in place:
    a post whose fsync ended while the file was being replaced (its store closed) was answered 200 off
    the old count, its row discarded. The count is raised as the restore begins, and the check runs on
    the writer behind it."""
    from storage.mapstore import MapStore

    copying, release = threading.Event(), threading.Event()
    install = MapStore.install_copy

    def slow_install(src, dest):
        copying.set()
        assert release.wait(30)
        install(src, dest)

    with make_client(tmp_path / "d", snapshot_every=0) as c:
        rt = c.app.state.registry.get("default")
        assert post_frame(c, frame(0)).status_code == 200
        sid = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]  # before the post
        syncing, gate = _hold_first_sync(rt)
        monkeypatch.setattr(MapStore, "install_copy", staticmethod(slow_install))
        try:
            with ThreadPoolExecutor(2) as ex:
                posted = ex.submit(c.post, "/v1/maps/default/observations", content=frame(1),
                                   params={"stream": "r"}, headers={"Content-Type": "image/png"})
                assert syncing.wait(30)
                restore = ex.submit(c.post, f"/v1/maps/default/snapshots/{sid}/restore")
                assert copying.wait(30)  # the store closed, the snapshot's file going in
                gate.set()
                time.sleep(0.3)
                assert not posted.done()  # not answered off the old store
                release.set()
                r, rr = posted.result(timeout=60), restore.result(timeout=60)
        finally:
            gate.set()
            release.set()
        assert rr.status_code == 200 and r.status_code == 409, r.text
        assert rt.store.count() == 1
