"""Embedder: a batch of image bytes -> sLSBH SDRs (docs/design/science.md §1, §6, §7).

Two entry points, stateless across calls and batch-first, so the service can batch concurrent requests:
`Embedder.embed(images)` gives backbone features (the service projects them with each map's own matrix,
service.maps.encoding.pool) and `Embedder.encode(images)` goes on to the sLSBH codes with the encoder's own
projection (evaluation, benchmarks). Configuration is a `default_conf` merged with the caller's (presets as
data); the encoder's identity string says which backbone, weights and resize mode it runs on, because
descriptors from different encoders are not comparable.

Example:
    >>> enc = Embedder({"backbone": "alexnet", "slsbh": {"s": 0.25}})
    >>> out = enc.encode([open("frame.jpg", "rb").read()])
    >>> out.codes[0]          # (2n,) int32 sorted active columns
"""

from __future__ import annotations

import copy
import functools
import logging
import time
from collections.abc import Hashable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import threadpoolctl
import torch

from models import presets
from models.frontend import backbones, images, limits, runtimes, slsbh, weights
from models.frontend.turns import TurnPool

log = logging.getLogger("cortexloc.encoder")

_SLSBH = presets.SlsbhParams()

default_conf: dict[str, Any] = {
    "backbone": backbones.PAPER,  # a name registered in models.frontend.backbones
    "resize": "crop",  # crop (Resize 256 + CenterCrop 224, as the paper) | squash (straight to 224)
    "weights_path": None,  # AlexNet conv1..conv3 file; None: look in the weights cache, else random
    "random_seed": 0,  # seed of the NumPy-generated fallback weights
    "torch_threads": 1,  # the backbone's intra-op threads, on either runtime
    # onnxruntime (the torch module exported to ONNX, same codes, measured faster: docs/benchmarks.md §10)
    # | torch (the reference); models.frontend.runtimes
    "runtime": runtimes.RUNTIMES[0],
    "device": "cpu",  # cpu | cuda | auto (CUDA through ONNX Runtime; auto falls back to the CPU)
    "export_dir": None,  # the ONNX exports' content-addressed store; None: <weights cache>/onnx
    "decode_threads": 2,  # OpenCV releases the GIL: frames decode and resize beside the backbone
    "chunk": limits.DEFAULT_CHUNK,  # images per backbone call while the next ones are prepared
    "max_bytes": limits.DEFAULT_MAX_BYTES,
    "max_pixels": limits.DEFAULT_MAX_PIXELS,
    # projection: the encoder's own (evaluation, benchmarks): dense (docs/design/science.md §7) | sparse
    # (the very sparse random projection, at parity in docs/results.md §6). A map's is chosen by the
    # service, sparse where dense would break its size budget (service/maps/projection.py: AlexNet).
    # k and s: the map defaults (presets.SlsbhParams); the encoder's own projection has seed 0.
    "slsbh": {"k": _SLSBH.k, "s": _SLSBH.s, "seed": 0, "projection": "dense"},
    "projection_dir": None,  # where projections are stored content-addressed; None: keep in memory
}

STAGES = ("decode", "preprocess", "backbone", "hash")


def merge_conf(conf: dict[str, Any] | None) -> dict[str, Any]:
    """`default_conf` updated with `conf` (one level deep for the `slsbh` section)."""
    out = copy.deepcopy(default_conf)
    for key, value in (conf or {}).items():
        if key not in out:
            raise ValueError(f"unknown encoder option {key!r}; known: {sorted(out)}")
        if key == "slsbh":
            unknown = set(value) - set(out["slsbh"])
            if unknown:
                raise ValueError(f"unknown sLSBH option(s) {sorted(unknown)}; known: {sorted(out['slsbh'])}")
            out["slsbh"].update(value)
        else:
            out[key] = value
    _check_resize(out["resize"])
    return out


def _check_resize(mode: str) -> str:
    if mode not in images.MODES:
        raise ValueError(f"resize must be one of {', '.join(images.MODES)}, got {mode!r}")
    return mode


@dataclass
class EncodeResult:
    """What `Embedder.encode` returns.

    Attributes:
        codes: (N, 2n) int32, each row the sorted active columns of one image (None from `embed`).
        features: (N, D) float32 L2-normalised backbone features, when asked for.
        timings_ms: wall time per stage for the whole batch (decode, preprocess, backbone, hash).
        projected: (N, k) float32 projections x·P, when a caller projected for a map
            (service.maps.encoding.pool).
        thumbnails: per image, a small JPEG of the decoded frame where `embed` was asked for one
            (`images.thumbnail`), else None; None when none was asked for.
        contrast: (N,) float64 each decoded frame's contrast (`images.contrast`, docs/design/science.md
            §11.7: how much it can say about where it was taken), from `embed`.
    """

    codes: np.ndarray | None
    features: np.ndarray | None = None
    projected: np.ndarray | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    thumbnails: list[bytes | None] | None = None
    contrast: np.ndarray | None = None


