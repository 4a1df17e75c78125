"""Bytes -> (H, W, 3) uint8 RGB (or (H, W) grey): `probe`'s checks, the bounded PNG inflate or the JPEG
scan-data check, then `cv2.imdecode`."""

from __future__ import annotations

from collections.abc import Collection

import cv2
import numpy as np

from models.frontend.images.common import (
    _FORMAT_NAMES,
    DEFAULT_MAX_ASPECT,
    DEFAULT_MAX_BYTES,
    DEFAULT_MAX_PIXELS,
    DEFAULT_MIN_SIDE,
    FORMATS,
    ImageError,
)
from models.frontend.images.jpeg import _jpeg_check_scan_data
from models.frontend.images.png import _png_check_inflate
from models.frontend.images.probing import probe
from models.frontend.images.raw import RawFrame, decode_raw


def decode(data: bytes | RawFrame, *, max_bytes: int = DEFAULT_MAX_BYTES,
           max_pixels: int = DEFAULT_MAX_PIXELS, max_aspect: float | None = DEFAULT_MAX_ASPECT,
           min_side: int | None = DEFAULT_MIN_SIDE, formats: Collection[str] = FORMATS,
           grey: bool = False) -> np.ndarray:
    """Decode an uploaded JPEG, PNG, BMP or WebP, or a raw frame (`raw.decode_raw`), to 8-bit RGB
    (docs/design/science.md §6).

    Grey images are replicated to three channels, alpha is dropped (not composited), 16-bit PNGs are
    scaled to 8 bits with rounding (v × 255 / 65535), and the EXIF orientation is applied, as OpenCV's
    `IMREAD_COLOR` does. All of `probe`'s checks run first, so nothing is decoded past a limit.

    Args:
        data: the uploaded bytes.
        max_bytes: byte limit ("too-large").
        max_pixels: pixel cap, checked on the header before decoding ("too-many-pixels").
        max_aspect: long side / short side limit ("degenerate"); None disables it.
        min_side: fewest pixels of the short side ("degenerate"); None disables it.
        formats: accepted formats, a subset of `FORMATS`.
        grey: decode to one grey channel instead (a third of the memory of RGB, and the codec skips its
            colour conversion: what local features take, docs/design/science.md §12.1).

    Returns:
        (H, W, 3) uint8 RGB, or (H, W) uint8 grey with `grey`, C-contiguous; H and W after the EXIF
        rotation.

    Raises:
        ImageError: see `probe`; also "not-an-image" when OpenCV cannot decode a structurally complete
            file (corrupt data) or a JPEG's scan data is damaged (`jpeg._jpeg_check_scan_data`), "bomb"
            when PNG image data inflates past its raster.
    """
    if isinstance(data, RawFrame):
        rgb = decode_raw(data, max_bytes=max_bytes, max_pixels=max_pixels, max_aspect=max_aspect,
                         min_side=min_side)
        return np.ascontiguousarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)) if grey else rgb
    if not isinstance(data, bytes):
        data = bytes(data)
    info = probe(data, max_bytes=max_bytes, max_pixels=max_pixels, max_aspect=max_aspect, min_side=min_side,
                 formats=formats)
    if info.format == "png":
        _png_check_inflate(data)
    elif info.format == "jpeg":
        _jpeg_check_scan_data(data)
    # IMREAD_COLOR_RGB: BGR->RGB inside the codec, grey/alpha to 3 channels, EXIF orientation applied.
    # For PNG also ask for 16-bit samples (IMREAD_ANYDEPTH keeps the orientation handling) so that 16-bit
    # files are scaled with rounding below instead of OpenCV's truncating `>> 8`. Only PNG: a 12-bit JPEG
    # would come back as 0..4095 in uint16 and need another scale.
    flags = cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR_RGB
    if info.format == "png":
        flags |= cv2.IMREAD_ANYDEPTH
    try:
        rgb = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as e:  # OpenCV's own pixel guard (OPENCV_IO_MAX_IMAGE_PIXELS) or a codec assertion
        if "MAX_IMAGE_PIXELS" in str(e):
            raise ImageError("too-many-pixels",
                             f"image has {info.width}x{info.height} = {info.width * info.height} pixels, "
                             "more than OpenCV's limit (OPENCV_IO_MAX_IMAGE_PIXELS, set before cv2 is "
                             "imported)", format=info.format, width=info.width, height=info.height) from e
        raise ImageError("not-an-image",
                         f"OpenCV refused the {_FORMAT_NAMES[info.format]} image "
                         f"({info.width}x{info.height}): {str(e).strip().splitlines()[-1]}",
                         format=info.format, width=info.width, height=info.height) from e
    if rgb is None or rgb.size == 0:
        raise ImageError("not-an-image",
                         f"corrupt {_FORMAT_NAMES[info.format]} image: its header is valid "
                         f"({info.width}x{info.height}) but OpenCV could not decode the pixel data",
                         format=info.format, width=info.width, height=info.height)
    if rgb.dtype == np.uint16:
        rgb = cv2.convertScaleAbs(rgb, alpha=255.0 / 65535.0)  # round(v / 257), saturating
    elif rgb.dtype != np.uint8:  # not expected from these four codecs; refuse rather than guess a scale
        raise ImageError("not-an-image", f"unexpected decoded sample type {rgb.dtype}", format=info.format)
    if rgb.ndim == 2 and not grey:
        rgb = cv2.cvtColor(rgb, cv2.COLOR_GRAY2RGB)
    return np.ascontiguousarray(rgb)

