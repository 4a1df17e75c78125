"""The decode threads: calls run in turn by key, not in the order they came (docs/design/service.md §6).

The service decodes each upload when its request arrives (`Embedder.prepare`), keyed by its map. With
one first-in first-out queue, a client that posts a burst of frames to one map, each at the size limit,
puts every other map's frame behind all of them: seconds of decoding on two threads. Here each key has
its own queue and the threads take the keys in turn, so a frame waits for at most one call per other
key that is waiting, however many that key has queued. With one key (one map, or a caller that names
none) the order is first in, first out, as before. Nothing idles: a thread takes any key's call while
one is waiting.
"""

from __future__ import annotations

import threading
import weakref
from collections import deque
from collections.abc import Callable, Hashable
from concurrent.futures import Future
from typing import Any

__all__ = ["TurnPool"]

_Call = tuple[Future, Callable[[], Any]]


class TurnPool:
    """`submit(fn, key) -> Future` run by `threads` daemon threads, the keys with calls waiting taken in
    turn (round robin), each key's calls in the order submitted. The threads start with the first call
    and end once the pool is garbage-collected and its calls are done (as a ThreadPoolExecutor's).

    Args:
        threads: how many calls run at once (>= 1).
        name: the threads' name prefix.
    """

    def __init__(self, threads: int, name: str) -> None:
        self._turns = _Turns()
        self._threads = [threading.Thread(target=self._turns.run, name=f"{name}-{i}", daemon=True)
                         for i in range(max(1, threads))]
        self._started = False
        # The threads hold the queues, never the pool: a pool dropped lets them end.
        weakref.finalize(self, self._turns.stop)

    def submit(self, fn: Callable[[], Any], key: Hashable = None) -> Future:
        """Queue `fn()` under `key`; its future holds the result or the exception. A future cancelled
        before a thread takes it never runs."""
        fut: Future = Future()
        if not self._turns.put(key, (fut, fn)):
            raise RuntimeError("cannot submit a call to a closed TurnPool")
        if not self._started:  # threads start with the first call: an encoder never asked costs none
            for t in self._threads:
                if not t.is_alive():
                    t.start()
            self._started = True
        return fut

    def waiting(self) -> dict[Hashable, int]:
        """Calls not yet taken, by key (for tests and diagnostics)."""
        return self._turns.waiting()

    def close(self) -> None:
        """Cancel the calls not yet taken and wait for those running; a later `submit` raises
        RuntimeError (as a ThreadPoolExecutor's `shutdown(cancel_futures=True)`)."""
        for fut, _ in self._turns.stop(cancel=True):
            fut.cancel()
        for t in self._threads:
            if t.is_alive():
                t.join()


class _Turns:
    """The queues by key and the loop the threads run (`TurnPool`)."""

    def __init__(self) -> None:
        self._ready = threading.Condition()
        # Insertion-ordered: the key at the front is the next one served, and a key served goes to the
        # back while it still has calls waiting (the turn).
        self._queues: dict[Hashable, deque[_Call]] = {}
        self._stopped = False
        self._closed = False

    def put(self, key: Hashable, call: _Call) -> bool:
        """Queue `call` under `key`; False (nothing queued) once stopped with its calls cancelled."""
        with self._ready:
            if self._closed:
                return False
            self._queues.setdefault(key, deque()).append(call)
            self._ready.notify()
            return True

    def stop(self, cancel: bool = False) -> list[_Call]:
        """Let the threads end once the queues are empty; with `cancel`, empty them first and take no
        more calls. Returns the calls taken out, for the caller to cancel."""
        with self._ready:
            self._stopped = True
            dropped: list[_Call] = []
            if cancel:
                self._closed = True
                for calls in self._queues.values():
                    dropped.extend(calls)
                self._queues.clear()
            self._ready.notify_all()
            return dropped

    def waiting(self) -> dict[Hashable, int]:
        with self._ready:
            return {k: len(q) for k, q in self._queues.items()}

    def _take(self) -> _Call | None:
        with self._ready:
            while not self._queues:
                if self._stopped:
                    return None
                self._ready.wait()
            key = next(iter(self._queues))
            calls = self._queues.pop(key)
            call = calls.popleft()
            if calls:
                self._queues[key] = calls
            return call

    def run(self) -> None:
        while (call := self._take()) is not None:
            fut, fn = call
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                fut.set_result(fn())
            except BaseException as e:  # the caller's to see, as a ThreadPoolExecutor's future holds it
                fut.set_exception(e)
            del call, fut, fn  # hold nothing of a done call while waiting for the next
