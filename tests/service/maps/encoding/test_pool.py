"""Projecting in the encoder pool: projections computed per batch with each request's map hasher equal
projecting one image at a time, bad images still fail alone, and `MapRuntime.apply` stores exactly the
same rows from the pool's projections as from projections made image by image (benchmarks/bench_http.py
measured why the pool projects: docs/benchmarks.md §1)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future
from contextlib import contextmanager
from functools import partial

import numpy as np
import pytest

from models.frontend import images
from models.frontend.embedding import EncodeResult, Prepared
from models.frontend.images import ImageError
from models.frontend.slsbh import Hasher, make_projection
from models.frontend.turns import TurnPool
from service.maps.encoding.embedders import Embedders
from service.maps.encoding.pool import EmbeddingPool
from service.maps.errors import Overloaded
from tests.service.helpers import frame, held_encoder, make_client


class FakeEmbedder:
    """`embed` returns one fixed feature row per image (derived from its bytes); b"bad" fails.
    `prepare` + `embed_prepared` (what the pool calls) give the same rows."""

    def __init__(self) -> None:
        self.calls: list[int] = []
        self.modes: list[tuple[bytes, str | None]] = []  # each image with the mode it was embedded with

    def prepare(self, body, thumbnail=False, resize=None, key=None):
        fut = Future()
        if body == b"bad":
            fut.set_exception(ImageError("truncated", "the image data ends early"))
        else:
            fut.set_result(Prepared((body, resize), None, 1.0, 0.0, 0.0))
        return fut

    def embed_prepared(self, prepared):
        return self.embed([f.result().x[0] for f in prepared], resize=prepared[0].result().x[1])

    def embed(self, data, resize=None):
        self.calls.append(len(data))
        self.modes.extend((b, resize) for b in data)
        if any(b == b"bad" for b in data):
            raise ImageError("truncated", "the image data ends early")
        feats = np.stack([np.random.default_rng(len(b)).standard_normal(32).astype(np.float32)
                          for b in data])
        return EncodeResult(codes=None, features=feats, timings_ms={"decode": 0.0})


def test_pool_projects_each_request_with_its_own_hasher() -> None:
    h1 = Hasher(make_projection(32, 16, seed=1), 0.25)
    h2 = Hasher(make_projection(32, 16, seed=2), 0.25)
    enc = FakeEmbedder()
    pool = EmbeddingPool(Embedders.one(enc), workers=1, queue=64)
    try:
        bodies = [bytes(10 + i) for i in range(9)]
        hashers = [h1, h2, None] * 3
        with held_encoder(enc) as (gate, sizes):
            futs = [pool.submit(b, hasher=h) for b, h in zip(bodies, hashers, strict=True)]
            gate.set()  # the first image held the worker while the others queued
            results = [f.result(timeout=30) for f in futs]
        assert max(sizes) > 1  # the images queued behind the held one went together
        for b, h, r in zip(bodies, hashers, results, strict=True):
            feats = enc.embed([b]).features
            assert np.array_equal(r.features, feats)
            assert r.codes is None
            if h is None:
                assert r.projected is None
            else:
                assert r.projected.shape == (1, h.k)
                np.testing.assert_allclose(r.projected, h.project(feats), rtol=1e-5, atol=1e-6)
        # A bad image fails alone; its batch-mates still get their codes.
        futs = [pool.submit(b"bad", hasher=h1), pool.submit(bytes(5), hasher=h1)]
        with pytest.raises(ImageError):
            futs[0].result(timeout=30)
        ok = futs[1].result(timeout=30)
        np.testing.assert_allclose(ok.projected, h1.project(enc.embed([bytes(5)]).features), rtol=1e-5,
                                   atol=1e-6)
    finally:
        pool.close()


def test_a_bad_image_fails_alone_and_its_batch_mates_are_encoded_once() -> None:
    enc = FakeEmbedder()
    pool = EmbeddingPool(Embedders.one(enc), workers=1, queue=64)
    try:
        with held_encoder(enc) as (gate, sizes):
            first = pool.submit(bytes(3))
            deadline = time.monotonic() + 30
            while not sizes and time.monotonic() < deadline:  # the worker is in the backbone call
                time.sleep(0.01)
            bodies = [bytes(4), b"bad", bytes(6), bytes(7)]
            futs = [pool.submit(b) for b in bodies]
            gate.set()
            first.result(timeout=30)
            with pytest.raises(ImageError):
                futs[1].result(timeout=30)
            for b, f in zip(bodies, futs, strict=True):
                if b != b"bad":
                    np.testing.assert_array_equal(f.result(timeout=30).features, enc.embed([b]).features)
        assert enc.calls[:2] == [1, 3]  # one backbone call for the three good ones, none image by image
    finally:
        pool.close()


def test_an_image_decodes_while_the_backbone_runs_the_batch_before_it(tmp_path, monkeypatch) -> None:
    """Decoding starts when a request is submitted, not when the worker takes its batch: the frames
    that queue behind a running backbone call are decoded by the time it ends."""
    decoded: list[bytes] = []
    real = images.decode

    def decode(data, **kw):
        decoded.append(data)
        return real(data, **kw)

    monkeypatch.setattr(images, "decode", decode)
    with make_client(tmp_path) as c:
        pool, encoder = c.app.state.encoder_pool, c.app.state.encoder
        with held_encoder(encoder) as (gate, sizes):
            first = pool.submit(frame(0))
            deadline = time.monotonic() + 30
            while not sizes and time.monotonic() < deadline:  # the worker is in the backbone call
                time.sleep(0.01)
            mark, queued = len(decoded), [frame(p) for p in (1, 2, 3)]
            futs = [pool.submit(b) for b in queued]
            while len(decoded) < mark + 3 and time.monotonic() < deadline:
                time.sleep(0.01)
            assert sorted(decoded[mark:]) == sorted(queued) and sizes == [1]  # decoded, backbone held
            gate.set()
            first.result(timeout=60)
            for f in futs:
                assert f.result(timeout=60).features.shape[0] == 1
        assert sizes == [1, 3]


def test_pool_batches_per_backbone_and_builds_each_encoder_once() -> None:
    built: dict[str, FakeEmbedder] = {}

    def build(name: str) -> FakeEmbedder:
        assert name not in built  # at most one encoder per backbone
        built[name] = FakeEmbedder()
        return built[name]

    first = FakeEmbedder()
    encoders = Embedders(build, "alexnet", {"alexnet": first})
    pool = EmbeddingPool(encoders, workers=1, queue=64)
    try:
        with held_encoder(first) as (gate, _):
            futs = [pool.submit(bytes(10 + i), backbone=("alexnet", "efficientnet-lite0")[i % 2])
                    for i in range(6)]
            gate.set()
            for f in futs:
                f.result(timeout=30)
        other = built["efficientnet-lite0"]
        assert sum(first.calls) == 3 and sum(other.calls) == 3  # each image on its map's backbone only
        assert list(built) == ["efficientnet-lite0"] and encoders.get("efficientnet-lite0") is other
        with pytest.raises(ValueError, match="unknown backbone"):
            pool.submit(b"x", backbone="vgg").result(timeout=30)
    finally:
        pool.close()


def test_pool_encodes_each_image_with_its_maps_resize_mode() -> None:
    enc = FakeEmbedder()
    pool = EmbeddingPool(Embedders.one(enc), workers=1, queue=64)
    try:
        wanted = {bytes(10 + i): (None, "squash", "crop")[i % 3] for i in range(9)}
        with held_encoder(enc) as (gate, sizes):
            futs = [pool.submit(b, resize=mode) for b, mode in wanted.items()]
            gate.set()
            for f in futs:
                f.result(timeout=30)
        assert sorted(enc.modes, key=str) == sorted(wanted.items(), key=str)
        assert len(sizes) >= 3  # one backbone call per mode present at least
    finally:
        pool.close()


def test_the_pools_projections_store_the_same_as_projecting_image_by_image(tmp_path) -> None:
    frames = [frame(p % 5, noise=3.0 * (p // 5)) for p in range(12)]
    stored = []
    for mode in ("one by one", "pool"):
        with make_client(tmp_path / mode.replace(" ", "-")) as c:
            rt = c.app.state.registry.get("default")
            pool = c.app.state.encoder_pool
            encs = [pool.submit(b, hasher=rt.hasher if mode == "pool" else None) for b in frames]
            for i, e in enumerate(encs):
                r = e.result(timeout=60)
                projected = r.projected[0] if mode == "pool" else rt.hasher.project(r.features)[0]
                rt.submit(partial(rt.apply, projected, f"{i:064x}", learn=True, stream="s", top_k=3,
                                  label=None)).result(timeout=60)
            stored.append([(o.input_sdr.tolist(), o.winner_cells.tolist()) for o in rt.store.rows()])
            with pytest.raises(ValueError):  # another width is refused before any state change
                rt.submit(partial(rt.apply, np.zeros(3, np.float32), "0" * 64, learn=True, stream="s",
                                  top_k=0, label=None)).result(timeout=60)
            assert rt.store.count() == len(frames)
    assert stored[0] == stored[1]


def test_a_prepare_that_raises_gives_its_slot_back() -> None:
    """`prepare` raising at submission (a remote encoder whose send fails, a decoder refusing the
    input) never queues the item, so no worker frees its slot: the pool must, or each such failure
    takes a slot for good and the pool ends up refusing everything (a permanent 503)."""

    class Failing(FakeEmbedder):
        def prepare(self, body, thumbnail=False, resize=None, key=None):
            if body == b"boom":
                raise OSError(104, "Connection reset by peer")
            return super().prepare(body, thumbnail, resize)

    pool = EmbeddingPool(Embedders.one(Failing()), workers=1, queue=1)
    try:
        for _ in range(5):  # more failures than the pool has slots
            with pytest.raises(OSError, match="reset"):
                pool.submit(b"boom")
        assert pool.pending == 0
        assert pool.submit(bytes(3)).result(timeout=30).features.shape == (1, 32)
    finally:
        pool.close()


def test_the_pools_batch_and_wait_and_the_encoders_chunk_are_the_settings(tmp_path) -> None:
    """CORTEXLOC_ENCODE_BATCH, CORTEXLOC_ENCODE_WAIT_MS and CORTEXLOC_ENCODE_CHUNK reach the pool and the
    encoder the service builds (issue 38 item 3: before, 16 images, 2 ms and 4 were fixed); a pool built
    in code batches as the service's defaults say."""
    with make_client(tmp_path / "data", encode_batch=4, encode_wait_ms=0.5, encode_chunk=2) as c:
        pool = c.app.state.encoder_pool
        assert (pool.max_batch, pool.wait_s) == (4, 0.5 / 1e3)
        assert pool.encoders.get(pool.encoders.default).chunk == 2
    plain = EmbeddingPool(Embedders.one(FakeEmbedder()), workers=1, queue=1)
    try:
        assert (plain.max_batch, plain.wait_s) == (16, 2.0 / 1e3)
    finally:
        plain.close()


