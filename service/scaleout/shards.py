"""The ingress's view of the shards: the durable map -> shard table, forwarding, and moving a map
(docs/scaling.md; docs/design/service.md §9).

A map is served by exactly one shard, named by its row in `shards.sqlite` (storage.shardtable), never
by hashing: a map moves without rehashing the others. A shard whose replica died answers nothing
until Ray has started another on the same data directory; meanwhile its maps are `ShardUnavailable`
(503 `map-unavailable` + Retry-After), and a client's retry with the same Idempotency-Key is answered
by the restarted shard from its store (replayed when the first post was committed, learned once
otherwise).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import Counter, OrderedDict
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

from service.maps.errors import MapNotFound, ShardUnavailable
from service.scaleout.replicas import unavailable_errors
from service.scaleout.shard import ForwardedReply
from storage.shardtable import ShardRoute, ShardTable

__all__ = ["MoveFailed", "ShardSet"]

#: Creations whose shard did not answer remembered (the latest ones), so that a retry goes to that shard.
_UNSURE = 4096

log = logging.getLogger("cortexloc.scaleout")

#: `call(shard, method, *args)`: a shard deployment's method by its handle (or a test's stand-in).
ShardCall = Callable[..., Awaitable[Any]]


class MoveFailed(Exception):  # noqa: N818
    """A move that could not finish; the map stays served where it was."""


class ShardSet:
    """The shards behind one ingress.

    Args:
        shards: shard names, in order (`shard-0`, `shard-1`, ...).
        call: `call(shard, method, *args)` awaits a shard deployment's method.
        table_path: the map -> shard table's SQLite file (on the ingress's volume).
        call_timeout_s: a forwarded request not answered within it is a 503 (the client retries).
        down_s: how often a shard that did not answer is probed; its maps are answered 503 until it does.
    """

    def __init__(self, shards: list[str], call: ShardCall, table_path: Path, *,
                 call_timeout_s: float = 120.0, down_s: float = 1.0) -> None:
        self.shards = list(shards)
        self._call = call
        self.table = ShardTable(table_path)
        self.call_timeout_s = call_timeout_s
        self.down_s = down_s
        self._down: set[str] = set()
        self._probes: dict[str, asyncio.Task[None]] = {}
        self._in_flight: Counter[str] = Counter()
        self._create_lock = asyncio.Lock()
        # map id -> the shard a creation of it was sent to that did not answer: it may have made the map.
        self._unsure: OrderedDict[str, str] = OrderedDict()
        #: Every shard's maps are in the table (`reconcile` done): an unknown id is then a 404, not a 503.
        self.reconciled = False
        self._errors = unavailable_errors()

    # ------------------------------------------------------------------ table

    async def reconcile(self) -> None:
        """Route every map a shard holds that the table does not know (a fresh table, or maps made by a
        shard at its first start, as `default`) to the first shard holding it."""
        for shard in self.shards:
            for map_id in await self.call(shard, "map_ids"):
                if self.table.add_missing(map_id, shard):
                    log.info("map %s routed to %s (found there)", map_id, shard)
        self.reconciled = True

    def owner(self, map_id: str) -> ShardRoute:
        """Raises MapNotFound (no route), ShardUnavailable (moving, or its shard is down)."""
        route = self.table.get(map_id)
        if route is None:
            self.require_reconciled()
            raise MapNotFound(map_id)
        if route.state == "moving":
            raise ShardUnavailable(map_id, route.shard, "it is moving between shards")
        if route.shard in self._down:
            raise ShardUnavailable(map_id, route.shard, f"its shard {route.shard} is restarting")
        return route

    def require_reconciled(self) -> None:
        """Raises ShardUnavailable until every shard's maps are in the table (a map not yet read may
        exist: a list would miss it, a new map could take its id)."""
        if not self.reconciled:
            raise ShardUnavailable("*", "*", "the shards' maps are not read yet")

    def least_loaded(self) -> str:
        """The shard with the fewest maps in the table (new maps go there)."""
        counts = Counter(r.shard for r in self.table.all())
        return min(self.shards, key=lambda s: (counts[s], self.shards.index(s)))

    # ------------------------------------------------------------------ calls

    async def call(self, shard: str, method: str, *args: Any, map_id: str = "") -> Any:
        """A shard's method; ShardUnavailable when its replica does not answer (it is then marked down,
        so that the requests behind this one are answered at once)."""
        try:
            return await asyncio.wait_for(self._call(shard, method, *args), self.call_timeout_s)
        except self._errors as e:
            log.warning("shard %s did not answer %s: %s", shard, method, type(e).__name__)
            self._mark_down(shard)
            # handed to the shard: it may have done it before it died or while the call timed out
            raise ShardUnavailable(map_id or "*", shard, f"its shard {shard} is restarting",
                                   outcome_unknown=True) from e

    def _mark_down(self, shard: str) -> None:
        """Answer the shard's maps 503 at once until a probe finds its (restarted) replica serving: a call
        meanwhile would wait in Ray's queue for the new replica for as long as recovery takes."""
        self._down.add(shard)
        if shard not in self._probes:
            self._probes[shard] = asyncio.get_running_loop().create_task(self._probe(shard))

    async def _probe(self, shard: str) -> None:
        try:
            while True:
                await asyncio.sleep(self.down_s)
                with contextlib.suppress(*self._errors):
                    await asyncio.wait_for(self._call(shard, "map_ids"), self.down_s * 5)
                    log.info("shard %s answers again", shard)
                    self._down.discard(shard)
                    return
        finally:
            self._probes.pop(shard, None)

    @contextlib.asynccontextmanager
    async def _counted(self, map_id: str) -> AsyncIterator[None]:
        self._in_flight[map_id] += 1
        try:
            yield
        finally:
            self._in_flight[map_id] -= 1

    async def forward(self, map_id: str, method: str, path: str, query: str,
                      headers: list[tuple[str, str]], body: bytes) -> ForwardedReply:
        """A request about one map, to its owner. Raises MapNotFound, ShardUnavailable."""
        route = self.owner(map_id)
        async with self._counted(map_id):
            return await self.call(route.shard, "request", method, path, query, headers, body, map_id=map_id)

    async def create(self, map_id: str, path: str, query: str, headers: list[tuple[str, str]],
                     body: bytes) -> ForwardedReply:
        """`POST /v1/maps` on the least loaded shard; routed there once the shard created it. A map id
        already routed goes to its owner, which answers 409 `map-exists` (or, to the retry of a keyed
        creation, 200 with that map: docs/design/service.md §1.1).

        A creation whose shard did not answer may have made the map there before its reply was lost: a
        retry of that id goes to the same shard, never to another that would make a second map of the
        id, and is routed by its answer (201 made now; 200 the first try's; a 409 for a map the shard
        holds: made by the first try, retried without a key).
        """
        self.require_reconciled()
        async with self._create_lock:
            route = self.table.get(map_id)
            shard = route.shard if route is not None else self._unsure.get(map_id) or self.least_loaded()
            try:
                reply = await self.call(shard, "request", "POST", path, query, headers, body, map_id=map_id)
            except ShardUnavailable:
                if route is None:
                    self._unsure[map_id] = shard
                    self._unsure.move_to_end(map_id)
                    while len(self._unsure) > _UNSURE:
                        self._unsure.popitem(last=False)
                raise
            made = reply[0] in (200, 201)
            if route is None and reply[0] == 409 and map_id in self._unsure:
                made = map_id in await self.call(shard, "map_ids")  # by the first try; no key this time
            if route is None and made:
                self.table.set(map_id, shard)
                self._unsure.pop(map_id, None)
            return reply

    async def each(self, method: str, path: str, query: str, headers: list[tuple[str, str]]
                   ) -> dict[str, ForwardedReply | ShardUnavailable]:
        """The same request to every shard (lists, /metrics, /readyz): each reply or why there is none."""
        async def one(shard: str) -> ForwardedReply | ShardUnavailable:
            if shard in self._down:
                return ShardUnavailable("*", shard, f"shard {shard} is restarting")
            try:
                return await self.call(shard, "request", method, path, query, headers, b"")
            except ShardUnavailable as e:
                return e
        replies = await asyncio.gather(*(one(s) for s in self.shards))
        return dict(zip(self.shards, replies, strict=True))

    async def delete(self, map_id: str, path: str, query: str, headers: list[tuple[str, str]]
                     ) -> ForwardedReply:
        reply = await self.forward(map_id, "DELETE", path, query, headers, b"")
        # 404 from its owner: gone there already (a first try that deleted it and did not answer)
        if reply[0] == 204 or (reply[0] == 404 and _slug(reply) == "map-not-found"):
            self.table.delete(map_id)
        return reply

    # ------------------------------------------------------------------ moving a map

    async def move(self, map_id: str, target: str, headers: list[tuple[str, str]],
                   drain_timeout_s: float = 60.0) -> dict[str, Any]:
        """Move a map to `target`: drain (new requests get 503 + Retry-After; those in flight finish),
        snapshot on its owner, download, import on `target`, switch the table, delete the old copy.

        Args:
            headers: headers of the internal requests (the API key, when one is set).

        Returns:
            {map_id, from, to, snapshot_id, observations, seconds}.

        Raises:
            MapNotFound; MoveFailed (the map stays where it was, serving).
        """
        if target not in self.shards:
            raise MoveFailed(f"no shard {target!r}; shards: {', '.join(self.shards)}")
        route = self.table.get(map_id)
        if route is None:
            raise MapNotFound(map_id)
        if route.state == "moving":
            raise MoveFailed(f"map {map_id!r} is already moving")
        if route.shard == target:
            raise MoveFailed(f"map {map_id!r} is on {target} already")
        source, t0 = route.shard, time.monotonic()
        self.table.set(map_id, source, "moving")
        base = f"/v1/maps/{map_id}"
        imported = False
        try:
            deadline = time.monotonic() + drain_timeout_s
            while self._in_flight[map_id] > 0:
                if time.monotonic() > deadline:
                    raise MoveFailed(f"map {map_id!r}: requests still in flight after {drain_timeout_s} s")
                await asyncio.sleep(0.05)
            snap = await self._ok(source, "POST", f"{base}/snapshots", headers, 201)
            snapshot_id = _json(snap)["snapshot_id"]
            tar = (await self._ok(source, "GET", f"{base}/snapshots/{snapshot_id}/download", headers, 200))[2]
            await self.call(target, "import_tar", tar, map_id=map_id)
            imported = True
            self.table.set(map_id, target)
        except BaseException as e:
            if imported:  # the table still routes to the source: the copy on the target goes
                with contextlib.suppress(Exception):
                    await self.call(target, "request", "DELETE", base, "", headers, b"")
            self.table.set(map_id, source)
            if isinstance(e, MoveFailed | MapNotFound):
                raise
            raise MoveFailed(f"map {map_id!r} stays on {source}: {type(e).__name__}: {e}") from e
        info = _json(await self._ok(target, "GET", base, headers, 200))
        try:  # the map serves from the target already; a copy left behind is only disk
            await self._ok(source, "DELETE", base, headers, 204)
        except Exception as e:
            log.error("map %s moved to %s, but its old copy on %s stays: %s", map_id, target, source, e)
        return {"map_id": map_id, "from": source, "to": target, "snapshot_id": snapshot_id,
                "observations": info.get("observations"), "seconds": round(time.monotonic() - t0, 3)}

    async def _ok(self, shard: str, method: str, path: str, headers: list[tuple[str, str]],
                  status: int) -> ForwardedReply:
        reply = await self.call(shard, "request", method, path, "", headers, b"")
        if reply[0] != status:
            raise MoveFailed(f"{method} {path} on {shard}: HTTP {reply[0]} {reply[2][:300]!r}")
        return reply


def _json(reply: ForwardedReply) -> dict[str, Any]:
    import json

    return json.loads(reply[2])


def _slug(reply: ForwardedReply) -> str | None:
    """The problem slug of a shard's reply (`map-not-found`), None for a body that is no problem."""
    try:
        body = _json(reply)
    except ValueError:
        return None
    kind = body.get("type") if isinstance(body, dict) else None
    return kind.rsplit(":", 1)[-1] if isinstance(kind, str) else None
