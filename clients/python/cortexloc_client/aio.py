"""The asynchronous client: `cortexloc_client.Client`'s methods, same arguments and replies, as coroutines
(asyncio) over one `httpx.AsyncClient`.

Example:
    >>> async with AsyncClient("http://127.0.0.1:8000") as c:
    ...     await c.create_map("lab")
    ...     answer = await c.observe("lab", open("frame.jpg", "rb").read(), stream="robot1")
    ...     answer.matches[0].seq if answer.matches else None
"""

from __future__ import annotations

import os
from asyncio import sleep
from collections.abc import Mapping
from itertools import count
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar, cast

import httpx

from cortexloc_client import _core, models
from cortexloc_client._core import Call, RetryPolicy, Settings
from cortexloc_client.errors import InvalidResponseError
from cortexloc_client.frames import ColourOrder

if TYPE_CHECKING:
    import numpy as np

__all__ = ["AsyncClient"]

T = TypeVar("T")


class AsyncClient:
    """An asynchronous cortexloc client over one `httpx.AsyncClient` (asyncio; connections kept alive).

    Keywords as `Settings` (base URL, API key, timeout, retry policy, idempotency keys), plus `transport`:
    an httpx transport instead of the network (tests; `httpx.MockTransport`).
    """

    def __init__(self, base_url: str = Settings.base_url, *, api_key: str | None = None,
                 timeout: float = Settings.timeout, retry: RetryPolicy | None = None,
                 idempotency_keys: bool = True, transport: httpx.AsyncBaseTransport | None = None) -> None:
        self.settings = Settings(base_url.rstrip("/"), api_key, timeout, retry or RetryPolicy(),
                                 idempotency_keys)
        self._http = httpx.AsyncClient(base_url=self.settings.base_url, headers=self.settings.headers(),
                                  timeout=timeout, transport=transport)

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    # ------------------------------------------------------------------------------- sending

    async def _send(self, call: Call[T], *, stream: bool = False) -> T:
        """`call` sent, retried by the policy, its reply decoded (`stream`: the body left unread for
        `call.decode`, the download's, to stream)."""
        request = self._http.build_request(call.method, call.path, params=call.params, json=call.json,
                                           content=call.content, headers=call.headers)
        unsure = False  # an earlier try may have been done (`_core.may_have_done`)
        for attempt in count():
            try:
                response = await self._http.send(request, stream=stream)
            except httpx.TransportError as e:
                await sleep(self.settings.retry.wait(call, attempt, error=e))
                unsure = unsure or _core.may_have_done(error=e)
                continue
            if response.status_code < 400:
                try:
                    return call.decode(response)
                except InvalidResponseError as e:  # a proxy's page sent with 200: as a lost reply
                    await response.aclose()
                    await sleep(self.settings.retry.wait(call, attempt, error=e))
                    unsure = True
                    continue
            await response.aread()
            await response.aclose()
            if _core.done_already(call, response, unsure):
                return cast(T, None)  # a delete's: Call[None]
            await sleep(self.settings.retry.wait(call, attempt, response=response))
            unsure = unsure or _core.may_have_done(response=response)
        raise AssertionError("unreachable")

    # ---------------------------------------------------------------------------- operations

    async def health(self) -> models.Health:
        """`GET /healthz`."""
        return await self._send(_core.health())

    async def ready(self) -> models.Readiness:
        """`GET /readyz`; not retried. Raises `ServiceUnavailableError` (checks in `extra`) when not ready."""
        return await self._send(_core.ready())

    # ---------------------------------------------------------------------------------- maps

    async def create_map(self, map_id: str | None = None, *, preset: str | None = None,
                         seed: int | None = None, tm: Mapping[str, Any] | None = None,
                         slsbh: Mapping[str, Any] | None = None,
                         backbone: str | None = None, memory: str | None = None,
                         revisit_threshold: float | None = None, localiser: Mapping[str, Any] | None = None,
                         thumbnails: bool | None = None, resize: str | None = None,
                         keyframes: Mapping[str, Any] | None = None,
                         verify_revisit: bool | None = None,
                         idempotency_key: str | None = None) -> models.Map:
        """`POST /v1/maps`: as `Client.create_map`."""
        return await self._send(_core.create_map(
            self.settings, map_id, idempotency_key=idempotency_key, preset=preset, seed=seed, tm=tm,
            slsbh=slsbh,
            backbone=backbone, memory=memory, revisit_threshold=revisit_threshold, localiser=localiser,
            thumbnails=thumbnails, resize=resize, keyframes=keyframes, verify_revisit=verify_revisit))

    async def list_maps(self) -> list[models.Map]:
        return await self._send(_core.list_maps())

    async def get_map(self, map_id: str) -> models.Map:
        return await self._send(_core.get_map(map_id))

    async def update_map(self, map_id: str, *, revisit_threshold: float | None = None,
                         verify_revisit: bool | None = None) -> models.Map:
        """`PATCH /v1/maps/{map_id}`: as `Client.update_map`."""
        return await self._send(_core.update_map(map_id, revisit_threshold, verify_revisit))

    async def delete_map(self, map_id: str) -> None:
        """`DELETE /v1/maps/{map_id}`, with its observations and snapshots."""
        await self._send(_core.delete_map(map_id))

    async def memory(self, map_id: str) -> models.Memory:
        return await self._send(_core.memory(map_id))

    async def memory_budget(self) -> models.Budget:
        """The process-wide memory budget: total, used, free, each map's share."""
        return await self._send(_core.memory_budget())

    async def reset_stream(self, map_id: str, stream: str) -> models.StreamReset:
        """Break the stream's sequence: its next frame starts a new one."""
        return await self._send(_core.reset_stream(map_id, stream))

    # -------------------------------------------------------------------------- observations

    async def observe(self, map_id: str, image: bytes | np.ndarray, *, learn: bool = True, top_k: int = 5,
                stream: str = "default", label: str | None = None,
                metadata: models.Metadata | Mapping[str, Any] | None = None, colour: ColourOrder = "rgb8",
                idempotency_key: str | None = None) -> models.Observation:
        """`POST /v1/maps/{map_id}/observations`: see `Client.observe`."""
        return await self._send(_core.observe(self.settings, map_id, image, learn=learn, top_k=top_k,
                                        stream=stream, label=label, metadata=metadata, colour=colour,
                                        idempotency_key=idempotency_key))

    async def get_observation(self, map_id: str, seq: int) -> models.StoredObservation:
        """`GET /v1/maps/{map_id}/observations/{seq}`: a learned observation."""
        return await self._send(_core.get_observation(map_id, seq))

    async def list_observations(self, map_id: str, *, after_seq: int = 0,
                                limit: int = 100) -> models.StoredObservationList:
        """`GET /v1/maps/{map_id}/observations`: learned observations with seq > `after_seq`, in seq
        order, at most `limit` (<= 500); continue with `after_seq=page.next_after_seq`."""
        return await self._send(_core.list_observations(map_id, after_seq, limit))

    async def loop_closures(self, map_id: str, *, after: int = 0, limit: int = 100) -> models.LoopClosureList:
        """`GET /v1/maps/{map_id}/loop-closures`: the revisits streams were told of, oldest first, after
        log id `after`, at most `limit` (<= 500); continue with `after=page.cursor(after)` (`next_after`
        is None when there is nothing more for now), and rebuild from the export when
        `page.missed(after)` (entries the log's cap pruned before they were read)."""
        return await self._send(_core.loop_closures(map_id, after, limit))

    async def repair(self, map_id: str, *, undo: bool = False) -> models.Repair:
        """`GET /v1/maps/{map_id}/repair` (undo False: what a repair would undo) or `POST` (undo True: undo
        it, durably): the merges a stream made from its own recent trail, and the loop closures that
        named them (retracted in the log). A POST whose answer was lost is sent again: the second finds
        nothing left to undo, so its lists are empty; the retractions are in `loop_closures`."""
        return await self._send(_core.repair(map_id, undo=undo))

    async def export_loop_closures(self, map_id: str, fmt: str = "csv") -> bytes:
        """`GET /v1/maps/{map_id}/loop-closures/export`: the whole log as candidate pairs (`csv` or
        `jsonl`): both stamps in seconds, both ids, the confidence, both poses where given."""
        return await self._send(_core.export_loop_closures(map_id, fmt))

    async def recent(self, map_id: str, *, limit: int = 50,
                     stream: str | None = None) -> models.RecentAnswers:
        """`GET /v1/maps/{map_id}/recent`: the map's last answers (at most `limit`, of one `stream` if
        given), oldest first; the service keeps them in memory only."""
        return await self._send(_core.recent(map_id, limit, stream))

    async def thumbnail(self, map_id: str, seq: int) -> bytes:
        """`GET /v1/maps/{map_id}/observations/{seq}/thumbnail`: the stored JPEG thumbnail."""
        return await self._send(_core.thumbnail(map_id, seq))

    async def recent_thumbnail(self, map_id: str, answer_id: int) -> bytes:
        """`GET /v1/maps/{map_id}/recent/{answer_id}/thumbnail`: see `Client.recent_thumbnail`."""
        return await self._send(_core.recent_thumbnail(map_id, answer_id))

    # ----------------------------------------------------------------------------- snapshots

    async def create_snapshot(self, map_id: str) -> models.Snapshot:
        return await self._send(_core.create_snapshot(map_id))

    async def list_snapshots(self, map_id: str) -> list[models.Snapshot]:
        """Newest first."""
        return await self._send(_core.list_snapshots(map_id))

    async def restore_snapshot(self, map_id: str, snapshot_id: str) -> models.RestoredMap:
        """Roll the map back (the present is kept in a `pre-restore` snapshot first)."""
        return await self._send(_core.restore_snapshot(map_id, snapshot_id))

    async def delete_snapshot(self, map_id: str, snapshot_id: str) -> None:
        """Delete one snapshot (not the one the map recovers from: 409 snapshot-in-use)."""
        await self._send(_core.delete_snapshot(map_id, snapshot_id))

    async def download_snapshot(self, map_id: str, snapshot_id: str, dest: str | os.PathLike[str]) -> Path:
        """Stream the snapshot's tar into `dest` (through `dest.part`, moved into place when complete).

        Returns:
            `dest` as a Path.
        """
        path, part = _core.part_path(dest)
        response = await self._send(_core.download_snapshot(map_id, snapshot_id), stream=True)
        written = 0
        try:
            with part.open("wb") as f:
                async for chunk in response.aiter_bytes():
                    written += f.write(chunk)
        except BaseException:
            part.unlink(missing_ok=True)
            raise
        finally:
            await response.aclose()
        return _core.finish_download(response, written, path, part)
