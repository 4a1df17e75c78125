"""Idempotency-Keys without HTTP (service/maps/runtime/idempotency.py): a repeated key answers the first
reply and steps nothing; another request under the same key is refused; a learned post's reply is in
its row's transaction, a localisation's in the bounded memory cache (docs/design/service.md §1.2)."""

from __future__ import annotations

import functools

import pytest

from service.maps.errors import IdempotencyKeyReused
from service.maps.runtime import idempotency
from storage.mapschema import KeyRecord
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
