"""The service's `Embedder` and the choice of the backbone of new maps, made once at startup
(docs/design/service.md §1.1, §7): `resolve_backbone`, `build_embedder`, and what /readyz says of the
weights (`embedder_weights_info`)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from models.frontend.embedding import Embedder
from service.settings import ConfigError, Settings

__all__ = ["EmbedderFactory", "build_embedder", "embedder_weights_info", "resolve_backbone"]

log = logging.getLogger("cortexloc.service")

EmbedderFactory = Callable[[Settings], Embedder]


def build_embedder(settings: Settings, **overrides: Any) -> Embedder:
    """The encoder of `settings.backbone` (resolved at startup; AlexNet conv3 with the configured weights
    and seed, or EfficientNet-Lite0 with its package's), threads and input limits.

    Args:
        settings: the settings.
        **overrides: `models.frontend.embedding.default_conf` keys merged last (tests: `slsbh={"k": 16}`).

    Raises:
        ConfigError: naming CORTEXLOC_WEIGHTS_PATH when the weights cannot be used.
    """
    from models.frontend import weights
    from models.frontend.runtimes import DeviceUnavailableError
    from service.maps.config import DEFAULT_RESIZE

    try:
        path = settings.weights_path if settings.weights_path is not None else weights.find_alexnet()
        if path is None and not settings.allow_random_weights:
            log.error("no AlexNet weights: CORTEXLOC_WEIGHTS_PATH is unset, none are installed, and "
                      "CORTEXLOC_ALLOW_RANDOM_WEIGHTS=false; the service will not be ready")
        conf = {"backbone": resolve_backbone(settings).backbone,
                "weights_path": str(path) if path is not None else None,
                "random_seed": settings.random_weights_seed, "torch_threads": settings.torch_threads,
                "chunk": settings.encode_chunk,
                "max_bytes": settings.max_upload_bytes, "max_pixels": settings.max_pixels,
                "runtime": settings.runtime, "device": settings.device,
                # the resize a new map gets, so the identity /readyz and /metrics show is a new map's
                # (each map embeds with its own: `Embedder.identity_for`)
                "resize": DEFAULT_RESIZE, **overrides}
        return Embedder(conf)
    except DeviceUnavailableError as e:
        raise ConfigError([("CORTEXLOC_DEVICE", f"={settings.device!r}: {e}")]) from e
    except weights.WeightsError as e:
        shown = f"={str(settings.weights_path)!r}" if settings.weights_path is not None else " (unset)"
        raise ConfigError([("CORTEXLOC_WEIGHTS_PATH", f"{shown}: {e}")]) from e


def resolve_backbone(settings: Settings) -> Settings:
    """The settings with `backbone` resolved once: the configured one, else AlexNet when its real
    weights are installed (CORTEXLOC_WEIGHTS_PATH or the cache), else `efficientnet-lite0-s5`
    (`service.maps.encoding.embedders.default_backbone`)."""
    from models.frontend import weights
    from service.maps.encoding.embedders import default_backbone

    if settings.backbone is not None:
        return settings
    installed = settings.weights_path is not None or weights.find_alexnet() is not None
    return settings.model_copy(update={"backbone": default_backbone(None, installed)})


def embedder_weights_info(encoder: Embedder) -> dict[str, Any]:
    """What /readyz reports about the weights: `weights_id`, and the file's SHA-256 (or the seed)."""
    from models.frontend import weights
    from storage.base.files import sha256_file

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