class Embedder:
    """Image bytes -> SDR codes, with the backbone and the sLSBH projection of one configuration.

    Timings: decode and preprocess are summed over the images (they run in a thread pool, overlapped
    with the backbone); backbone and hash are wall time.

    Args:
        conf: overrides of `default_conf`.
        projection: an existing projection (d, k), dense array or `slsbh.SparseProjection`, to use
            instead of generating one (a map's).
    """

    def __init__(self, conf: dict[str, Any] | None = None,
                 projection: np.ndarray | slsbh.SparseProjection | None = None) -> None:
        self.conf = merge_conf(conf)
        self.chunk = int(self.conf["chunk"])  # images per backbone call (limits.DEFAULT_CHUNK: why)
        torch.set_num_threads(int(self.conf["torch_threads"]))
        # The same budget for the BLAS behind the sLSBH projection (NumPy's OpenBLAS starts one thread per
        # core): on cores shared with the decode threads and the map writers its threads wait on each
        # other; one thread measured 12.6 ms against 54-94 ms (median) for a batch-16 x·P at D = 5,488,
        # with the same codes (docs/benchmarks.md §10).
        threadpoolctl.threadpool_limits(int(self.conf["torch_threads"]), user_api="blas")
        self.backbone = backbones.get(self.conf["backbone"])(self.conf)
        export_dir = self.conf["export_dir"]
        self.runner = runtimes.make_runner(
            self.backbone, self.conf["runtime"], self.conf["device"], int(self.conf["torch_threads"]),
            Path(export_dir) if export_dir is not None else weights.default_cache_dir() / "onnx")
        self.weights_id = self.backbone.weights_id
        self.input_mean, self.input_std = self.backbone.input_mean, self.backbone.input_std
        self.pretrained = self.weights_id.startswith("imagenet")
        if self.weights_id.startswith("random"):
            log.warning(
                "encoder runs on RANDOM weights (%s): results cannot support claims about the paper. "
                "Fix: `cortexloc weights download` (online) or `cortexloc weights import PATH`.",
                self.weights_id)
        s_conf = self.conf["slsbh"]
        if s_conf["projection"] not in ("dense", "sparse"):
            raise ValueError(f"slsbh.projection must be dense or sparse, got {s_conf['projection']!r}")
        if projection is not None:
            self._check_projection(projection)
            self.__dict__["hasher"] = slsbh.Hasher(projection, float(s_conf["s"]))
        # Always a pool, even of one thread: `prepare` never decodes on its caller's thread (the service's
        # event loop), and the backbone runs beside the decoding. Its keys (the service's maps) take turns.
        self._pool = TurnPool(int(self.conf["decode_threads"]), "decode")

    # ------------------------------------------------------------------ projection

    def _check_projection(self, projection: np.ndarray | slsbh.SparseProjection) -> None:
        expected = (self.feature_dim, int(self.conf["slsbh"]["k"]))
        if tuple(projection.shape) != expected:
            raise ValueError(f"projection shape {tuple(projection.shape)} != {expected}")

    @functools.cached_property
    def hasher(self) -> slsbh.Hasher:
        """The sLSBH hasher, built on first use: a service that hashes with each map's own projection
        (`Embedder.embed` + the map's hasher) never pays for a 266 MB matrix it does not use."""
        s_conf = self.conf["slsbh"]
        d, k, seed = self.feature_dim, int(s_conf["k"]), int(s_conf["seed"])
        if s_conf["projection"] == "sparse":
            projection = slsbh.make_sparse_projection(d, k, seed)
        else:
            projection = slsbh.make_projection(d, k, seed)
            if self.conf["projection_dir"] is not None:
                slsbh.save_projection(projection, Path(self.conf["projection_dir"]))
        return slsbh.Hasher(projection, float(s_conf["s"]))

    @property
    def projection(self) -> np.ndarray | slsbh.SparseProjection:
        return self.hasher.P

    @functools.cached_property
    def projection_sha256(self) -> str:
        """SHA-256 of the projection (hashing 266 MB takes ~0.2 s: computed once)."""
        return self.hasher.sha256()

    # ------------------------------------------------------------------ identity

    @property
    def feature_dim(self) -> int:
        """D, the length of the flattened backbone descriptor at 224x224."""
        if not hasattr(self, "_feature_dim"):
            with torch.inference_mode():
                self._feature_dim = int(self._forward(torch.zeros(1, 3, 224, 224)).shape[1])
        return self._feature_dim

    @property
    def identity(self) -> str:
        """e.g. `alexnet-conv3/imagenet-7be5be79:crop` or `alexnet-conv3/random-seed0:crop`."""
        return self.identity_for(self.conf["resize"])

    def identity_for(self, resize: str) -> str:
        """The identity of this encoder's features under another resize mode (`embed(resize=...)`): a
        map made with `resize: squash` records `...:squash`."""
        # The architecture names its descriptor layer: that is part of what makes codes comparable.
        return f"{self.backbone.arch}/{self.weights_id}:{_check_resize(resize)}"

    def describe(self) -> dict[str, Any]:
        """What the service reports in /readyz and every response: the backbone, its weights, and the
        runtime and device it runs on (`models.frontend.runtimes`; the identity does not name them: both
        runtimes compute the same codes).

        The projection is not part of it: in the service every map hashes with its own persisted
        projection, and building this encoder's would cost 266 MB and a SHA-256 per call.
        """
        weights = "pretrained" if self.pretrained else self.weights_id.split("-", 1)[0]  # random | file
        return {"encoder": self.identity, "weights": weights, **runtimes.describe_runner(self.runner)}

    # ------------------------------------------------------------------ encoding

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.backbone.describe(x)

    def preprocess(self, rgbs: Sequence[np.ndarray]) -> np.ndarray:
        """(N, 3, 224, 224) float32 network input for decoded RGB images."""
        return images.preprocess_batch(rgbs, mode=self.conf["resize"], mean=self.input_mean,
                                       std=self.input_std)

    def features(self, batch: np.ndarray) -> np.ndarray:
        """(N, D) float32 L2-normalised descriptors of a preprocessed batch (N, 3, 224, 224), on the
        encoder's runtime and device."""
        return self.runner(batch)

    def encode(self, data: Sequence[bytes], return_features: bool = False) -> EncodeResult:
        """Encode a batch of uploaded images into sLSBH codes; see `embed` for the errors."""
        out = self.embed(data)
        # Once for the batch, not per chunk: x·P is bound by reading P (21 MB for the default backbone),
        # so hashing each chunk of 4 read it four times (measured 18 ms of CPU against 5 for the batch).
        t0 = time.perf_counter()
        out.codes = self.hasher(out.features)
        out.timings_ms["hash"] = (time.perf_counter() - t0) * 1e3
        if not return_features:
            out.features = None
        return out

    @property
    def decode_limits(self) -> dict[str, int]:
        """The byte and pixel limits every decode of this encoder applies (its `max_bytes`, `max_pixels`)."""
        return {"max_bytes": int(self.conf["max_bytes"]), "max_pixels": int(self.conf["max_pixels"])}

    def decode(self, data: bytes | images.RawFrame, *, grey: bool = False) -> np.ndarray:
        """One upload to (H, W, 3) uint8 RGB (`grey`: (H, W)) at its native resolution, within this
        encoder's limits (what `embed` decodes, for work beside the backbone such as local features)."""
        return images.decode(data, grey=grey, **self.decode_limits)

    def prepare(self, data: bytes | images.RawFrame, *, thumbnail: bool = False, resize: str | None = None,
                out: np.ndarray | None = None, key: Hashable = None) -> Future[Prepared]:
        """Start decoding and preprocessing one upload in the encoder's decode threads, for
        `embed_prepared`; returns at once.

        The service's encoder pool calls this when a request arrives, so a frame decodes while the
        backbone runs on the batch before it (docs/design/service.md §6); OpenCV releases the GIL.

        Args:
            data: one encoded image (JPEG, PNG, BMP, WebP) or raw frame.
            thumbnail: also keep a small JPEG of the decoded frame (`images.thumbnail`).
            resize: crop | squash; None: the encoder's own `resize`.
            out: (3, 224, 224) float32 row of the batch the backbone will run on, written in place (no
                second copy); None: a new array.
            key: whose frame it is (the service's map): the decode threads take keys in turn
                (`models.frontend.turns`), so one key's burst does not hold the others' frames back.

        Returns:
            A future of the `Prepared` frame; its exception is the `images.ImageError` of a bad upload.
        """
        kw = {"mode": _check_resize(resize or self.conf["resize"]), "mean": self.input_mean,
              "std": self.input_std}
        limits = self.decode_limits

        def run() -> Prepared:
            t0 = time.perf_counter()
            rgb = images.decode(data, **limits)
            thumb = images.thumbnail(rgb) if thumbnail else None
            contrast = images.contrast(rgb)
            t1 = time.perf_counter()
            x = images.preprocess(rgb, out=out, **kw)
            return Prepared(x, thumb, contrast, (t1 - t0) * 1e3, (time.perf_counter() - t1) * 1e3)

        return self._pool.submit(run, key)

    def embed_prepared(self, prepared: Sequence[Future[Prepared]]) -> EncodeResult:
        """Backbone features of frames from `prepare`, in their order, forwarded in chunks of `chunk` as
        they become ready, so the backbone starts on the first frames while the others still decode.

        Args:
            prepared: N futures from `prepare` (all of the same resize mode).

        Returns:
            EncodeResult with features (N, D), contrast (N,) and the timings decode and preprocess
            (summed over the frames) and backbone (wall).

        Raises:
            images.ImageError: a frame did not decode (the first such, in order); the remaining futures
                are cancelled.
        """
        return self._forward_chunks(prepared, None)

    def _forward_chunks(self, prepared: Sequence[Future[Prepared]], batch: np.ndarray | None) -> EncodeResult:
        """`embed_prepared`, where `batch` (N, 3, 224, 224) is the buffer the frames were prepared into
        (None: stack them)."""
        timings = dict.fromkeys(STAGES[:3], 0.0)
        contrast = np.zeros(len(prepared))
        feats_parts: list[np.ndarray] = []
        try:
            for start in range(0, len(prepared), self.chunk):
                ready = [f.result() for f in prepared[start:start + self.chunk]]
                for j, p in enumerate(ready):
                    contrast[start + j] = p.contrast
                    timings["decode"] += p.decode_ms
                    timings["preprocess"] += p.preprocess_ms
                # Rows prepared in place into the batch are already the chunk: no second copy.
                chunk = (batch[start:start + len(ready)] if batch is not None
                         else np.stack([p.x for p in ready]))
                t0 = time.perf_counter()
                feats = self.features(chunk)
                timings["backbone"] += (time.perf_counter() - t0) * 1e3
                feats_parts.append(feats)
        except BaseException:
            for f in prepared:
                f.cancel()
            raise
        if not feats_parts:
            feats_parts.append(self.features(np.zeros((0, 3, 224, 224), np.float32)))
        return EncodeResult(codes=None, features=np.concatenate(feats_parts) if len(feats_parts) > 1
                            else feats_parts[0], timings_ms=timings, contrast=contrast)

    def embed(self, data: Sequence[bytes | images.RawFrame],
              thumbnails: Sequence[bool] | None = None, resize: str | None = None) -> EncodeResult:
        """Backbone features of a batch of uploaded images (no hashing: `codes` is None).

        Args:
            data: N encoded images (JPEG, PNG, BMP, WebP) or raw frames.
            thumbnails: per image, whether to keep a small JPEG of the decoded frame
                (`EncodeResult.thumbnails`), made in the decode threads from the frame already decoded.
            resize: crop | squash for this batch (a map's frozen option, docs/design/science.md §6);
                None: the encoder's own `resize`. The features are those of `identity_for(resize)`.

        Returns:
            EncodeResult with features (N, D) and the decode, preprocess and backbone timings.

        Raises:
            images.ImageError: an input is not a decodable image within the limits (the whole batch is
                refused; the service's encoder pool prepares each image on its own, so one bad upload
                fails only its own request).
        """
        # Each frame is preprocessed straight into its row of the batch the backbone runs on.
        batch = np.empty((len(data), 3, 224, 224), np.float32)
        prepared = [self.prepare(b, thumbnail=bool(thumbnails and thumbnails[i]), resize=resize, out=batch[i])
                    for i, b in enumerate(data)]
        out = self._forward_chunks(prepared, batch)
        if thumbnails is not None:
            out.thumbnails = [f.result().thumbnail for f in prepared]
        return out


@dataclass
class Prepared:
    """One frame ready for the backbone (`Embedder.prepare`).

    Attributes:
        x: (3, 224, 224) float32 network input (docs/design/science.md §6).
        thumbnail: a small JPEG of the decoded frame, where asked for.
        contrast: the decoded frame's contrast (`images.contrast`, docs/design/science.md §11.7).
        decode_ms, preprocess_ms: the time each step took.
    """

    x: np.ndarray
    thumbnail: bytes | None
    contrast: float
    decode_ms: float
    preprocess_ms: float
