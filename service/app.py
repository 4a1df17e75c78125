"""The app factory: `create_app(settings=None) -> FastAPI` (docs/design/service.md §1, §6, §8).

Nothing is read or built at import time. At startup the lifespan:

1. reads `Settings.from_env()` (unless settings were given), configures logging;
2. creates `CORTEXLOC_DATA_DIR` (a failure is reported by /readyz, not fatal);
3. builds the encoder in a worker thread (`app.state.encoder`, `app.state.encoder_weights`) and sets
   `cortexloc_encoder_info`; an unusable weights file stops startup with a `ConfigError`;
4. enters each component (async context managers taking the app, in order; left in reverse order at
   shutdown): the place for the map registry (`map_registry`), which fills `app.state.registry`,
   `app.state.maps` (map_id -> `MapRuntime`) and `app.state.encoder_pool`, or `app.state.registry_error`
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

import json
import logging
import os
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import AbstractAsyncContextManager, AsyncExitStack, asynccontextmanager
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

import anyio
from fastapi import FastAPI
from fastapi_offline import FastAPIOffline

from models.frontend.encoder import Encoder
from service.errors import RequestContextMiddleware, install_error_handlers, problem_responses, request_id_var
from service.headers import SecurityHeadersMiddleware
from service.limits import UploadLimitMiddleware
from service.metrics import Metrics, MetricsMiddleware
from service.routes import api_router
from service.settings import ConfigError, Settings
from service.ui import UI_PATH, static_files

__all__ = ["Component", "EncoderFactory", "build_encoder", "configure_logging", "create_app",
           "encoder_weights_info"]

log = logging.getLogger("cortexloc.service")

EncoderFactory = Callable[[Settings], Encoder]
#: A startup/shutdown step: `async with component(app): ...` around the app's life.
Component = Callable[[FastAPI], AbstractAsyncContextManager[Any]]


def _version() -> str:
    try:
        return metadata.version("cortexloc")
    except metadata.PackageNotFoundError:  # pragma: no cover - running from a bare checkout
        return "0.0.0"


# -------------------------------------------------------------------------------------- logging


class _RequestIdFilter(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        record.request_id = request_id_var.get() or "-"
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per line: ts, level, logger, message, request_id, exc."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "ts": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname, "logger": record.name, "message": record.getMessage()}
        rid = getattr(record, "request_id", "-")
        if rid != "-":
            out["request_id"] = rid
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


def configure_logging(settings: Settings) -> None:
    """One stderr handler on the `cortexloc` logger with the configured level and format (idempotent)."""
    logger = logging.getLogger("cortexloc")
    for h in list(logger.handlers):
        if getattr(h, "_cortexloc", False):
            logger.removeHandler(h)
    handler = logging.StreamHandler()
    handler._cortexloc = True  # type: ignore[attr-defined]
    handler.addFilter(_RequestIdFilter())
    if settings.log_format == "json":
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(
            logging.Formatter("%(asctime)s %(levelname)s %(name)s [%(request_id)s] %(message)s"))
    logger.addHandler(handler)
    logger.setLevel(settings.log_level)


# -------------------------------------------------------------------------------------- encoder


def build_encoder(settings: Settings, **overrides: Any) -> Encoder:
    """The encoder of `settings.backbone` (resolved at startup; AlexNet conv3 with the configured weights
    and seed, or EfficientNet-Lite0 with its package's), threads and input limits.

    Args:
        settings: the settings.
        **overrides: `models.frontend.encoder.default_conf` keys merged last (tests: `slsbh={"k": 16}`).

    Raises:
        ConfigError: naming CORTEXLOC_WEIGHTS_PATH when the weights cannot be used.
    """
    from models.frontend import weights
    from models.frontend.runtimes import DeviceUnavailableError

    try:
        path = settings.weights_path if settings.weights_path is not None else weights.find_alexnet()
        if path is None and not settings.allow_random_weights:
            log.error("no AlexNet weights: CORTEXLOC_WEIGHTS_PATH is unset, none are installed, and "
                      "CORTEXLOC_ALLOW_RANDOM_WEIGHTS=false; the service will not be ready")
        conf = {"backbone": resolve_backbone(settings).backbone,
                "weights_path": str(path) if path is not None else None,
                "random_seed": settings.random_weights_seed, "torch_threads": settings.torch_threads,
                "max_bytes": settings.max_upload_bytes, "max_pixels": settings.max_pixels,
                "runtime": settings.runtime, "device": settings.device, **overrides}
        return Encoder(conf)
    except DeviceUnavailableError as e:
        raise ConfigError([("CORTEXLOC_DEVICE", f"={settings.device!r}: {e}")]) from e
    except weights.WeightsError as e:
        shown = f"={str(settings.weights_path)!r}" if settings.weights_path is not None else " (unset)"
        raise ConfigError([("CORTEXLOC_WEIGHTS_PATH", f"{shown}: {e}")]) from e


def resolve_backbone(settings: Settings) -> Settings:
    """The settings with `backbone` resolved once: the configured one, else AlexNet when its real
    weights are installed (CORTEXLOC_WEIGHTS_PATH or the cache), else `efficientnet-lite0-s5`
    (`service.maps.encoders.default_backbone`)."""
    from models.frontend import weights
    from service.maps.encoders import default_backbone

    if settings.backbone is not None:
        return settings
    installed = settings.weights_path is not None or weights.find_alexnet() is not None
    return settings.model_copy(update={"backbone": default_backbone(None, installed)})


def encoder_weights_info(encoder: Encoder) -> dict[str, Any]:
    """What /readyz reports about the weights: `weights_id`, and the file's SHA-256 (or the seed)."""
    from common.files import sha256_file
    from models.frontend import weights

    info: dict[str, Any] = {"weights_id": encoder.weights_id}
    if encoder.weights_id.startswith("random"):
        info["seed"] = int(encoder.conf["random_seed"])
        return info
    path = encoder.conf.get("weights_path") or weights.find_alexnet()
    if path is None:  # pragma: no cover - a non-AlexNet backbone
        return info
    info["path"] = str(path)
    meta = weights.read_sidecar(path)
    if meta is not None:
        info["sha256"] = meta["trimmed_sha256"]
        info["original_sha256"] = meta["original_sha256"]
    else:
        info["sha256"] = sha256_file(path)
    return info


# ------------------------------------------------------------------------------------------ app


def _prepare_data_dir(data_dir: Path) -> None:
    try:
        Path(data_dir).mkdir(parents=True, exist_ok=True)
    except OSError as e:
        log.error("cannot create CORTEXLOC_DATA_DIR %s: %s; the service will not be ready", data_dir, e)


def _openapi_with_problems(app: FastAPI) -> Callable[[], dict[str, Any]]:
    """FastAPI documents validation errors as 422 HTTPValidationError; they are 400 problem+json here."""
    original = app.openapi
    invalid = problem_responses(400)[400]

    def openapi() -> dict[str, Any]:
        schema = original()
        for path_item in schema.get("paths", {}).values():
            for op in path_item.values():
                responses = op.get("responses") if isinstance(op, dict) else None
                if not responses or "422" not in responses:
                    continue
                if "HTTPValidationError" in json.dumps(responses["422"]):
                    del responses["422"]
                    responses.setdefault("400", invalid)
        components = schema.get("components", {}).get("schemas", {})
        for name in ("HTTPValidationError", "ValidationError"):
            if name in components:
                rest = {k: v for k, v in components.items() if k != name}
                if f"#/components/schemas/{name}" not in json.dumps({"paths": schema["paths"], "c": rest}):
                    del components[name]
        return schema

    return openapi


@asynccontextmanager
async def map_registry(app: FastAPI) -> AsyncIterator[None]:
    """The maps of the data directory: opened and recovered by replay at start, closed at shutdown."""
    from service.maps.encoder_pool import EncoderPool
    from service.maps.encoders import Encoders
    from service.maps.registry import MapRegistry

    s = app.state.settings
    try:
        encoders = Encoders(lambda name: app.state.encoder_factory(s.model_copy(update={"backbone": name})),
                            s.backbone, {s.backbone: app.state.encoder})
        registry = await anyio.to_thread.run_sync(MapRegistry, s.data_dir, encoders, s)
        await anyio.to_thread.run_sync(registry.start)
    except Exception as e:
        # /readyz says why; the process stays alive for /healthz.
        log.exception("cannot open the maps in %s; the service will not be ready", s.data_dir)
        app.state.registry_error = f"the maps could not be opened: {type(e).__name__}: {e}"
        yield
        return
    app.state.registry = registry
    app.state.maps = registry.maps
    app.state.encoder_pool = EncoderPool(encoders, s.encoder_workers, s.encoder_queue)
    try:
        yield
    finally:
        await anyio.to_thread.run_sync(app.state.encoder_pool.close)
        await anyio.to_thread.run_sync(registry.close)


def create_app(settings: Settings | None = None, *, encoder_factory: EncoderFactory | None = None,
               components: Sequence[Component] = (map_registry,)) -> FastAPI:
    """Build the app; settings are read and the encoder built when it starts, not here.

    Args:
        settings: explicit settings; None: `Settings.from_env()` at startup.
        encoder_factory: builds the encoder from the settings (default `build_encoder`); runs in a thread.
        components: startup/shutdown steps entered in order after the encoder (e.g. the map runtime).

    Returns:
        The app. `app.state` after startup: `settings`, `metrics`, `encoder`, `encoder_weights`, `maps`
        (dict), and what the components add (`map_registry`: `registry`, `encoder_pool`).
    """
    metrics = Metrics()
    factory = encoder_factory or build_encoder

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
        app.state.encoder_weights = await anyio.to_thread.run_sync(encoder_weights_info, encoder)
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
    install_error_handlers(app)
    # add_middleware puts each one outside the previous: the last added runs first.
    app.add_middleware(UploadLimitMiddleware)
    app.add_middleware(MetricsMiddleware, metrics=metrics)
    app.add_middleware(RequestContextMiddleware)
    app.add_middleware(SecurityHeadersMiddleware)
    app.include_router(api_router)
    app.mount(UI_PATH, static_files(), name="ui")  # the map viewer: static files, no API of its own
    app.openapi = _openapi_with_problems(app)  # type: ignore[method-assign]
    return app
