"""Magic bytes and the checks before any decoding, in the order of docs/design/service.md §1.2: byte
limit, signature, header size, pixel and aspect caps and the minimum side, completeness (an RLE bitmap's
rows, a JPEG's scans), decoding cost."""

from __future__ import annotations

from collections.abc import Collection

from models.frontend.images.bmp_webp import _bmp_check_rle, _bmp_header, _webp_header
from models.frontend.images.common import (
    _FORMAT_NAMES,
    DEFAULT_MAX_ASPECT,
    DEFAULT_MAX_BYTES,
    DEFAULT_MAX_PIXELS,
    DEFAULT_MIN_SIDE,
    FORMATS,
    ImageError,
    ImageInfo,
    _check_shape,
    _truncated,
)
from models.frontend.images.jpeg import _jpeg_header
from models.frontend.images.png import _png_header
from models.frontend.images.raw import RawFrame, probe_raw
from models.frontend.limits import PIXEL_CAP_BYTES

# ----------------------------------------------------------------------------------------------- sniffing

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SIGNATURE = b"\xff\xd8\xff"

# Formats recognised only to say clearly that they are refused (OpenCV could decode several of them, but
# every extra codec is attack surface and none is in the contract).
_UNSUPPORTED_SIGNATURES = (
    (b"GIF87a", "GIF"),
    (b"GIF89a", "GIF"),
    (b"II*\x00", "TIFF"),
    (b"MM\x00*", "TIFF"),
    (b"II+\x00", "BigTIFF"),
    (b"MM\x00+", "BigTIFF"),
    (b"\x00\x00\x00\x0cjP  \r\n\x87\n", "JPEG 2000"),
    (b"\xff\x4f\xff\x51", "JPEG 2000"),
    (b"\xff\x0a", "JPEG XL"),
    (b"\x00\x00\x00\x0cJXL \r\n\x87\n", "JPEG XL"),
    (b"8BPS", "PSD"),
    (b"v/1\x01", "OpenEXR"),
    (b"#?RADIANCE", "Radiance HDR"),
    (b"#?RGBE", "Radiance HDR"),
    (b"qoif", "QOI"),
    (b"DDS ", "DDS"),
    (b"\x00\x00\x01\x00", "ICO"),
    (b"%PDF", "PDF"),
)
_HEIF_BRANDS = {b"heic": "HEIC", b"heix": "HEIC", b"hevc": "HEIC", b"heim": "HEIC", b"heis": "HEIC",
                b"mif1": "HEIF", b"msf1": "HEIF", b"avif": "AVIF", b"avis": "AVIF"}


def sniff(data: bytes) -> str | None:
    """The supported format the magic bytes announce, without any further check.

    Args:
        data: the uploaded bytes (only the first 12 are read).

    Returns:
        "jpeg", "png", "bmp", "webp", or None for anything else.
    """
    head = bytes(data[:12])
    if head.startswith(_JPEG_SIGNATURE):
        return "jpeg"
    if head.startswith(_PNG_SIGNATURE):
        return "png"
    if head.startswith(b"BM"):
        return "bmp"
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return "webp"
    return None


def _unsupported_name(head: bytes) -> str | None:
    """Human name of a recognised but refused format, or None."""
    for sig, name in _UNSUPPORTED_SIGNATURES:
        if head.startswith(sig):
            return name
    if head[4:8] == b"ftyp" and head[8:12] in _HEIF_BRANDS:
        return _HEIF_BRANDS[head[8:12]]
    if len(head) >= 3 and head[0:1] == b"P" and head[1:2] in b"1234567" and head[2:3] in b" \t\r\n":
        return "PNM"
    stripped = head.lstrip()
    if stripped.startswith((b"<?xml", b"<svg", b"<SVG")):
        return "SVG/XML"
    return None


def _is_signature_prefix(data: bytes) -> str | None:
    """Format whose signature `data` is a proper prefix of (a body cut within its magic bytes)."""
    if len(data) < len(_JPEG_SIGNATURE) and _JPEG_SIGNATURE.startswith(data):
        return "jpeg"
    if len(data) < len(_PNG_SIGNATURE) and _PNG_SIGNATURE.startswith(data):
        return "png"
    if len(data) < 12 and data.startswith(b"RIFF") and b"WEBP".startswith(data[8:12]):
        return "webp"
    return None


# ------------------------------------------------------------------------------------------ header parsers


_HEADER_PARSERS = {"jpeg": _jpeg_header, "png": _png_header, "bmp": _bmp_header, "webp": _webp_header}


# ---------------------------------------------------------------------------------------------- decoding


def _accepted_list(formats: Collection[str]) -> str:
    names = [_FORMAT_NAMES[f] for f in FORMATS if f in formats]
    return ", ".join(names[:-1]) + " or " + names[-1] if len(names) > 1 else names[0]


