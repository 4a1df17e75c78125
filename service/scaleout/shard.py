"""One map shard: the single-process service (`service.app.create_app`, its routes, map runtime and
recovery, unchanged) on the shard's own data directory, answering requests that the ingress forwards
(docs/scaling.md; docs/design/service.md §9).

The app runs in process behind an ASGI transport: a forwarded request goes through the same
middleware, routes and error table as one sent to `cortexloc serve`; the encoder is the encoder
deployment, behind `RemoteEmbedder`. Ray Serve keeps exactly one replica of a shard (one owner, one
writer per map); when it dies, Ray starts another on the same data directory and the registry
recovers every map from it as at any start (§4.3).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from contextlib import AsyncExitStack
from pathlib import Path
from typing import Any

import anyio
import httpx

from service.app import create_app
from service.scaleout.embedding import RemoteEmbedder
from service.settings import Settings

__all__ = ["ForwardedReply", "ShardHost"]

#: (status, headers as (name, value) pairs, body).
ForwardedReply = tuple[int, list[tuple[str, str]], bytes]


class ShardHost:
    """The shard's app, started (`start`) and stopped (`stop`) around the replica's life.

    Args:
        settings: the service's settings with this shard's `data_dir`.
        encoder_info: backbone -> `EmbeddingService.info` (the deployment's answer).
        embed_call: `RemoteEmbedder`'s call into the encoder deployment.
    """

    def __init__(self, settings: Settings, encoder_info: Callable[[str], dict[str, Any]],
                 embed_call: Callable[..., Any]) -> None:
        def factory(s: Settings) -> RemoteEmbedder:
            assert s.backbone is not None  # resolved by the app before it builds an encoder
            return RemoteEmbedder(encoder_info(s.backbone), embed_call)

        self.settings = settings
        self.app = create_app(settings, encoder_factory=factory)
        self._stack = AsyncExitStack()
        self.client = httpx.AsyncClient(transport=httpx.ASGITransport(app=self.app),
                                        base_url="http://shard", timeout=None)

    async def start(self) -> None:
        """Run the app's startup: encoder info, then every map opened and recovered by replay."""
        await self._stack.enter_async_context(self.app.router.lifespan_context(self.app))

    async def stop(self) -> None:
        await self.client.aclose()
        await self._stack.aclose()

    async def request(self, method: str, path: str, query: str, headers: list[tuple[str, str]],
                      body: bytes) -> ForwardedReply:
        """One HTTP request through the app, answered whole."""
        # The query as it came (Starlette's str of the raw bytes): parsed and re-encoded, a non-UTF-8
        # escape would reach the shard's checks as U+FFFD (docs/design/service.md §2)
        r = await self.client.request(method, httpx.URL(path, query=query.encode("latin-1")), headers=headers,
                                      content=body)
        return r.status_code, list(r.headers.multi_items()), r.content

    def map_ids(self) -> list[str]:
        registry = getattr(self.app.state, "registry", None)
        return sorted(registry.maps) if registry is not None else []

    async def import_tar(self, tar: bytes) -> str:
        """Open a map from a snapshot tar (a move's receiving end); returns its id."""
        registry = self.app.state.registry
        data_dir = Path(self.settings.data_dir)
        fd, name = tempfile.mkstemp(prefix=".move-", suffix=".tar", dir=data_dir)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(tar)
            rt = await anyio.to_thread.run_sync(registry.import_live, Path(name),
                                                self.settings.max_import_bytes)
        finally:
            os.unlink(name)
        return rt.map_id