def _wait_until(cond, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


@contextmanager
def _busy(queue: int, max_batch: int = 16, first: bytes = bytes(10)
          ) -> Iterator[tuple[EmbeddingPool, FakeEmbedder, threading.Event, Future]]:
    """A pool of one worker and `queue` + 1 slots whose worker holds key a's `first` request in the
    backbone call until the gate opens: (pool, encoder, gate, first's future). Closed on the way out, so
    what follows the block sees every slot given back."""
    enc = FakeEmbedder()
    pool = EmbeddingPool(Embedders.one(enc), workers=1, queue=queue, max_batch=max_batch)
    try:
        with held_encoder(enc) as (gate, sizes):
            fut = pool.submit(first, key="a")
            _wait_until(lambda: sizes)
            yield pool, enc, gate, fut
    finally:
        pool.close()


def test_one_key_may_hold_every_slot_while_no_other_wants_one() -> None:
    with _busy(queue=5) as (pool, _, gate, first):  # 6 slots
        futs = [first] + [pool.submit(bytes(11 + i), key="a") for i in range(5)]
        with pytest.raises(Overloaded):  # its own seventh: no share to take back
            pool.submit(bytes(99), key="a")
        gate.set()
        assert all(f.result(timeout=30).features.shape == (1, 32) for f in futs)
    assert pool.pending == 0


def test_a_key_under_its_share_takes_a_slot_back_from_the_key_holding_the_most() -> None:
    """A client flooding one map fills the pool; another map's post is admitted, and the flood's newest
    waiting request fails with Overloaded (a 503 with Retry-After) instead: before, the other map got
    503 for as long as the flood lasted."""
    with _busy(queue=5) as (pool, _, gate, first):  # 6 slots, a share of 3 for two keys
        # the first is in the backbone call; the next five wait
        flood = [first] + [pool.submit(bytes(11 + i), key="a") for i in range(5)]
        other = [pool.submit(bytes(50 + i), key="b") for i in range(3)]
        with pytest.raises(Overloaded):  # b holds its share now, a no more than its own
            pool.submit(bytes(60), key="b")
        # a's three newest gave their slots back, newest first; its oldest (in the backbone) did not
        for f in flood[3:]:
            with pytest.raises(Overloaded):
                f.result(timeout=30)
        assert pool.pending == 6
        gate.set()
        for f in flood[:3] + other:
            assert f.result(timeout=30).features.shape == (1, 32)
    assert pool.pending == 0


def test_a_request_already_cancelled_is_not_taken_back_twice() -> None:
    with _busy(queue=1) as (pool, _, gate, first):  # 2 slots
        second = pool.submit(bytes(11), key="a")
        assert second.cancel()  # its client went away
        other = pool.submit(bytes(12), key="b")  # takes the cancelled one's slot back
        assert second.cancelled()
        gate.set()
        assert first.result(timeout=30).features.shape == (1, 32)
        assert other.result(timeout=30).features.shape == (1, 32)
    assert pool.pending == 0 and pool._held == {}  # each slot given back once, none twice


def test_batches_take_the_keys_in_turn() -> None:
    """A key's burst does not hold another key's request back behind it: the next batch takes one of
    each waiting key in turn before a second of any."""
    with _busy(queue=64, max_batch=2, first=bytes(5)) as (pool, enc, gate, _):
        flood = [pool.submit(bytes(10 + i), key="a") for i in range(6)]
        late = pool.submit(bytes(40), key="b")
        gate.set()
        late.result(timeout=30)
        for f in flood:
            f.result(timeout=30)
    # batches of 2: [first], then a's oldest with b's, then the rest of a's
    assert enc.calls[:2] == [1, 2]
    assert (bytes(10), None) in enc.modes[1:3] and (bytes(40), None) in enc.modes[1:3]


def test_the_pool_decodes_each_maps_frames_in_turn(tmp_path, monkeypatch) -> None:
    """Through the service's own encoder: with the decode threads held, a burst to one map and then one
    frame of another, the other map's frame decodes next but one, not after the burst."""
    order: list[bytes] = []
    real = images.decode
    held = threading.Event()

    def decode(data, **kw):
        if not order:
            held.wait(30)
        order.append(data)
        return real(data, **kw)

    monkeypatch.setattr(images, "decode", decode)
    with make_client(tmp_path, encoder_queue=64) as c:
        pool = c.app.state.encoder_pool
        burst = [frame(p) for p in range(6)]
        futs = [pool.submit(b, key="a") for b in burst]
        other = frame(9)
        futs.append(pool.submit(other, key="b"))
        held.set()
        for f in futs:
            f.result(timeout=60)
    threads = c.app.state.encoder.conf["decode_threads"]
    # behind the calls the threads held and at most one more of the burst's (its turn), not all six
    assert order.index(other) <= threads + 1 < len(burst)


def test_with_more_maps_than_slots_a_map_with_none_still_takes_one_from_a_map_with_two() -> None:
    with _busy(queue=2) as (pool, _, gate, first):  # 3 slots
        futs = [first, pool.submit(bytes(11), key="a"), pool.submit(bytes(12), key="b")]
        c = pool.submit(bytes(13), key="c")  # a holds 2: its waiting one is taken back
        with pytest.raises(Overloaded):
            futs[1].result(timeout=30)
        with pytest.raises(Overloaded):  # a, b and c hold one each now: none to take back
            pool.submit(bytes(14), key="d")
        gate.set()
        for f in (futs[0], futs[2], c):
            assert f.result(timeout=30).features.shape == (1, 32)


class HeldDecodes(FakeEmbedder):
    """Decodes in a real `TurnPool` that wait for `gate`: a request's decode can be queued or running
    when its slot is taken back or its client goes away."""

    def __init__(self, threads: int = 1) -> None:
        super().__init__()
        self.gate, self.decodes, self.decoded = threading.Event(), TurnPool(threads, "held"), []

    def prepare(self, body, thumbnail=False, resize=None, key=None):
        def run():
            self.gate.wait(30)
            self.decoded.append(body)
            return Prepared((body, resize), None, 1.0, 0.0, 0.0)

        return self.decodes.submit(run, key)


def _empty(pool: EmbeddingPool) -> bool:
    return pool.pending == 0 and pool._held == {} and pool._unbatched == {} and pool._decoded == {}


def test_a_request_taken_back_while_its_decode_is_queued_or_running_never_reaches_a_batch() -> None:
    """(From review.) Queued: the take-back cancels its decode, which never runs; running: its decode
    ends after the take-back and the frame is dropped. Every slot comes back once."""
    enc = HeldDecodes(threads=1)
    pool = EmbeddingPool(Embedders.one(enc), workers=1, queue=3)  # 4 slots
    try:
        a = [pool.submit(bytes(10 + i), key="a") for i in range(4)]
        _wait_until(lambda: enc.decodes.waiting() == {"a": 3})  # a0 decoding, a1-a3 queued
        b = [pool.submit(bytes(50 + i), key="b") for i in range(2)]  # takes back a3, then a2
        for f in a[2:]:
            with pytest.raises(Overloaded):
                f.result(timeout=5)
        enc.gate.set()
        for f in a[:2] + b:
            assert f.result(timeout=30).features.shape == (1, 32)
        assert sorted(enc.decoded) == [bytes(10), bytes(11), bytes(50), bytes(51)]  # a2, a3 never decoded
    finally:
        pool.close()
    assert _empty(pool)

    enc = HeldDecodes(threads=2)
    pool = EmbeddingPool(Embedders.one(enc), workers=1, queue=1)  # 2 slots
    try:
        a = [pool.submit(bytes(10 + i), key="a") for i in range(2)]
        _wait_until(lambda: enc.decodes.waiting() == {})  # both decoding, held
        b = pool.submit(bytes(50), key="b")  # takes a1 back while its decode runs
        with pytest.raises(Overloaded):
            a[1].result(timeout=5)
        enc.gate.set()
        assert a[0].result(timeout=30).features.shape == (1, 32)
        assert b.result(timeout=30).features.shape == (1, 32)
        assert sorted(b for b, _ in enc.modes) == [bytes(10), bytes(50)]  # a1 decoded, never encoded
    finally:
        pool.close()
    assert _empty(pool)


def test_a_cancelled_requests_decode_is_skipped_and_its_slot_comes_back() -> None:
    """(From review.) A client gone before its frame decoded costs no decode."""
    enc = HeldDecodes(threads=1)
    pool = EmbeddingPool(Embedders.one(enc), workers=1, queue=3)
    try:
        futs = [pool.submit(bytes(10 + i), key="a") for i in range(3)]
        _wait_until(lambda: enc.decodes.waiting() == {"a": 2})
        assert futs[2].cancel()
        enc.gate.set()
        for f in futs[:2]:
            assert f.result(timeout=30).features.shape == (1, 32)
        _wait_until(lambda: pool.pending == 0)
        assert sorted(enc.decoded) == [bytes(10), bytes(11)]
    finally:
        pool.close()
    assert _empty(pool)


def test_close_stops_every_worker_at_once_with_decodes_in_flight() -> None:
    """(From review.) Two workers, one decode in flight at close: the worker that batches it must wake
    the other, or close() waits 30 s for it."""
    enc = HeldDecodes(threads=1)
    pool = EmbeddingPool(Embedders.one(enc), workers=2, queue=2)
    fut = pool.submit(bytes(10), key="a")
    _wait_until(lambda: enc.decodes.waiting() == {})
    closing = threading.Thread(target=pool.close)
    closing.start()
    time.sleep(0.05)
    enc.gate.set()
    assert fut.result(timeout=30).features.shape == (1, 32)
    t0 = time.monotonic()
    closing.join(timeout=60)
    assert not closing.is_alive() and time.monotonic() - t0 < 10
    assert not any(t.is_alive() for t in pool._threads)
