"""The encoder behind a bounded executor (service.md §6): encodings of different requests run
concurrently, a full queue answers 503 `overloaded` at once instead of letting latency grow."""

from __future__ import annotations

import threading
from concurrent.futures import Future, ThreadPoolExecutor

from models.encoder import Encoder, EncodeResult
from service.errors import Problem


class EncoderPool:
    """`submit(image bytes) -> Future[EncodeResult]` with at most `workers + queue` in flight."""

    def __init__(self, encoder: Encoder, workers: int, queue: int) -> None:
        self.encoder = encoder
        self.limit = workers + queue
        self._executor = ThreadPoolExecutor(workers, thread_name_prefix="encoder")
        self._lock = threading.Lock()
        self.pending = 0

    def submit(self, body: bytes) -> Future[EncodeResult]:
        with self._lock:
            if self.pending >= self.limit:
                raise Problem(503, "overloaded",
                              f"the encoder queue is full ({self.limit} requests in flight)",
                              headers={"Retry-After": "1"}, retry_after=1)
            self.pending += 1
        fut = self._executor.submit(self.encoder.embed, [body])
        fut.add_done_callback(self._done)
        return fut

    def _done(self, _: Future[EncodeResult]) -> None:
        with self._lock:
            self.pending -= 1

    def close(self) -> None:
        self._executor.shutdown(wait=True)
