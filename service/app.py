"""The app factory: `create_app(settings=None) -> FastAPI` (docs/design/service.md §1, §6, §8).

Nothing is read or built at import time. At startup the lifespan:

1. reads `Settings.from_env()` (unless settings were given), configures logging;
2. creates `CORTEXLOC_DATA_DIR` (a failure is reported by /readyz, not fatal);
3. builds the encoder in a worker thread (`app.state.encoder`, `app.state.encoder_weights`) and sets
   `cortexloc_encoder_info`; an unusable weights file stops startup with a `ConfigError`;
4. enters each component (async context managers taking the app, in order; left in reverse order at
   shutdown): the place for the map registry (`map_registry`), which fills `app.state.registry`,
   `app.state.maps` (map_id -> `MapRuntime`), `app.state.encoder_pool` and `app.state.extractions` (the
   keyframe extractions, `service.maps.keyframes.Extractions`), or `app.state.registry_error`
   when the maps cannot be opened (/readyz reports it).

`/docs` and `/redoc` load their assets from the service itself (`fastapi_offline`), never from a CDN.

Middleware, outermost first (all pure ASGI): `SecurityHeadersMiddleware` (nosniff, no framing, no
referrer; a Content-Security-Policy on pages), `RequestContextMiddleware` (request id, last-resort 500),
`MetricsMiddleware`, `UploadLimitMiddleware` (413 before routing). Errors are problem+json everywhere
(`service.errors`).

Example:
    >>> app = create_app()                       # reads CORTEXLOC_* when it starts
    >>> app = create_app(Settings(data_dir=tmp))  # tests: explicit settings
    $ uvicorn --factory service.app:create_app   # or `cortexloc serve`
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import AbstractAsyncContextManager, AsyncExitStack, asynccontextmanager
from importlib import metadata
from pathlib import Path
from typing import Any

import anyio
from fastapi import FastAPI
from fastapi_offline import FastAPIOffline

from service.errors import install_error_handlers, problem_responses
from service.frontend import EmbedderFactory, build_embedder, embedder_weights_info, resolve_backbone
from service.headers import SecurityHeadersMiddleware
from service.limits import UploadLimitMiddleware
from service.logs import configure_logging
from service.metrics import Metrics, MetricsMiddleware
from service.openapi import openapi_with_problems
from service.request_context import RequestContextMiddleware
from service.routes import api_router
from service.routing import HeadMiddleware
from service.settings import Settings
from service.ui import mount_viewer

__all__ = ["Component", "create_app", "map_registry"]

log = logging.getLogger("cortexloc.service")

#: A startup/shutdown step: `async with component(app): ...` around the app's life.
Component = Callable[[FastAPI], AbstractAsyncContextManager[Any]]


def _version() -> str:
    try:
        return metadata.version("cortexloc")
    except metadata.PackageNotFoundError:  # pragma: no cover - running from a bare checkout
        return "0.0.0"


# ------------------------------------------------------------------------------------------ app


def _prepare_data_dir(data_dir: Path) -> None:
    try:
        Path(data_dir).mkdir(parents=True, exist_ok=True)
    except OSError as e:
        log.error("cannot create CORTEXLOC_DATA_DIR %s: %s; the service will not be ready", data_dir, e)


@asynccontextmanager
async def map_registry(app: FastAPI) -> AsyncIterator[None]:
    """The maps of the data directory: opened and recovered by replay at start, closed at shutdown."""
    from service.maps.encoding.embedders import Embedders
    from service.maps.encoding.pool import EmbeddingPool
    from service.maps.errors import DataDirectoryInUse
    from service.maps.keyframes import Extractions
    from service.maps.registry import MapRegistry

    s = app.state.settings
    registry = None
    try:
        encoders = Embedders(lambda name: app.state.encoder_factory(s.model_copy(update={"backbone": name})),
                            s.backbone, {s.backbone: app.state.encoder})
        registry = await anyio.to_thread.run_sync(MapRegistry, s.data_dir, encoders, s)
        await anyio.to_thread.run_sync(registry.start)
    except DataDirectoryInUse as e:
        # Still held after `lock_wait_s`: this process exits (its supervisor, Ray or systemd, starts it
        # again), rather than stay up refusing every map for good. The message says it all.
        log.error("%s; exiting", e)
        raise
    except Exception as e:
        if registry is not None:  # the maps it opened, and the directory's lock, are let go
            with contextlib.suppress(Exception):
                await anyio.to_thread.run_sync(registry.close)
        # /readyz says why; the process stays alive for /healthz.
        log.exception("cannot open the maps in %s; the service will not be ready", s.data_dir)
        app.state.registry_error = f"the maps could not be opened: {type(e).__name__}: {e}"
        yield
        return
    app.state.registry = registry
    app.state.maps = registry.maps
    app.state.encoder_pool = EmbeddingPool(encoders, s.encoder_workers, s.encoder_queue, s.encode_batch,
                                         s.encode_wait_ms)
    app.state.extractions = Extractions(s.max_extractions)
    try:
        yield
    finally:
        await anyio.to_thread.run_sync(app.state.encoder_pool.close)
        await anyio.to_thread.run_sync(app.state.extractions.close)
        await anyio.to_thread.run_sync(registry.close)


def create_app(settings: Settings | None = None, *, encoder_factory: EmbedderFactory | None = None,
               components: Sequence[Component] = (map_registry,)) -> FastAPI:
    """Build the app; settings are read and the encoder built when it starts, not here.

    Args:
        settings: explicit settings; None: `Settings.from_env()` at startup.
        encoder_factory: builds the encoder from the settings (default `build_embedder`); runs in a thread.
        components: startup/shutdown steps entered in order after the encoder (e.g. the map runtime).

    Returns:
        The app. `app.state` after startup: `settings`, `metrics`, `encoder`, `encoder_weights`, `maps`
        (dict), and what the components add (`map_registry`: `registry`, `encoder_pool`).
    """
    metrics = Metrics()
    factory = encoder_factory or build_embedder

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        s = resolve_backbone(settings if settings is not None else Settings.from_env())
        configure_logging(s)
        app.state.settings = s
        app.state.maps = {}
        app.state.registry = app.state.registry_error = None
        app.state.encoder = None
        app.state.encoder_weights = None
        _prepare_data_dir(s.data_dir)
        cv2_pixels = os.environ.get("OPENCV_IO_MAX_IMAGE_PIXELS")
        if cv2_pixels is not None and cv2_pixels != str(s.max_pixels):
            log.warning("OpenCV's pixel guard is %s, CORTEXLOC_MAX_PIXELS is %d (the header check applies "
                        "the latter; `cortexloc serve` sets both)", cv2_pixels, s.max_pixels)
        encoder = await anyio.to_thread.run_sync(factory, s)
        app.state.encoder_weights = await anyio.to_thread.run_sync(embedder_weights_info, encoder)
        app.state.encoder = encoder
        desc = encoder.describe()
        metrics.set_encoder(weights=desc["weights"], encoder=desc["encoder"])
        log.info("encoder %s loaded (%s weights) on %s, %s", desc["encoder"], desc["weights"],
                 desc["runtime"], desc["device"])
        async with AsyncExitStack() as stack:
            for component in components:
                await stack.enter_async_context(component(app))
            log.info("cortexloc ready to serve on data dir %s", s.data_dir)
            yield
        log.info("cortexloc stopped")

    # /docs (Swagger UI 5, which reads OpenAPI 3.1) and /redoc with their scripts and styles served from
    # the package's files under /static-offline-docs, not a CDN: robot networks are often offline.
    app = FastAPIOffline(title="cortexloc", version=_version(), lifespan=lifespan,
                         description="Visual place recognition with a Hierarchical Temporal Memory.",
                         responses=problem_responses(500))
    app.state.metrics = metrics
    app.state.encoder_factory = factory
    if settings is not None:
        app.state.settings = settings
    install_edge(app, metrics)
    app.include_router(api_router)
    mount_viewer(app)  # the map viewer: static files, no API of its own
    app.openapi = openapi_with_problems(app)  # type: ignore[method-assign]
    return app


def install_edge(app: FastAPI, metrics: Metrics) -> None:
    """The edge every HTTP entry point of cortexloc has (this app, and the Ray Serve ingress): the
    problem+json handlers, then security headers, request ids, metrics, the upload limits and HEAD answered
    as GET, outermost first (docs/design/service.md §1.9, §2, §3, §9)."""
    install_error_handlers(app)
    # A path with a slash too many is a 404 problem, not a 307 to an absolute URL made from the request's
    # `Host` header (a client's word; a cache in front would keep it). `mount_viewer` redirects `/ui`.
    app.router.redirect_slashes = False
    # add_middleware puts each one outside the previous: the last added runs first.
    app.add_middleware(HeadMiddleware)
    app.add_middleware(UploadLimitMiddleware)
    app.add_middleware(MetricsMiddleware, metrics=metrics)
    app.add_middleware(RequestContextMiddleware)
    app.add_middleware(SecurityHeadersMiddleware)
