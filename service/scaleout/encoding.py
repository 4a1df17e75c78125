"""The encoder as its own stateless deployment (docs/scaling.md; docs/design/service.md §6, §9).

`EncoderService` holds the real encoders (one per backbone, built on first use) and embeds a batch
of single-image requests that Ray Serve's `@serve.batch` gathered from every shard; `RemoteEncoder`
stands in a shard's process for `models.frontend.encoder.Encoder`: the same identity, feature
dimension, limits and `embed`, with each image sent to the encoder deployment by its handle. The
shard's own `EncoderPool` (service/maps/encoding/pool.py) still projects each batch with the map's
sLSBH matrix: the deployment returns features (1, D), never codes, so it needs no map's state.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Any

import numpy as np

from models.frontend import images
from models.frontend.encoder import EncodeResult
from models.frontend.images import ImageError
from service.encoder import build_encoder, resolve_backbone
from service.maps.encoding.encoders import Encoders
from service.settings import Settings

__all__ = ["EmbedRequest", "EncoderService", "RemoteEncoder"]

#: One image for the encoder deployment: (backbone, resize or None, encoded bytes or raw frame, thumbnail?).
EmbedRequest = tuple[str, str | None, "bytes | images.RawFrame", bool]
#: Its answer: ("ok", features (1, D), thumbnail JPEG or None, timings ms) or ("error", the ImageError).
EmbedReply = tuple[str, Any, Any, dict[str, float]]


class EncoderService:
    """The encoder deployment's work, Ray left out (tested in process).

    Args:
        settings: the service's settings (backbone, weights, threads, input limits).
    """

    def __init__(self, settings: Settings) -> None:
        settings = resolve_backbone(settings)
        self.encoders = Encoders(lambda name: build_encoder(settings.model_copy(update={"backbone": name})),
                                 settings.backbone)
        self.encoders.get(settings.backbone)  # loaded before the replica says it is ready

    def info(self, backbone: str) -> dict[str, Any]:
        """What a `RemoteEncoder` needs to stand in for the encoder of `backbone` (ValueError: none here)."""
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
                        out[i] = ("error", e, None, {})
            for idx, res in parts:
                assert res.features is not None
                for j, i in enumerate(idx):
                    thumb = res.thumbnails[j] if res.thumbnails else None
                    out[i] = ("ok", res.features[j:j + 1], thumb, res.timings_ms)
        return [o for o in out if o is not None]


class RemoteEncoder:
    """A shard's stand-in for `Encoder` (the attributes the service reads), embedding by `call`.

    Args:
        info: `EncoderService.info` of this backbone.
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
        """The real encoder's identity (models.frontend.encoder.Encoder.identity_for)."""
        if resize not in images.MODES:
            raise ValueError(f"resize must be one of {', '.join(images.MODES)}, got {resize!r}")
        return f"{self._arch}/{self.weights_id}:{resize}"

    def describe(self) -> dict[str, Any]:
        return dict(self._describe)

    @property
    def decode_limits(self) -> dict[str, int]:
        return {"max_bytes": int(self.conf["max_bytes"]), "max_pixels": int(self.conf["max_pixels"])}

    def decode(self, data: bytes | images.RawFrame) -> np.ndarray:
        """(H, W, 3) uint8 RGB, decoded here (keyframes' local features are the shard's work)."""
        return images.decode(data, **self.decode_limits)

    def embed(self, data: Sequence[bytes | images.RawFrame], thumbnails: Sequence[bool] | None = None,
              resize: str | None = None) -> EncodeResult:
        """Features (N, D) of N images, each sent alone so that the deployment batches across shards.

        Raises:
            ImageError: the first image the deployment could not decode (the pool then retries each
                image alone, so that only its own request fails).
        """
        t0 = time.perf_counter()
        backbone = self.conf["backbone"]
        futures = [self._call((backbone, resize, d, bool(thumbnails[i]) if thumbnails else False))
                   for i, d in enumerate(data)]
        replies = [f.result() for f in futures]
        for kind, value, _, _ in replies:
            if kind == "error":
                raise value
        feats = (np.concatenate([r[1] for r in replies]) if replies
                 else np.zeros((0, self.feature_dim), np.float32))
        # The deployment's batch timings (a batch may hold other shards' images too), and the round trip.
        timings = {"decode": 0.0, "preprocess": 0.0, "backbone": 0.0}
        for r in replies:
            for k, v in r[3].items():
                timings[k] = max(timings.get(k, 0.0), v)
        timings["remote"] = (time.perf_counter() - t0) * 1e3
        thumbs = [r[2] for r in replies] if thumbnails is not None else None
        return EncodeResult(codes=None, features=feats, timings_ms=timings, thumbnails=thumbs)
