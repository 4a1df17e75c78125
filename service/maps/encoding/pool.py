"""The encoder behind a bounded, batching executor (docs/design/service.md §6): the one place where
images are batched.

Concurrent requests are encoded together: a worker takes the first waiting image, gathers whatever
else arrives within a few milliseconds (up to `max_batch`), and runs one backbone call for all of
them, so throughput under load approaches the backbone's batch throughput. A full queue answers 503
`overloaded` at once instead of letting latency grow without bound.

Each image starts decoding when it is submitted (`Embedder.prepare`, in the encoder's decode threads),
not when its batch is taken: the next batch decodes while the backbone runs the current one, so the
forward never waits for a decode it could have overlapped. A bad image fails its own request alone.

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

import queue as queues
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np

from models.frontend.embedding import EncodeResult, Prepared
from models.frontend.images import ImageError, RawFrame
from models.frontend.slsbh import Hasher
from service.maps.encoding.embedders import Embedders
from service.maps.errors import Overloaded
from service.settings import Settings

_STOP = object()
# The defaults have one home, `Settings` (with why): a pool built in code batches as the service does.
_BATCH: int = Settings.model_fields["encode_batch"].default
_WAIT_MS: float = Settings.model_fields["encode_wait_ms"].default


class EmbeddingPool:
    """`submit(image bytes) -> Future[EncodeResult]` with at most `workers + queue` in flight.

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
        self._queue: queues.Queue = queues.Queue()
        self._lock = threading.Lock()
        self.pending = 0
        self._threads = [threading.Thread(target=self._run, name=f"encoder-{i}", daemon=True)
                         for i in range(workers)]
        for t in self._threads:
            t.start()

    def submit(self, body: bytes | RawFrame, hasher: Hasher | None = None, backbone: str | None = None,
               thumbnail: bool = False, resize: str | None = None) -> Future[EncodeResult]:
        """Queue one image (encoded bytes or a raw frame) for `backbone` (None: the default) resized by
        `resize` (None: the encoder's own mode); the future's
        `EncodeResult` has `features` (1, D), with `hasher` `projected` (1, k) = features · that hasher's
        projection (else None), and with `thumbnail` `thumbnails` = [a small JPEG of the decoded frame].

        Raises:
            Overloaded: `workers + queue` requests are already in flight.
        """
        with self._lock:
            if self.pending >= self.limit:
                raise Overloaded(self.limit)
            self.pending += 1
        fut: Future[EncodeResult] = Future()
        how = (backbone or self.encoders.default, resize)
        # The decode starts now where the encoder is built; one that is not yet is built, and the image
        # prepared, by the worker (never here: the caller is the event loop).
        try:
            encoder = self.encoders.ready(how[0])
            prepared = None if encoder is None else encoder.prepare(body, thumbnail=thumbnail, resize=resize)
        except BaseException:  # never queued: no worker will give the slot back
            with self._lock:
                self.pending -= 1
            raise
        self._queue.put(_Item(body, fut, hasher, thumbnail, how, prepared))
        return fut

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            batch = [item]
            deadline = time.monotonic() + self.wait_s
            while len(batch) < self.max_batch:
                remaining = deadline - time.monotonic()
                try:
                    nxt = self._queue.get(timeout=remaining) if remaining > 0 else self._queue.get_nowait()
                except queues.Empty:
                    break
                if nxt is _STOP:
                    self._queue.put(_STOP)  # let the other workers see it too
                    break
                batch.append(nxt)
            groups: dict[tuple[str, str | None], list[_Item]] = {}
            for one in batch:
                groups.setdefault(one.how, []).append(one)
            for (backbone, resize), group in groups.items():
                self._encode(backbone, resize, group)

    def _encode(self, backbone: str, resize: str | None, batch: list[_Item]) -> None:
        taken = len(batch)
        try:
            # A request whose client went away cancelled its future while it waited: its decode is
            # cancelled too where it has not started, and it costs no backbone time.
            live = []
            for item in batch:
                if item.fut.set_running_or_notify_cancel():
                    live.append(item)
                elif item.prepared is not None:
                    item.prepared.cancel()
            if not live:
                return
            try:
                encoder = self.encoders.get(backbone)
                ok, frames = [], []
                for item in live:
                    prepared = item.prepared or encoder.prepare(item.body, thumbnail=item.thumbnail,
                                                                resize=resize)
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
            with self._lock:
                self.pending -= taken

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
        self._queue.put(_STOP)
        for t in self._threads:
            t.join(timeout=30)


@dataclass
class _Item:
    """One submitted image: its body, its request's future, its map's hasher, whether it wants a
    thumbnail, (backbone, resize), and its decode, started at submission (None: by the worker)."""

    body: bytes | RawFrame
    fut: Future[EncodeResult]
    hasher: Hasher | None
    thumbnail: bool
    how: tuple[str, str | None]
    prepared: Future[Prepared] | None
