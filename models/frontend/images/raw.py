"""Raw sensor frames: uncompressed pixels as a camera driver (ROS `sensor_msgs/Image`) hands them over,
with their encoding, width and height given beside the bytes (docs/design/service.md §1.2).

Checked in the order of the other formats, cheapest first: the body's length against width × height ×
channels × bytes per sample (before anything else: a mismatch means the frame is not what its
parameters say), the byte limit, the pixel cap, the aspect cap. Decoding is a reshape and at most one
OpenCV colour conversion; there is nothing to inflate, so there is no bomb.

`mono16` is little-endian (what `cortexloc_client` sends; a big-endian camera's frame is byte-swapped by
the client) and scaled to 8 bits like a 16-bit PNG (v × 255 / 65535, rounded).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from models.frontend.images.common import (
    DEFAULT_MAX_ASPECT,
    DEFAULT_MAX_BYTES,
    DEFAULT_MAX_PIXELS,
    DEFAULT_MIN_SIDE,
    ImageError,
    _check_shape,
)

__all__ = ["RAW_ENCODINGS", "RawFrame", "decode_raw", "probe_raw"]

#: encoding -> (channels, bytes per sample).
RAW_ENCODINGS: dict[str, tuple[int, int]] = {"rgb8": (3, 1), "bgr8": (3, 1), "mono8": (1, 1),
                                             "mono16": (1, 2)}


@dataclass(frozen=True, eq=False)
class RawFrame:
    """Uncompressed pixels: `data` holds `height` rows of `width` samples of `encoding`, row-major, no
    padding between rows."""

    data: bytes
    encoding: str
    width: int
    height: int

    @property
    def expected_bytes(self) -> int:
        channels, depth = RAW_ENCODINGS[self.encoding]
        return self.width * self.height * channels * depth


def probe_raw(frame: RawFrame, *, max_bytes: int = DEFAULT_MAX_BYTES, max_pixels: int = DEFAULT_MAX_PIXELS,
              max_aspect: float | None = DEFAULT_MAX_ASPECT, min_side: int | None = DEFAULT_MIN_SIDE) -> None:
    """Every check `decode_raw` makes, without touching a pixel.

    Raises:
        ImageError: "unsupported-encoding" (an encoding not in `RAW_ENCODINGS`), "size-mismatch" (the
            body is not width × height × channels × bytes long, or a side is not positive),
            "too-large", "too-many-pixels", "degenerate".
    """
    if frame.encoding not in RAW_ENCODINGS:
        raise ImageError("unsupported-encoding",
                         f"raw encoding {frame.encoding!r} is not supported; send one of "
                         f"{', '.join(RAW_ENCODINGS)}", encoding=frame.encoding,
                         allowed_encodings=list(RAW_ENCODINGS))
    n, w, h = len(frame.data), frame.width, frame.height
    expected = frame.expected_bytes if w > 0 and h > 0 else None
    if expected is None or n != expected:
        raise ImageError("size-mismatch",
                         f"a {frame.encoding} frame of {w}x{h} is {expected} bytes, the body has {n}"
                         if expected is not None else f"width and height must be positive, got {w}x{h}",
                         received_bytes=n, expected_bytes=expected, width=w, height=h,
                         encoding=frame.encoding)
    if n > max_bytes:
        raise ImageError("too-large", f"image is {n} bytes, more than the limit of {max_bytes} bytes",
                         received_bytes=n, max_bytes=max_bytes)
    if w * h > max_pixels:
        raise ImageError("too-many-pixels",
                         f"image has {w}x{h} = {w * h} pixels, more than the limit of {max_pixels}",
                         width=w, height=h, max_pixels=max_pixels, format="raw")
    _check_shape(w, h, "raw", max_aspect, min_side)


def decode_raw(frame: RawFrame, *, max_bytes: int = DEFAULT_MAX_BYTES, max_pixels: int = DEFAULT_MAX_PIXELS,
               max_aspect: float | None = DEFAULT_MAX_ASPECT,
               min_side: int | None = DEFAULT_MIN_SIDE) -> np.ndarray:
    """A raw frame as (H, W, 3) uint8 RGB, C-contiguous (docs/design/science.md §6): `bgr8` swapped,
    grey replicated to three channels, `mono16` scaled to 8 bits with rounding.

    Raises:
        ImageError: see `probe_raw`.
    """
    probe_raw(frame, max_bytes=max_bytes, max_pixels=max_pixels, max_aspect=max_aspect, min_side=min_side)
    w, h = frame.width, frame.height
    if frame.encoding == "mono16":
        grey16 = np.frombuffer(frame.data, dtype="<u2").reshape(h, w)
        grey = cv2.convertScaleAbs(grey16, alpha=255.0 / 65535.0)  # round(v / 257), as for 16-bit PNG
        return np.ascontiguousarray(cv2.cvtColor(grey, cv2.COLOR_GRAY2RGB))
    channels = RAW_ENCODINGS[frame.encoding][0]
    pixels = np.frombuffer(frame.data, dtype=np.uint8).reshape(h, w, channels)
    if frame.encoding == "mono8":
        return np.ascontiguousarray(cv2.cvtColor(pixels[:, :, 0], cv2.COLOR_GRAY2RGB))
    if frame.encoding == "bgr8":
        return np.ascontiguousarray(cv2.cvtColor(pixels, cv2.COLOR_BGR2RGB))
    return pixels.copy()  # rgb8: a writable copy, not a view of the request body
