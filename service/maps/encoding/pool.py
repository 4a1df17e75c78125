"""The encoder behind a bounded, batching executor (docs/design/service.md §6): the one place where
images are batched.

Concurrent requests are encoded together: a worker takes the first decoded image, gathers whatever
else is decoded within a few milliseconds (up to `max_batch`), and runs one backbone call for all of
them, so throughput under load approaches the backbone's batch throughput. A full queue answers 503
`overloaded` at once instead of letting latency grow without bound; the slots are shared between maps
(`EmbeddingPool`).

Each image starts decoding when it is submitted (`Embedder.prepare`, in the encoder's decode threads),
not when its batch is taken: the next batch decodes while the backbone runs the current one, so the
forward never waits for a decode it could have overlapped, and a frame never waits for a batch-mate's
decode (a 25 MP PNG's decodes every pixel). A bad image fails its own request alone.

Batches are per backbone and resize mode: a request names its map's backbone and `resize` (crop |
squash, frozen with the map), and a batch holding several runs one backbone call per pair present
(`service.maps.encoding.embedders.Embedders` holds one encoder per backbone; the mode is a per-call
argument).

A request brings its map's sLSBH hasher (`MapRuntime.observe` passes it): the batch is then also
projected here (y = x·P), one matrix product per map present in the batch. A dense projection is
D x 1,024 float32 (21.4 MiB for the default `efficientnet-lite0-s5`, D = 5,488; an AlexNet map gets the
very sparse one, service/maps/projection.py) and the product is bound by reading it, so projecting
image by image in the map's writer would read the matrix once per image where a batch reads it once
(docs/scaling.md has the sizes and the command); in the writer it would also serialise behind the TM
step and the commit. The projection is stateless (a map's matrix never changes), so doing it before the writer
changes no ordering; what depends on the stream (adaptation, models.frontend.adaptation) and the top-n
selection of the code stay in the writer, on k values.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Hashable
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np

from models.frontend.embedding import EncodeResult, Prepared
from models.frontend.images import ImageError, RawFrame
from models.frontend.slsbh import Hasher
from service.maps.encoding.embedders import Embedders
from service.maps.errors import Overloaded
from service.settings import Settings

# The defaults have one home, `Settings` (with why): a pool built in code batches as the service does.
_BATCH: int = Settings.model_fields["encode_batch"].default
_WAIT_MS: float = Settings.model_fields["encode_wait_ms"].default


class EmbeddingPool:
    """`submit(image bytes) -> Future[EncodeResult]` with at most `workers + queue` in flight, shared
    fairly between the keys (the service's maps) that use it (docs/design/service.md §6):

    - a key may hold every slot while no other key wants one (nothing idles);
    - when the slots are full, a key holding fewer than its share (the slots over the keys holding
      any, its own counted) takes one back from the key holding the most above its share: that key's
      newest request not yet in a batch fails with `Overloaded` (a 503 with Retry-After, as if refused
      at once), its decode cancelled where it has not started;
    - the workers make each batch taking the keys in turn, and the decode threads take them in turn
      too (`models.frontend.turns`), so a request waits behind at most one of each other key's, not
      behind a burst.

    Args:
        encoders: the service's encoders by backbone (`embed` is called with a list of image bytes).
        workers: threads running backbone calls.
        queue: requests that may wait beyond those being encoded.
        max_batch: images per backbone call at most (CORTEXLOC_ENCODE_BATCH; default: its default).
        wait_ms: how long a worker waits for more images once it has one (CORTEXLOC_ENCODE_WAIT_MS).
    """

    def __init__(self, encoders: Embedders, workers: int, queue: int, max_batch: int = _BATCH,
                 wait_ms: float = _WAIT_MS) -> None:
        self.encoders = encoders
        self.limit = workers + queue
        self.max_batch = max_batch
        self.wait_s = wait_ms / 1e3
        self._ready = threading.Condition()
        # Admitted and in no batch yet, by key, oldest first: a slot is taken back from here.
        self._unbatched: dict[Hashable, deque[_Item]] = {}
        # Of those, the ones decoded (or to be prepared by the worker), by key; insertion-ordered: the
        # front key is served next, and a key served goes to the back while it has more (the turn). A
        # batch is made of decoded frames only: a frame never waits for its batch-mates' decodes.
        self._decoded: dict[Hashable, deque[_Item]] = {}
        self._held: dict[Hashable, int] = {}  # slots held by key: unbatched or in a batch
        self.pending = 0
        self._closed = False
        self._threads = [threading.Thread(target=self._run, name=f"encoder-{i}", daemon=True)
                         for i in range(workers)]
        for t in self._threads:
            t.start()

    def submit(self, body: bytes | RawFrame, hasher: Hasher | None = None, backbone: str | None = None,
               thumbnail: bool = False, resize: str | None = None, key: Hashable = None
               ) -> Future[EncodeResult]:
        """Queue one image (encoded bytes or a raw frame) for `backbone` (None: the default) resized by
        `resize` (None: the encoder's own mode), on behalf of `key` (the map; None: one key for all); the
        future's `EncodeResult` has `features` (1, D), with `hasher` `projected` (1, k) = features · that
        hasher's projection (else None), and with `thumbnail` `thumbnails` = [a small JPEG of the
        decoded frame]. The future may fail with `Overloaded` before its batch: its slot was taken back
        for a key holding less than its share.

        Raises:
            Overloaded: `workers + queue` requests are already in flight and `key` holds its share.
        """
        with self._ready:
            victim = self._take_back(key) if self.pending >= self.limit else None
            self.pending += 1
            self._held[key] = self._held.get(key, 0) + 1
        if victim is not None:
            _refuse(victim, self.limit)
        fut: Future[EncodeResult] = Future()
        how = (backbone or self.encoders.default, resize)
        # The decode starts now where the encoder is built; one that is not yet is built, and the image
        # prepared, by the worker (never here: the caller is the event loop).
        try:
            encoder = self.encoders.ready(how[0])
            prepared = None if encoder is None else encoder.prepare(body, thumbnail=thumbnail, resize=resize,
                                                                    key=key)
        except BaseException:  # never queued: no worker will give the slot back
            with self._ready:
                self._release(key)
            raise
        item = _Item(body, fut, hasher, thumbnail, how, prepared, key)
        # A request whose client went away (its future cancelled before its batch): slot given back now,
        # decode skipped where not begun.
        fut.add_done_callback(lambda f: f.cancelled() and self._abandoned(item))
        # A remote encoder's pending reply cannot say when it is done: its frame is ready for a batch now.
        when_done = getattr(prepared, "add_done_callback", None)
        with self._ready:
            self._unbatched.setdefault(key, deque()).append(item)
            if when_done is None:
                self._to_batch(item)
        if when_done is not None:  # outside the lock: a decode already done calls back at once
            when_done(lambda _: self._decoded_one(item))
        return fut

    def _abandoned(self, item: _Item) -> None:
        """A request cancelled before its batch leaves the queues, its slot given back at once."""
        with self._ready:
            if not self._withdraw(item):
                return  # in a batch already (it is skipped there), or taken back
            if self._closed and not self._unbatched:
                self._ready.notify_all()
        if item.prepared is not None:
            item.prepared.cancel()

    def _decoded_one(self, item: _Item) -> None:
        """A decode ended (or failed: its batch gives the request its error): the frame may be batched,
        unless it left the queues meanwhile (its slot taken back, or its client gone)."""
        with self._ready:
            if item in self._unbatched.get(item.key, ()):
                self._to_batch(item)

    def _to_batch(self, item: _Item) -> None:
        """(Lock held.)"""
        self._decoded.setdefault(item.key, deque()).append(item)
        self._ready.notify()

    def _take_back(self, key: Hashable) -> _Item:
        """(Lock held, every slot taken.) The newest unbatched request of the key holding the most slots
        above its share, its slot now `key`'s; `Overloaded` if `key` holds its share already or no key
        above its share has one unbatched."""
        holders = self._held.keys() | {key}
        share = max(self.limit // len(holders), 1)  # more maps than slots: one each, while any holds two
        if self._held.get(key, 0) < share:
            over = [k for k, q in self._unbatched.items() if k != key and q and self._held[k] > share]
            if over:
                heavy = max(over, key=self._held.__getitem__)
                victim = self._unbatched[heavy][-1]
                self._withdraw(victim)
                return victim
        raise Overloaded(self.limit)

    def _withdraw(self, item: _Item) -> bool:
        """(Lock held.) An unbatched request out of the queues, its slot given back and its decode's end
        batching nothing; False where it is in a batch already or withdrawn."""
        if not _remove(self._unbatched, item):
            return False
        _remove(self._decoded, item)
        self._release(item.key)
        return True

    def _release(self, key: Hashable) -> None:
        """(Lock held.) `key` gives back a slot."""
        self.pending -= 1
        left = self._held[key] - 1
        if left:
            self._held[key] = left
        else:
            del self._held[key]

    def _next_batch(self) -> list[_Item] | None:
        """The next batch: up to `max_batch` decoded requests taken key by key in turn, gathered for up
        to `wait_s` after the first; None once the pool is closed and nothing is left."""
        with self._ready:
            while not self._decoded:
                if self._closed and not self._unbatched:
                    return None
                self._ready.wait()
            batch = [self._pop_turn()]
            deadline = time.monotonic() + self.wait_s
            while len(batch) < self.max_batch:
                if self._decoded:
                    batch.append(self._pop_turn())
                    continue
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._closed:
                    break
                self._ready.wait(remaining)
            if self._closed and not self._unbatched:
                self._ready.notify_all()  # the last taken: the other workers may stop
            return batch

    def _pop_turn(self) -> _Item:
        """(Lock held, something decoded.) The oldest decoded request of the key whose turn it is, now in
        a batch."""
        key = next(iter(self._decoded))
        item = self._decoded[key][0]
        _remove(self._decoded, item)
        if key in self._decoded:  # more of this key: its next turn comes after the others'
            self._decoded[key] = self._decoded.pop(key)
        _remove(self._unbatched, item)
        return item

    def _run(self) -> None:
        while (batch := self._next_batch()) is not None:
            groups: dict[tuple[str, str | None], list[_Item]] = {}
            for one in batch:
                groups.setdefault(one.how, []).append(one)
            for (backbone, resize), group in groups.items():
                self._encode(backbone, resize, group)

    def _encode(self, backbone: str, resize: str | None, batch: list[_Item]) -> None:
        try:
            # A request whose client went away cancelled its future while it waited (and its decode
            # where that had not started, `submit`): it costs no backbone time.
            live = [item for item in batch if item.fut.set_running_or_notify_cancel()]
            if not live:
                return
            try:
                encoder = self.encoders.get(backbone)
                ok, frames = [], []
                for item in live:
                    prepared = item.prepared or encoder.prepare(item.body, thumbnail=item.thumbnail,
                                                                resize=resize, key=item.key)
                    try:
                        prepared.result()
                    except ImageError as e:  # this image alone fails; its batch-mates go on
                        item.fut.set_exception(e)
                        continue
                    ok.append(item)
                    frames.append(prepared)
                if not ok:
                    return
                out = encoder.embed_prepared(frames)
                projected, ms = self._project(out.features, [item.hasher for item in ok])
                for i, (item, prepared) in enumerate(zip(ok, frames, strict=True)):
                    frame = prepared.result()
                    item.fut.set_result(EncodeResult(
                        codes=None, features=out.features[i:i + 1], projected=projected[i],
                        timings_ms={**out.timings_ms, "project": ms},
                        thumbnails=[frame.thumbnail] if item.thumbnail else None,
                        contrast=out.contrast[i:i + 1] if out.contrast is not None else None))
            except Exception as e:
                for item in live:
                    if not item.fut.done():
                        item.fut.set_exception(e)
        finally:
            with self._ready:
                for item in batch:
                    self._release(item.key)

    @staticmethod
    def _project(features: np.ndarray, hashers: list[Hasher | None]
                 ) -> tuple[list[np.ndarray | None], float]:
        """Each row of `features` (N, D) times its own hasher's projection, one product per hasher.

        Returns:
            ([(1, k) float32 projections or None per row], milliseconds spent).
        """
        t0 = time.perf_counter()
        out: list[np.ndarray | None] = [None] * len(hashers)
        groups: dict[int, list[int]] = {}
        for i, h in enumerate(hashers):
            if h is not None:
                groups.setdefault(id(h), []).append(i)
        for rows in groups.values():
            hasher = hashers[rows[0]]
            assert hasher is not None
            Y = hasher.project(features[rows])  # (len(rows), k): the matrix is read once for the group
            for j, i in enumerate(rows):
                out[i] = Y[j:j + 1]
        return out, (time.perf_counter() - t0) * 1e3

    def close(self) -> None:
        """Stop the workers once what waits is encoded."""
        with self._ready:
            self._closed = True
            self._ready.notify_all()
        for t in self._threads:
            t.join(timeout=30)


@dataclass(eq=False)
class _Item:
    """One submitted image: its body, its request's future, its map's hasher, whether it wants a
    thumbnail, (backbone, resize), its decode, started at submission (None: by the worker), and its key."""

    body: bytes | RawFrame
    fut: Future[EncodeResult]
    hasher: Hasher | None
    thumbnail: bool
    how: tuple[str, str | None]
    prepared: Future[Prepared] | None
    key: Hashable


def _remove(queues: dict[Hashable, deque[_Item]], item: _Item) -> bool:
    """`item` out of its key's queue, the key dropped once its queue is empty; False where it is not
    there."""
    q = queues.get(item.key)
    if q is None or item not in q:
        return False
    q.remove(item)
    if not q:
        del queues[item.key]
    return True


def _refuse(item: _Item, limit: int) -> None:
    """A waiting request whose slot was taken back: it fails as a refusal at submission would, its
    decode cancelled where it has not started (never one its client already cancelled)."""
    if item.prepared is not None:
        item.prepared.cancel()
    if item.fut.set_running_or_notify_cancel():
        item.fut.set_exception(Overloaded(limit))
