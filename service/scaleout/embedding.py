"""The encoder as its own stateless deployment (docs/scaling.md; docs/design/service.md §6, §9).

`EmbeddingService` holds the real encoders (one per backbone, built on first use) and embeds a batch
of single-image requests that Ray Serve's `@serve.batch` gathered from every shard; `RemoteEmbedder`
stands in a shard's process for `models.frontend.embedding.Embedder`: the same identity, feature
dimension, limits and `embed`, with each image sent to the encoder deployment by its handle. The
shard's own `EmbeddingPool` (service/maps/encoding/pool.py) still projects each batch with the map's
sLSBH matrix: the deployment returns features (1, D), never codes, so it needs no map's state.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

import numpy as np

from models.frontend import images
from models.frontend.embedding import EncodeResult
from models.frontend.images import ImageError
from service.frontend import build_embedder, resolve_backbone
from service.maps.encoding.embedders import Embedders
from service.maps.errors import EncoderUnavailable
from service.scaleout.replicas import unavailable_errors
from service.settings import Settings

__all__ = ["EmbedRequest", "Embedded", "EmbeddingService", "PendingReply", "RemoteEmbedder"]

#: One image for the encoder deployment: (backbone, resize or None, encoded bytes or raw frame, thumbnail?).
EmbedRequest = tuple[str, str | None, "bytes | images.RawFrame", bool]
#: Its answer: ("ok", features (1, D), thumbnail JPEG or None, timings ms, contrast) or ("error", the
#: ImageError, None, {}, None). The contrast (`images.contrast`) carries the low-information rule
#: (docs/design/science.md §11.7) across the process boundary.
EmbedReply = tuple[str, Any, Any, dict[str, float], Any]


class EmbeddingService:
    """The encoder deployment's work, Ray left out (tested in process).

    Args:
        settings: the service's settings (backbone, weights, threads, input limits).
    """

    def __init__(self, settings: Settings) -> None:
        settings = resolve_backbone(settings)
        self.encoders = Embedders(lambda name: build_embedder(settings.model_copy(update={"backbone": name})),
                                 settings.backbone)
        self.encoders.get(settings.backbone)  # loaded before the replica says it is ready

    def info(self, backbone: str) -> dict[str, Any]:
        """What a `RemoteEmbedder` needs to stand in for the encoder of `backbone` (ValueError: none here)."""
        e = self.encoders.get(backbone)
        return {"conf": e.conf, "weights_id": e.weights_id, "feature_dim": e.feature_dim,
                "arch": e.backbone.arch, "describe": e.describe()}

    def embed_batch(self, batch: list[EmbedRequest]) -> list[EmbedReply]:
        """Embed requests from any shards: one backbone call per (backbone, resize) present; an image
        that cannot be decoded fails only its own request (the others of its group are embedded alone)."""
        out: list[EmbedReply | None] = [None] * len(batch)
        groups: dict[tuple[str, str | None], list[int]] = {}
        for i, (backbone, resize, _, _) in enumerate(batch):
            groups.setdefault((backbone, resize), []).append(i)
        for (backbone, resize), rows in groups.items():
            encoder = self.encoders.get(backbone)
            how = {"resize": resize} if resize is not None else {}

            def embed(idx: list[int], encoder: Any = encoder, how: dict = how) -> EncodeResult:
                thumbs = [batch[i][3] for i in idx]
                kw = {"thumbnails": thumbs} if any(thumbs) else {}
                return encoder.embed([batch[i][2] for i in idx], **kw, **how)

            try:
                parts = [(rows, embed(rows))]
            except ImageError:
                parts = []
                for i in rows:
                    try:
                        parts.append(([i], embed([i])))
                    except ImageError as e:
                        out[i] = ("error", e, None, {}, None)
            for idx, res in parts:
                assert res.features is not None
                for j, i in enumerate(idx):
                    thumb = res.thumbnails[j] if res.thumbnails else None
                    contrast = float(res.contrast[j]) if res.contrast is not None else None
                    out[i] = ("ok", res.features[j:j + 1], thumb, res.timings_ms, contrast)
        return [o for o in out if o is not None]


class RemoteEmbedder:
    """A shard's stand-in for `Embedder` (the attributes the service reads), embedding by `call`.

    Args:
        info: `EmbeddingService.info` of this backbone.
        call: one `EmbedRequest` -> a future of its `EmbedReply` (the deployment handle's call).
    """

    def __init__(self, info: dict[str, Any], call: Callable[[EmbedRequest], Future[EmbedReply]]) -> None:
        self.conf = dict(info["conf"])
        self.weights_id: str = info["weights_id"]
        self.feature_dim: int = int(info["feature_dim"])
        self.pretrained = self.weights_id.startswith("imagenet")
        self._arch: str = info["arch"]
        self._describe: dict[str, Any] = dict(info["describe"], runtime_location="encoder deployment")
        self._call = call

    @property
    def identity(self) -> str:
        return self.identity_for(self.conf["resize"])

    def identity_for(self, resize: str) -> str:
        """The real encoder's identity (models.frontend.embedding.Embedder.identity_for)."""
        if resize not in images.MODES:
            raise ValueError(f"resize must be one of {', '.join(images.MODES)}, got {resize!r}")
        return f"{self._arch}/{self.weights_id}:{resize}"

    def describe(self) -> dict[str, Any]:
        return dict(self._describe)

    @property
    def decode_limits(self) -> dict[str, int]:
        return {"max_bytes": int(self.conf["max_bytes"]), "max_pixels": int(self.conf["max_pixels"])}

    def decode(self, data: bytes | images.RawFrame, *, grey: bool = False) -> np.ndarray:
        """(H, W, 3) uint8 RGB, decoded here (keyframes' local features are the shard's work)."""
        return images.decode(data, grey=grey, **self.decode_limits)

    def prepare(self, data: bytes | images.RawFrame, *, thumbnail: bool = False,
                resize: str | None = None, key: Hashable = None) -> PendingReply:
        """Send one image to the encoder deployment now (`Embedder.prepare`'s place in the shard's encoder
        pool: the decode, and here the forward too, start when the request arrives); returns at once.
        `key` (the map) is not sent: the deployment's batching queue is Ray Serve's, first in first out
        across shards (docs/scaling.md).

        Returns:
            The pending reply (`result()` blocks: the pool's worker threads call it, never the event
            loop); its `result()` raises the deployment's `ImageError` for a bad upload.
        """
        return PendingReply(self._call((self.conf["backbone"], resize, data, bool(thumbnail))))

    def embed_prepared(self, prepared: Sequence[PendingReply]) -> EncodeResult:
        """Features (N, D) of images sent by `prepare`, in their order (`Embedder.embed_prepared`).

        Raises:
            ImageError: the first image the deployment could not decode.
        """
        replies = [f.result() for f in prepared]
        feats = (np.concatenate([r.features for r in replies]) if replies
                 else np.zeros((0, self.feature_dim), np.float32))
        # The deployment's batch timings (a batch may hold other shards' images too), and the round trip.
        timings = {"decode": 0.0, "preprocess": 0.0, "backbone": 0.0}
        for r in replies:
            for k, v in r.timings_ms.items():
                timings[k] = max(timings.get(k, 0.0), v)
        timings["remote"] = max((r.remote_ms for r in replies), default=0.0)
        contrast = np.array([np.nan if r.contrast is None else r.contrast for r in replies])
        return EncodeResult(codes=None, features=feats, timings_ms=timings,
                            contrast=None if np.isnan(contrast).any() else contrast)

    def embed(self, data: Sequence[bytes | images.RawFrame], thumbnails: Sequence[bool] | None = None,
              resize: str | None = None) -> EncodeResult:
        """Features (N, D) of N images, each sent alone so that the deployment batches across shards.

        Raises:
            ImageError: the first image the deployment could not decode (the pool then retries each
                image alone, so that only its own request fails).
        """
        prepared = [self.prepare(d, thumbnail=bool(thumbnails[i]) if thumbnails else False, resize=resize)
                    for i, d in enumerate(data)]
        out = self.embed_prepared(prepared)
        if thumbnails is not None:
            out.thumbnails = [f.result().thumbnail for f in prepared]
        return out


class PendingReply:
    """One image's call into the encoder deployment, read once (the pool's stand-in for
    `Future[Prepared]`: `result()` and `cancel()`).

    Args:
        call: the deployment handle's response (or any object with `result()`), started at `prepare`.
    """

    def __init__(self, call: Any) -> None:
        self._call = call
        self._t0 = time.perf_counter()
        self._reply: Embedded | None = None

    def result(self) -> Embedded:
        """The reply; raises the deployment's `ImageError` for an image it could not decode, and
        `EncoderUnavailable` when the replica died with the call (a 503, never the app's 500)."""
        if self._reply is None:
            try:
                kind, value, thumb, timings, contrast = self._call.result()
            except unavailable_errors() as e:
                raise EncoderUnavailable(type(e).__name__) from e
            if kind == "error":
                raise value
            remote_ms = (time.perf_counter() - self._t0) * 1e3
            self._reply = Embedded(value, thumb, contrast, dict(timings), remote_ms)
        return self._reply

    def cancel(self) -> bool:
        """Cancel the call where it has not run (a request whose client went away)."""
        cancel = getattr(self._call, "cancel", None)
        return bool(cancel()) if cancel is not None else False


@dataclass
class Embedded:
    """One image's reply from the encoder deployment (the shard's `Prepared`, already forwarded).

    Attributes:
        features: (1, D) float32 descriptor; thumbnail: a small JPEG where asked for, else None;
        contrast: the decoded frame's contrast (docs/design/science.md §11.7), None from an older
        deployment; timings_ms: the deployment's batch timings; remote_ms: the round trip.
    """

    features: np.ndarray
    thumbnail: bytes | None
    contrast: float | None
    timings_ms: dict[str, float]
    remote_ms: float
