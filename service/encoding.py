"""The encoder behind a bounded, batching executor (service.md §6).

Concurrent requests are encoded together: a worker takes the first waiting image, gathers whatever
else arrives within a few milliseconds (up to `max_batch`), and runs one backbone call for all of
them, so throughput under load approaches the backbone's batch throughput. A full queue answers 503
`overloaded` at once instead of letting latency grow without bound.
"""

from __future__ import annotations

import queue as queues
import threading
import time
from concurrent.futures import Future

from models.encoder import Encoder, EncodeResult
from models.images import ImageError
from service.errors import Problem

_STOP = object()


class EncoderPool:
    """`submit(image bytes) -> Future[EncodeResult]` with at most `workers + queue` in flight.

    Args:
        encoder: the service's encoder (`embed` is called with a list of image bytes).
        workers: threads running backbone calls.
        queue: requests that may wait beyond those being encoded.
        max_batch: images per backbone call at most.
        wait_ms: how long a worker waits for more images once it has one.
    """

    def __init__(self, encoder: Encoder, workers: int, queue: int, max_batch: int = 16,
                 wait_ms: float = 2.0) -> None:
        self.encoder = encoder
        self.limit = workers + queue
        self.max_batch = max_batch
        self.wait_s = wait_ms / 1e3
        self._queue: queues.Queue = queues.Queue()
        self._lock = threading.Lock()
        self.pending = 0
        self.batches: list[int] = []  # sizes of the recent backbone calls (tests, metrics)
        self._threads = [threading.Thread(target=self._run, name=f"encoder-{i}", daemon=True)
                         for i in range(workers)]
        for t in self._threads:
            t.start()

    def submit(self, body: bytes) -> Future[EncodeResult]:
        with self._lock:
            if self.pending >= self.limit:
                raise Problem(503, "overloaded",
                              f"the encoder queue is full ({self.limit} requests in flight)",
                              headers={"Retry-After": "1"}, retry_after=1)
            self.pending += 1
        fut: Future[EncodeResult] = Future()
        self._queue.put((body, fut))
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
            self._encode(batch)

    def _encode(self, batch: list[tuple[bytes, Future[EncodeResult]]]) -> None:
        try:
            try:
                out = self.encoder.embed([body for body, _ in batch])
                self.batches = [*self.batches[-99:], len(batch)]
                for i, (_, fut) in enumerate(batch):
                    fut.set_result(EncodeResult(codes=None, features=out.features[i:i + 1],
                                                timings_ms=dict(out.timings_ms)))
            except ImageError:
                # One bad image must not fail the others: encode each alone to attribute the error.
                for body, fut in batch:
                    try:
                        fut.set_result(self.encoder.embed([body]))
                    except Exception as e:
                        fut.set_exception(e)
            except Exception as e:
                for _, fut in batch:
                    if not fut.done():
                        fut.set_exception(e)
        finally:
            with self._lock:
                self.pending -= len(batch)

    def close(self) -> None:
        self._queue.put(_STOP)
        for t in self._threads:
            t.join(timeout=30)