def probe(data: bytes | RawFrame, *, max_bytes: int = DEFAULT_MAX_BYTES, max_pixels: int = DEFAULT_MAX_PIXELS,
          max_aspect: float | None = DEFAULT_MAX_ASPECT, min_side: int | None = DEFAULT_MIN_SIDE,
          formats: Collection[str] = FORMATS) -> ImageInfo:
    """Every check `decode` makes, without decoding a pixel (docs/design/service.md §1.2 order of work).

    Args:
        data: the uploaded bytes, or a raw frame (`raw.probe_raw`: its format is "raw").
        max_bytes: refuse longer inputs ("too-large").
        max_pixels: refuse images whose header gives width × height above this ("too-many-pixels"), and
            a PNG whose pixels decode to more than `max_pixels` × `PIXEL_CAP_BYTES` bytes (16-bit or
            alpha samples: up to 8 bytes a pixel).
        max_aspect: refuse images whose long side exceeds `max_aspect` × the short side ("degenerate");
            None disables the check.
        min_side: refuse images whose short side is under `min_side` pixels ("degenerate"); None
            disables the check.
        formats: accepted formats, a subset of `FORMATS` (the service may narrow it to JPEG and PNG).

    Returns:
        The format and the stored width and height.

    Raises:
        ImageError: with `code` "empty", "too-large", "unsupported-format", "not-an-image", "truncated",
            "too-many-pixels", "degenerate" or "bomb".
    """
    unknown = set(formats) - set(FORMATS)
    if unknown or not formats:
        raise ValueError(f"formats must be a non-empty subset of {FORMATS}, got {tuple(formats)}")
    if isinstance(data, RawFrame):
        probe_raw(data, max_bytes=max_bytes, max_pixels=max_pixels, max_aspect=max_aspect, min_side=min_side)
        return ImageInfo("raw", data.width, data.height)
    if not isinstance(data, bytes):
        data = bytes(data)
    n = len(data)
    if n == 0:
        raise ImageError("empty", "image is empty (0 bytes)", received_bytes=0)
    if n > max_bytes:
        raise ImageError("too-large", f"image is {n} bytes, more than the limit of {max_bytes} bytes",
                         received_bytes=n, max_bytes=max_bytes)

    fmt = sniff(data)
    if fmt is None:
        head = data[:16]
        prefix_of = _is_signature_prefix(data)
        if prefix_of is not None:
            raise _truncated(prefix_of, "the file ends inside its signature", n)
        name = _unsupported_name(head)
        if name is not None:
            raise ImageError("unsupported-format",
                             f"{name} images are not supported; send {_accepted_list(formats)}",
                             detected=name)
        # No known signature at all: the upload is of an unsupported kind (docs/design/service.md §2: 415), as
        # opposed to a recognised image whose contents are corrupt (422).
        raise ImageError("unsupported-format",
                         f"data is not a {_accepted_list(formats)} image (first bytes: {head[:8].hex(' ')})",
                         detected=None)
    if fmt not in formats:
        raise ImageError("unsupported-format",
                         f"{_FORMAT_NAMES[fmt]} images are not accepted here; send {_accepted_list(formats)}",
                         detected=_FORMAT_NAMES[fmt])

    width, height, complete, costly, bits, damaged = _HEADER_PARSERS[fmt](data)
    if width * height > max_pixels:
        raise ImageError("too-many-pixels",
                         f"image has {width}x{height} = {width * height} pixels, "
                         f"more than the limit of {max_pixels}",
                         width=width, height=height, max_pixels=max_pixels, format=fmt)
    if bits is not None and width * height * bits > max_pixels * PIXEL_CAP_BYTES * 8:
        # A flat 16-bit RGBA PNG at the pixel cap held the decode threads of every map for seconds
        # (`cortexloc bench hostile`, png_5000x5000_rgba16_flat): the cap is sized for 3 bytes a pixel,
        # and the decode costs by the bytes.
        raster = width * height * bits // 8
        raise ImageError("too-many-pixels",
                         f"image has {width}x{height} pixels of {bits} bits = {raster} bytes decoded, more "
                         f"than the limit of {max_pixels * PIXEL_CAP_BYTES} ({max_pixels} pixels of "
                         f"{PIXEL_CAP_BYTES} bytes)", width=width, height=height, max_pixels=max_pixels,
                         bits_per_pixel=bits, format=fmt)
    _check_shape(width, height, fmt, max_aspect, min_side)
    if not complete:
        end = {"jpeg": "no end-of-image marker (FF D9) after the last scan",
               "png": "no IEND chunk",
               "bmp": "the pixel array is shorter than the header says",
               "webp": "shorter than its RIFF header says"}[fmt]
        raise _truncated(fmt, end, n)
    if fmt == "bmp":
        _bmp_check_rle(data)  # after the caps: its walk takes a turn per row
    if damaged is not None:
        raise damaged
    if costly is not None:
        raise costly
    return ImageInfo(fmt, width, height)
