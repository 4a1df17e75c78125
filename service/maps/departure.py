"""A client's departure, as the domain sees it (docs/design/service.md §6): an event the route sets when
the client goes away, on which the post's runtime hangs what to stop (its encoding, where not yet in a
batch), so an abandoned post costs no decode or backbone time and holds no encoder slot until its turn."""

from __future__ import annotations

import threading
from collections.abc import Callable

__all__ = ["Departure"]


class Departure(threading.Event):
    """A `threading.Event` that also runs the callbacks `when_set` registered, once, when it is set
    (at once for one registered after)."""

    def __init__(self) -> None:
        super().__init__()
        self._lock = threading.Lock()
        self._callbacks: list[Callable[[], object]] = []

    def set(self) -> None:
        super().set()
        with self._lock:
            callbacks, self._callbacks = self._callbacks, []
        for callback in callbacks:
            callback()

    def when_set(self, callback: Callable[[], object]) -> None:
        with self._lock:
            if not self.is_set():
                self._callbacks.append(callback)
                return
        callback()
