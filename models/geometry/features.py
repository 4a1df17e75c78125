"""Local features of a frame, in its native pixels, and their compact bytes
(docs/design/science.md §12.1).

A small registry of OpenCV extractors (`EXTRACTORS`: orb, sift, akaze). Every descriptor is stored as
uint8 (ORB and AKAZE are binary strings already; OpenCV's SIFT values are integers in [0, 255] held as
float32, so uint8 keeps them exactly after rounding) and keypoint positions as float32 pixels, so a
keyframe of n features takes 8 n + n D bytes plus a 16-byte header (D: 32 orb, 61 akaze, 128 sift).
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

__all__ = ["EXTRACTORS", "EXTRACT_MAX_SIDE", "MIN_SIDE", "Features", "KeyframeParams", "available", "extract",
           "pack", "unpack"]

#: Registered extractors, in their stored code order (the code is the header's first byte).
EXTRACTORS = ("orb", "sift", "akaze")
_FACTORIES = {"orb": "ORB_create", "sift": "SIFT_create", "akaze": "AKAZE_create"}
_DIMS = {"orb": 32, "sift": 128, "akaze": 61}
#: Hamming (binary strings) or L2 (SIFT) between descriptors.
NORMS = {"orb": cv2.NORM_HAMMING, "sift": cv2.NORM_L2, "akaze": cv2.NORM_HAMMING}
#: A frame whose shorter side is below this many pixels is not verifiable: ORB's and AKAZE's border
#: (31 px patches) leave almost nothing of it, and the few features left could not tell a wrong match
#: from a right one. 64 x 32 thumbnails fall here and are refused with a reason, never matched.
MIN_SIDE = 96
#: Features are taken on the frame scaled down to this longer side at most (as RTAB-Map and hloc do), then
#: their positions scaled back to native pixels (RANSAC's threshold and the intrinsics are in native
#: pixels). SIFT's is smaller: its pyramid starts from the image doubled (a 1024 px frame is a 2048 px
#: base) and holds ~250 bytes per pixel it is given, so 1024 px keep a 25 MP frame's extraction within
#: ~300 MB; at native resolution it took 12-14 s and 5.7 GB (docs/benchmarks.md §13.1).
EXTRACT_MAX_SIDE = {"orb": 1600, "sift": 1024, "akaze": 1600}
_HEADER = struct.Struct("<BBHHHHxxxxxx")  # code, descriptor bytes % 256 flag, n, D, width, height
assert _HEADER.size == 16


@dataclass(frozen=True, slots=True)
class KeyframeOptions:
    """The `keyframes` map option, typed (docs/design/service.md §1.1, science.md §12.1): the one home of
    its names and defaults. Build one from untrusted values with `of` (checked by `KeyframeParams`)."""

    #: the extractor (`EXTRACTORS`): ORB is in every OpenCV build and the fastest
    features: str = "orb"
    #: features kept per frame (the strongest)
    max: int = 500

    @classmethod
    def of(cls, values: Mapping[str, Any] | None = None) -> KeyframeOptions:
        """The section of `values` (a map's `keyframes` dict), checked, the missing names the defaults.
        Raises pydantic.ValidationError."""
        return cls(**KeyframeParams.model_validate(dict(values or {})).model_dump())

    def values(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


_KF = KeyframeOptions()


class KeyframeParams(BaseModel):
    """The check of the `keyframes` map option (`KeyframeOptions`: names, defaults): which extractor,
    how many features per frame at most."""

    model_config = ConfigDict(extra="forbid", strict=True)
    features: Literal["orb", "sift", "akaze"] = _KF.features  # type: ignore[assignment]
    max: int = Field(default=_KF.max, ge=50, le=8000, description="features kept per frame (the strongest)")

    @field_validator("features")
    @classmethod
    def _available(cls, v: str) -> str:
        if (why := _unavailable(v)) is not None:
            raise ValueError(why)
        return v


@dataclass(frozen=True)
class Features:
    """One frame's local features.

    Attributes:
        kind: the extractor (`EXTRACTORS`).
        xy: (n, 2) float32 keypoint positions in pixels of the native frame.
        desc: (n, D) uint8 descriptors.
        size: (width, height) of the frame they were taken from.
    """

    kind: str
    xy: np.ndarray
    desc: np.ndarray
    size: tuple[int, int]

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    @property
    def too_small(self) -> bool:
        return min(self.size) < MIN_SIDE


def available() -> tuple[str, ...]:
    """The extractors this OpenCV build has (OpenCV 5's main modules dropped AKAZE to contrib)."""
    return tuple(k for k in EXTRACTORS if hasattr(cv2, _FACTORIES[k]))


def _unavailable(kind: str) -> str | None:
    """Why `kind` cannot be used here, or None."""
    if kind in available():
        return None
    return f"extractor {kind!r} is not in this OpenCV build; available: {', '.join(available())}"


def _detector(kind: str, max_n: int) -> cv2.Feature2D:
    if (why := _unavailable(kind)) is not None:
        raise ValueError(why)
    factory = getattr(cv2, _FACTORIES[kind])
    return factory() if kind == "akaze" else factory(nfeatures=max_n)  # AKAZE has no count: cut below


def extract(image: np.ndarray, kind: str = "orb", max_n: int = 500) -> Features:
    """Detect and describe `image`'s local features.

    Args:
        image: (H, W) uint8 grey or (H, W, 3) uint8 RGB, at the frame's native resolution (before any
            backbone resize: docs/design/science.md §12.1). Features are taken on it scaled to
            `EXTRACT_MAX_SIDE[kind]` at most and their positions given in its native pixels.
        kind: an extractor of `available()` (ValueError otherwise).
        max_n: the strongest `max_n` are kept (by response).

    Returns:
        Features; empty (n = 0) for a frame with a side below `MIN_SIDE` (nothing is detected on it).
    """
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    h, w = grey.shape[:2]
    det = _detector(kind, max_n)  # ValueError for an unknown or unavailable extractor
    empty = Features(kind, np.zeros((0, 2), np.float32), np.zeros((0, _DIMS[kind]), np.uint8), (w, h))
    if min(h, w) < MIN_SIDE:
        return empty
    scale = min(1.0, EXTRACT_MAX_SIDE[kind] / max(h, w))
    if scale < 1.0:  # INTER_AREA: the average of the pixels each one covers (no aliasing)
        small = (max(1, round(w * scale)), max(1, round(h * scale)))
        grey = cv2.resize(grey, small, interpolation=cv2.INTER_AREA)
    kps, desc = det.detectAndCompute(np.ascontiguousarray(grey), None)
    del grey
    if desc is None or not kps:
        return empty
    order = np.argsort([-k.response for k in kps], kind="stable")[:max_n]
    xy = np.array([kps[i].pt for i in order], np.float32).reshape(-1, 2)
    if scale < 1.0:  # back to native pixels: (x + 0.5) / s - 0.5, OpenCV's pixel-centre convention
        small_w, small_h = small
        xy = ((xy + 0.5) * np.array([w / small_w, h / small_h], np.float32) - 0.5).astype(np.float32)
    d = desc[order]
    if d.dtype != np.uint8:  # SIFT: integer values in [0, 255] held as float32
        d = np.clip(np.rint(d), 0, 255).astype(np.uint8)
    return Features(kind, xy, np.ascontiguousarray(d), (w, h))


def pack(f: Features) -> bytes:
    """Features -> bytes: a 16-byte header, then xy (n, 2) float32 and desc (n, D) uint8, little-endian."""
    n, dim = f.desc.shape
    return (_HEADER.pack(EXTRACTORS.index(f.kind), 0, n, dim, *f.size)
            + f.xy.astype("<f4").tobytes() + f.desc.astype(np.uint8).tobytes())


def unpack(data: bytes) -> Features:
    """bytes (`pack`) -> Features. Raises ValueError on a short or inconsistent blob."""
    if len(data) < _HEADER.size:
        raise ValueError("keyframe blob shorter than its header")
    code, _, n, dim, w, h = _HEADER.unpack_from(data)
    if code >= len(EXTRACTORS) or len(data) != _HEADER.size + n * (8 + dim):
        raise ValueError("keyframe blob does not match its header")
    xy = np.frombuffer(data, "<f4", 2 * n, _HEADER.size).reshape(n, 2).astype(np.float32)
    desc = np.frombuffer(data, np.uint8, n * dim, _HEADER.size + 8 * n).reshape(n, dim)
    return Features(EXTRACTORS[code], xy, desc, (w, h))
