"""The retraction follower: the node publishes each loop closure as the service answers it, and a back end
builds its pose graph from the topic; when an operator's repair withdraws closures (merges a stream made
from its own recent trail, the service README's "Repairing a map"), the service logs a retraction entry
per closure. This follower reads the map's loop-closure log every `retractions_poll` seconds, one page at
a time, on the poster's thread, and hands on each retraction of this node's stream's closures, so the
back end can drop the edge the closure's `id` names.

- It follows what is logged after its first read (the page's `newest`, read at its first poll, just after
  the node's first contact with the service); a retraction made before is in the service's exports.
- A failed read is said once and tried again at the next period; it never holds a frame back more than
  one request.
- A restore (the page's `epoch` changes) took away what came after its snapshot and undid the retractions
  made since, and a repair beyond what the log keeps withdrew closures it could not retract: neither can
  be published as edges, so it is said (rebuild from the export; `on_epoch`, which the node publishes) and
  the follower goes on from the log's newest id. Entries the log's cap pruned before they were read are said
  the same way.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Protocol

import httpx

from cortexloc_client import CortexlocError
from cortexloc_client.models import LoopClosure, LoopClosureList

__all__ = ["PAGE", "RetractionFollower"]

#: Log entries read per poll (the service's largest page).
PAGE = 500


class _Log(Protocol):
    def loop_closures(self, map_id: str, *, after: int = 0, limit: int = 100) -> LoopClosureList: ...


class RetractionFollower:
    """Follows `map_id`'s loop-closure log for the retractions of `stream`'s closures; `on_retraction(entry)`
    runs for each, and `on_epoch(previous, epoch)` when the log's epoch changes (both on the caller's
    thread). `every_s` 0: off."""

    def __init__(self, client: _Log, map_id: str, stream: str, every_s: float,
                 on_retraction: Callable[[LoopClosure], None], log: Any,
                 clock: Callable[[], float] = time.monotonic,
                 on_epoch: Callable[[str, str], None] = lambda previous, epoch: None) -> None:
        self.client, self.map_id, self.stream, self.every_s = client, map_id, stream, every_s
        self.on_retraction, self.on_epoch, self.log, self.clock = on_retraction, on_epoch, log, clock
        self.after: int | None = None  # the last log id read; None: not started
        self.epoch = ""
        self.published = 0
        self._next_at = 0.0
        self._failing = False
        self._off = every_s <= 0

    def due(self) -> bool:
        return not self._off and self.clock() >= self._next_at

    def poll(self) -> None:
        """One page after the cursor (the first poll reads where the log stands: `newest`)."""
        self._next_at = self.clock() + self.every_s
        try:
            page = self.client.loop_closures(self.map_id, after=self.after or 0, limit=1 if self.after is None
                                             else PAGE)
        except (CortexlocError, httpx.HTTPError) as e:
            if not self._failing:
                self.log.warning(f"reading the loop-closure log for retractions failed ({e}); tried again "
                                 f"every {self.every_s:g} s")
            self._failing = True
            return
        if self._failing:
            self.log.info("reading the loop-closure log for retractions again")
        self._failing = False
        if page.newest is None:  # a server before it: no way to start from now, so no following
            self._off = True
            self.log.warning("the service gives no `newest` log id (an older server): retractions are not "
                             "published; read them from the loop-closure export")
            return
        if self.after is None or page.epoch != self.epoch:
            if self.after is not None:
                self.on_epoch(self.epoch, page.epoch)
                self.log.warning(f"map {self.map_id!r} was restored (closures logged after its snapshot are "
                                 f"gone, the retractions made since undone) or repaired beyond what its log "
                                 f"keeps (closures withdrawn without a retraction): rebuild the graph from "
                                 f"the loop-closure export")
            self.after, self.epoch = page.newest, page.epoch
            return
        if page.missed(self.after):
            self.log.warning(f"the loop-closure log's cap pruned entries before they were read (after id "
                             f"{self.after}): edges they withdrew may stay; rebuild the graph from the "
                             f"loop-closure export")
        for entry in page.loop_closures:
            if entry.retracts is not None and entry.stream == self.stream:
                self.on_retraction(entry)
                self.published += 1
        self.after = page.cursor(self.after)
        if page.next_after is not None:  # a full page: the next one at the next turn, not a period later
            self._next_at = self.clock()
