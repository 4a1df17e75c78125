"""Group commit: a map's learned rows acknowledged once durable, one fsync for all those committed
meanwhile (docs/design/service.md §4.3).

The map's writer commits each learned row without waiting for its fsync (`MapStore.append(durable=
False)`: the row is in the WAL, visible, and survives a crash of the process) and goes on with the next
frame; the request then waits on `GroupCommit.durable()`, which resolves after the next fsync of the
WAL that starts after the call, so it covers that row. The fsyncs run in this thread, one after the
other: every request that asks while one runs shares the next. A row is still acknowledged only when
durable; the writer no longer sits idle for each fsync (4-8 ms each on the development machine, against
0.4 ms of CPU for the commit itself: docs/benchmarks.md §10).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future


class GroupCommit:
    """`durable() -> Future[None]`, resolved by the first `sync()` that starts after the call.

    Args:
        sync: makes every commit made before it started durable (`MapStore.sync`); its exception is
            every waiting request's.
        name: the thread's name.
    """

    def __init__(self, sync: Callable[[], None], name: str) -> None:
        self._sync = sync
        self._cond = threading.Condition()
        self._waiting: list[Future[None]] = []
        self._closed = False
        # Resolved by the thread's last sync at `close`, which follows every commit (the writer is
        # drained first): what a request that asks after `close` waits for.
        self._final: Future[None] = Future()
        self.syncs = 0  # fsyncs run (each served every request waiting when it started)
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def waiting(self) -> int:
        """Requests waiting for the next sync."""
        with self._cond:
            return len(self._waiting)

    def durable(self) -> Future[None]:
        """A future resolved once every commit made before this call is durable.

        After `close` (a map deleted or the service stopping while a learned row's request waits), the
        future of the final sync that `close` runs after the writer is drained: it covers that row
        too, so the row is acknowledged as any other, never failed for a race it did not lose.
        """
        fut: Future[None] = Future()
        with self._cond:
            if self._closed:
                return self._final
            self._waiting.append(fut)
            self._cond.notify()
        return fut

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._waiting and not self._closed:
                    self._cond.wait()
                closing = self._closed
                group, self._waiting = self._waiting, []
            if closing:  # the last sync: it serves whoever asks from now on too
                group.append(self._final)
            try:
                self._sync()
            except BaseException as e:  # the rows' durability is unknown: none is acknowledged
                for fut in group:
                    fut.set_exception(e)
            else:
                for fut in group:
                    fut.set_result(None)
            self.syncs += 1
            if closing:
                return

    def close(self) -> None:
        """Run a last sync (it serves the requests already waiting and every later `durable()`), then
        stop (idempotent). The caller has stopped committing: the last sync covers every commit."""
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(timeout=60)
