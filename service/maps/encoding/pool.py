"""The encoder behind a bounded, batching executor (docs/design/service.md §6): the one place where
images are batched.

Concurrent requests are encoded together: a worker takes the first waiting image, gathers whatever
else arrives within a few milliseconds (up to `max_batch`), and runs one backbone call for all of
them, so throughput under load approaches the backbone's batch throughput. A full queue answers 503
`overloaded` at once instead of letting latency grow without bound.

Batches are per backbone and resize mode: a request names its map's backbone and `resize` (crop |
squash, frozen with the map), and a batch holding several runs one backbone call per pair present
(`service.maps.encoding.encoders.Encoders` holds one encoder per backbone; the mode is a per-call
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

import numpy as np

from models.frontend.encoder import Encoder, EncodeResult
from models.frontend.images import ImageError, RawFrame
from models.frontend.slsbh import Hasher
from service.maps.encoding.encoders import Encoders
from service.maps.errors import Overloaded

_STOP = object()


class EncoderPool:
    """`submit(image bytes) -> Future[EncodeResult]` with at most `workers + queue` in flight.

    Args:
        encoders: the service's encoders by backbone (`embed` is called with a list of image bytes).
        workers: threads running backbone calls.
        queue: requests that may wait beyond those being encoded.
        max_batch: images per backbone call at most.
        wait_ms: how long a worker waits for more images once it has one.
    """

    def __init__(self, encoders: Encoders, workers: int, queue: int, max_batch: int = 16,
                 wait_ms: float = 2.0) -> None:
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
        self._queue.put((body, fut, hasher, thumbnail, (backbone or self.encoders.default, resize)))
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
            groups: dict[tuple[str, str | None],
                         list[tuple[bytes | RawFrame, Future[EncodeResult], Hasher | None, bool]]] = {}
            for body, fut, hasher, thumb, how in batch:
                groups.setdefault(how, []).append((body, fut, hasher, thumb))
            for (backbone, resize), group in groups.items():
                self._encode(backbone, resize, group)

    def _encode(self, backbone: str, resize: str | None,
                batch: list[tuple[bytes | RawFrame, Future[EncodeResult], Hasher | None, bool]]) -> None:
        taken = len(batch)
        # A request whose client went away cancelled its future while it waited: it costs no encoding.
        batch = [item for item in batch if item[1].set_running_or_notify_cancel()]
        try:
            if not batch:
                return
            try:
                encoder = self.encoders.get(backbone)
                out = _embed(encoder, [item[0] for item in batch], [item[3] for item in batch], resize)
                projected, ms = self._project(out.features, [item[2] for item in batch])
                for i, (_, fut, _, _) in enumerate(batch):
                    fut.set_result(EncodeResult(codes=None, features=out.features[i:i + 1],
                                                projected=projected[i],
                                                timings_ms={**out.timings_ms, "project": ms},
                                                thumbnails=out.thumbnails and out.thumbnails[i:i + 1],
                                                contrast=None if out.contrast is None
                                                else out.contrast[i:i + 1]))
            except ImageError:
                # One bad image must not fail the others: encode each alone to attribute the error.
                for body, fut, hasher, thumb in batch:
                    try:
                        one = _embed(encoder, [body], [thumb], resize)
                        projected, one.timings_ms["project"] = self._project(one.features, [hasher])
                        one.projected = projected[0]
                        fut.set_result(one)
                    except Exception as e:
                        fut.set_exception(e)
            except Exception as e:
                for _, fut, _, _ in batch:
                    if not fut.done():
                        fut.set_exception(e)
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


def _embed(encoder: Encoder, bodies: list[bytes | RawFrame], thumbs: list[bool],
           resize: str | None) -> EncodeResult:
    # Only maps that keep thumbnails ask for them; the others' batches are encoded as before.
    how = {"resize": resize} if resize is not None else {}
    return encoder.embed(bodies, thumbnails=thumbs, **how) if any(thumbs) else encoder.embed(bodies, **how)
