"""Image bytes -> 8-bit RGB -> normalised network input (docs/design/science.md §6 "Front end",
Preprocessing).

The one place that knows image formats. Everything is OpenCV + NumPy: no torchvision, no PIL.

Decoding follows the order of work of docs/design/service.md §1.2 and §3, so a hostile upload costs almost
nothing before it is refused: byte limit -> magic bytes (JPEG, PNG, BMP, WebP; everything else is refused
before OpenCV sees it, which keeps OpenCV's many other codecs out of reach) -> width and height read from the
header by small pure-Python parsers -> pixel cap and aspect-ratio cap -> a structural completeness check
(truncated uploads are refused rather than decoded into half-grey frames) -> a decoding-cost check ->
`cv2.imdecode`.

Decoding cost is bounded by the declared raster, not only by the byte limit: a 10 MB PNG can hold ~10 GB
of deflated zeros (libpng inflates all of it, ~25 s), and a 300 kB progressive JPEG thousands of empty
scans over a 25-megapixel frame (~100 s). So the header walk refuses PNG image data larger than its
raster could need compressed and JPEGs with more than `JPEG_MAX_SCANS` scans (both cheap, before
anything is queued), and `decode` inflates the PNG data once with a bounded decompressor that stops at
the raster's exact size, so no upload costs more than a legitimate image of its declared size. These
parsers stay ours rather than Pillow's lazy `open`: Pillow's bomb guard is a pixel count (the cap we
already check) and says nothing about compression ratios or scan counts, and a second codec library
would be more attack surface than these few hundred lines.

Preprocessing reproduces torchvision's `Resize(256)` + `CenterCrop(224)` + `ToTensor` + `Normalize`
geometry and arithmetic (docs/design/science.md §6), with OpenCV's `INTER_AREA` standing in for antialiased
bilinear when shrinking, plus the `squash` mode (straight to 224×224).

Example:
    >>> rgb = decode(open("frame.jpg", "rb").read())      # (H, W, 3) uint8 RGB
    >>> x = preprocess_batch([rgb], mode="crop")           # (1, 3, 224, 224) float32
"""

from __future__ import annotations

import os

# OpenCV's own decompression-bomb guard, read once when cv2 is loaded (docs/design/service.md §3: "set to the
# same value before OpenCV is imported"). It is the second line of defence behind the header check below;
# setdefault so that a deployment (or a test) that sets it first keeps its value. If cv2 was already
# imported elsewhere this is a harmless no-op.
os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", "25000000")

import re
import struct
import zlib
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import cv2
import numpy as np

__all__ = [
    "DEFAULT_MAX_ASPECT",
    "DEFAULT_MAX_BYTES",
    "DEFAULT_MAX_PIXELS",
    "ERROR_CODES",
    "FORMATS",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "JPEG_MAX_SCANS",
    "MODES",
    "ImageError",
    "ImageInfo",
    "decode",
    "preprocess",
    "preprocess_batch",
    "probe",
    "sniff",
]

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
DEFAULT_MAX_BYTES = 10 * 2**20
DEFAULT_MAX_PIXELS = 25_000_000
# docs/design/service.md §1.2: "long side more than 16× the short side" is a degenerate image. The cap also
# bounds the Resize(256) intermediate: a 1×4000 upload would otherwise become a 256×1,024,000 array (786 MB).
DEFAULT_MAX_ASPECT = 16.0

FORMATS = ("jpeg", "png", "bmp", "webp")
MODES = ("crop", "squash")
ERROR_CODES = frozenset(
    {"empty", "too-large", "not-an-image", "truncated", "too-many-pixels", "unsupported-format", "degenerate",
     "bomb"}
)

_FORMAT_NAMES = {"jpeg": "JPEG", "png": "PNG", "bmp": "BMP", "webp": "WebP"}


class ImageError(ValueError):
    """An upload that is not a decodable image within the limits.

    The HTTP service maps `code` to a 4xx problem+json (docs/design/service.md §2): `too-large` -> 413
    payload-too-large, `too-many-pixels` -> 413 image-too-large, `unsupported-format` -> 415,
    `degenerate` -> 422 degenerate-image, `bomb` -> 422 decompression-bomb, `empty` / `not-an-image` /
    `truncated` -> 422 undecodable-image.

    Attributes:
        code: one of `ERROR_CODES`: "empty", "too-large", "not-an-image", "truncated", "too-many-pixels",
            "unsupported-format", "degenerate", "bomb" (a small file whose decoding would cost far more
            than its declared size needs: PNG data that inflates past its raster, a JPEG with too many
            progressive scans).
        message: the human sentence, also `str(error)`.
        details: the numbers behind the message, for problem+json members (e.g. `width`, `height`,
            `max_pixels`; `received_bytes`, `max_bytes`; `detected`; `format`).
    """

    def __init__(self, code: str, message: str, **details: Any) -> None:
        if code not in ERROR_CODES:
            raise ValueError(f"unknown ImageError code {code!r}")
        super().__init__(message)
        self.code = code
        self.message = message
        self.details = details

    def __repr__(self) -> str:
        return f"ImageError({self.code!r}, {self.message!r})"


@dataclass(frozen=True)
class ImageInfo:
    """What the header says, read without decoding.

    Attributes:
        format: "jpeg", "png", "bmp" or "webp".
        width: stored width in pixels (before any EXIF rotation, which may swap it with height).
        height: stored height in pixels.
    """

    format: str
    width: int
    height: int

    @property
    def pixels(self) -> int:
        return self.width * self.height


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
# Each returns a `_Header`. They raise ImageError("truncated") when the file ends before the dimensions,
# ImageError("not-an-image") when the structure is corrupt. `complete` says whether the file reaches its
# end marker and `costly` holds a "bomb" error; both are reported separately so that the pixel cap is
# checked first (a tiny file that claims 20000×20000 is "too-many-pixels", whatever follows its header).


class _Header(NamedTuple):
    width: int
    height: int
    complete: bool
    costly: ImageError | None = None  # raised by `probe` after the size and completeness checks


_JPEG_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
# Inside entropy-coded data 0xFF is byte-stuffed (FF 00) and restart markers FF D0..D7 may occur; any
# other FF xx (xx not FF, a fill byte) is a real marker that ends the scan.
_JPEG_SCAN_END = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")


def _truncated(fmt: str, detail: str, n: int) -> ImageError:
    return ImageError("truncated", f"{_FORMAT_NAMES[fmt]} image is truncated: {detail} ({n} bytes received)",
                      format=fmt, received_bytes=n)


def _corrupt(fmt: str, detail: str) -> ImageError:
    return ImageError("not-an-image", f"corrupt {_FORMAT_NAMES[fmt]} image: {detail}", format=fmt)


def _jpeg_header(data: bytes) -> _Header:
    """Walk the JPEG marker segments: SOFn gives the size; EOI (FF D9) must follow the last scan.

    Walking segments (rather than looking for FF D9 anywhere) matters because an EXIF thumbnail is a
    whole JPEG, EOI included, inside the APP1 segment of a truncated file. Progressive files have
    several scans; each scan's entropy-coded data is skipped with one C-level regex search. Scans are
    counted: libjpeg walks every block of the frame once per scan, even for an empty one.
    """
    n = len(data)
    size: tuple[int, int] | None = None
    pos = 2  # after SOI
    segments = 0
    scans = 0
    while True:
        segments += 1
        if segments > _JPEG_MAX_SEGMENTS:
            # Real files have tens of segments; millions of empty ones only cost time under the GIL.
            raise _corrupt("jpeg", f"more than {_JPEG_MAX_SEGMENTS} marker segments")
        if pos < n and data[pos] != 0xFF:
            # Garbage between segments: libjpeg skips it with a warning, so do we.
            pos = data.find(b"\xff", pos)
            if pos < 0:
                pos = n
        m_fill = _JPEG_FILL.match(data, pos)  # fill bytes, skipped in C rather than one by one
        if m_fill:
            pos = m_fill.end()
        if pos >= n:
            break
        marker = data[pos]
        pos += 1
        if marker == 0xD9:  # EOI
            if size is None:
                raise _corrupt("jpeg", "end-of-image marker before any frame header (SOF)")
            return _Header(size[0], size[1], True, _jpeg_scans_error(scans, size))
        if marker in (0x00, 0x01, 0xD8) or 0xD0 <= marker <= 0xD7:  # standalone markers carry no length
            continue
        if pos + 2 > n:
            break
        length = int.from_bytes(data[pos:pos + 2], "big")
        if length < 2:
            raise _corrupt("jpeg", f"segment FF {marker:02X} has an invalid length {length}")
        seg_end = pos + length
        if marker in _JPEG_SOF and size is None:
            if pos + 7 > n:
                break
            height, width = struct.unpack_from(">HH", data, pos + 3)
            if width == 0:
                raise _corrupt("jpeg", "frame header gives width 0")
            if height == 0:
                # Height defined later by a DNL marker: legal, practically unused, and libjpeg refuses it.
                raise ImageError("unsupported-format",
                                 "JPEG images whose height is set by a DNL marker are not supported",
                                 detected="JPEG (DNL)")
            size = (width, height)
        if marker == 0xDA:  # SOS: header segment, then entropy-coded data up to the next real marker
            if size is None:
                raise _corrupt("jpeg", "scan (SOS) before any frame header (SOF)")
            scans += 1
            if scans > JPEG_MAX_SCANS:  # stop walking: the answer is known
                return _Header(size[0], size[1], True, _jpeg_scans_error(scans, size))
            m = _JPEG_SCAN_END.search(data, seg_end)
            if m is None:
                pos = n
                break
            pos = m.start()
            continue
        pos = seg_end
    if size is None:
        raise _truncated("jpeg", "the file ends before the frame header (SOF) that gives its size", n)
    return _Header(size[0], size[1], False)


_JPEG_FILL = re.compile(rb"\xff+")
_JPEG_MAX_SEGMENTS = 4096
#: Scans per JPEG at most. Encoders write 1 (baseline) to about 10 (libjpeg's progressive script; mozjpeg's
#: optimised ones are of that order); each extra scan costs a pass over every block of the frame, ~23 ms
#: at 25 megapixels here, so 4,000 empty scans in 300 kB held the encoder for 100 s.
JPEG_MAX_SCANS = 32


def _jpeg_scans_error(scans: int, size: tuple[int, int]) -> ImageError | None:
    if scans <= JPEG_MAX_SCANS:
        return None
    return ImageError("bomb", f"JPEG image has more than {JPEG_MAX_SCANS} scans; each one costs a pass over "
                      f"the whole {size[0]}x{size[1]} frame", format="jpeg", width=size[0], height=size[1],
                      max_scans=JPEG_MAX_SCANS)


# Colour type -> samples per pixel, and the bit depths the PNG specification allows with it.
_PNG_COLOUR_TYPES = {0: (1, (1, 2, 4, 8, 16)), 2: (3, (8, 16)), 3: (1, (1, 2, 4, 8)), 4: (2, (8, 16)),
                     6: (4, (8, 16))}
# Adam7 passes: first column, first row, column step, row step.
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))
# Real files have a handful of chunks plus IDATs of 8-64 kB (libpng writes 8 kB: 1,280 for 10 MB); the
# cap keeps the Python walk under ~20 ms.
_PNG_MAX_CHUNKS = 16384
_INFLATE_STEP = 1 << 22


@dataclass(frozen=True)
class _PngLayout:
    """What the chunk walk found: the raster and where its compressed data lies."""

    width: int
    height: int
    raster_bytes: int  # exact size of the filtered scanlines the IDAT stream must inflate to
    idat: tuple[tuple[int, int], ...]  # (start, end) of each IDAT chunk's data
    complete: bool  # the walk reached IEND


def _png_raster_bytes(width: int, height: int, bits_per_pixel: int, interlaced: bool) -> int:
    """Filtered scanline bytes: one filter byte plus the packed pixels per row, per Adam7 pass if any."""
    def rows(w: int, h: int) -> int:
        return h * (1 + (w * bits_per_pixel + 7) // 8) if w and h else 0

    if not interlaced:
        return rows(width, height)
    return sum(rows(max(0, -(-(width - x0) // dx)), max(0, -(-(height - y0) // dy)))
               for x0, y0, dx, dy in _ADAM7)


def _png_layout(data: bytes) -> _PngLayout:
    """Walk the chunks: IHDR first (size, depth, colour type, interlace), then every IDAT, up to IEND."""
    n = len(data)
    if n < 33:  # signature 8 + length 4 + type 4 + IHDR data 13 + CRC 4
        raise _truncated("png", "the file ends inside the IHDR header", n)
    length, ctype = struct.unpack_from(">I4s", data, 8)
    if ctype != b"IHDR" or length != 13:
        raise _corrupt("png", "the first chunk is not a 13-byte IHDR")
    width, height, depth, colour, compression, filtering, interlace = struct.unpack_from(">IIBBBBB", data, 16)
    if width == 0 or height == 0 or width > 2**31 - 1 or height > 2**31 - 1:
        raise _corrupt("png", f"IHDR gives an invalid size {width}x{height}")
    samples, depths = _PNG_COLOUR_TYPES.get(colour, (0, ()))
    if depth not in depths or compression != 0 or filtering != 0 or interlace > 1:
        raise _corrupt("png", f"IHDR gives an invalid format (bit depth {depth}, colour type {colour}, "
                              f"compression {compression}, filter {filtering}, interlace {interlace})")
    idat: list[tuple[int, int]] = []
    complete = False
    pos = 33
    unpack = struct.Struct(">I4s").unpack_from
    for _ in range(_PNG_MAX_CHUNKS):
        if pos + 8 > n:
            break
        length, ctype = unpack(data, pos)
        if ctype == b"IDAT":
            idat.append((pos + 8, min(pos + 8 + length, n)))
        elif ctype == b"IEND":
            complete = pos + 12 + length <= n
            break
        pos += 12 + length  # length, type, data, CRC
    else:
        raise _corrupt("png", f"more than {_PNG_MAX_CHUNKS} chunks")
    raster = _png_raster_bytes(width, height, samples * depth, bool(interlace))
    return _PngLayout(width, height, raster, tuple(idat), complete)


def _png_deflate_bound(raster_bytes: int) -> int:
    """Most compressed bytes a raster this size can take: stored deflate blocks add 5 bytes per 64 kB,
    fixed Huffman codes at most 1/8; a quarter plus 64 kB leaves room for odd encoders."""
    return raster_bytes + raster_bytes // 4 + 65536


def _png_header(data: bytes) -> _Header:
    """IHDR must be the first chunk; complete if the walk reaches IEND; costly if the compressed image
    data is larger than its raster could need (the inflated bytes would be thrown away, after costing
    ~2.5 s per GB)."""
    png = _png_layout(data)
    compressed = sum(end - start for start, end in png.idat)
    costly = None
    if compressed > _png_deflate_bound(png.raster_bytes):
        costly = ImageError("bomb", f"PNG image data is {compressed} bytes compressed, more than a "
                            f"{png.width}x{png.height} image could need ({png.raster_bytes} bytes "
                            "uncompressed)", format="png", width=png.width, height=png.height,
                            compressed_bytes=compressed, raster_bytes=png.raster_bytes)
    return _Header(png.width, png.height, png.complete, costly)


def _png_check_inflate(data: bytes) -> None:
    """Inflate the IDAT stream once with a bounded decompressor: it must end at the raster's exact size.

    libpng inflates the whole stream, also what follows the last row, so the cost of `cv2.imdecode` is
    set by the stream, not by the image; here at most `raster_bytes` + 4 MB are inflated (in 4 MB
    steps, never held), which is what a legitimate image of the declared size costs anyway (about as
    much again as OpenCV's own decode of a PNG: ~10 ms at 640x480).

    Raises:
        ImageError: "bomb" when the stream inflates past the raster, "not-an-image" when it is not
            valid zlib data or ends short of the raster.
    """
    png = _png_layout(data)
    z = zlib.decompressobj()
    produced = 0
    view = memoryview(data)
    try:
        for start, end in png.idat:
            pending = view[start:end]
            while pending and not z.eof:
                produced += len(z.decompress(pending, _INFLATE_STEP))
                if produced > png.raster_bytes:
                    raise ImageError("bomb", f"PNG image data inflates past the {png.raster_bytes} bytes of "
                                     f"its {png.width}x{png.height} raster", format="png", width=png.width,
                                     height=png.height, raster_bytes=png.raster_bytes)
                pending = z.unconsumed_tail
            if z.eof:
                break
    except zlib.error as e:
        raise _corrupt("png", f"image data is not a valid zlib stream ({e})") from e
    if not z.eof or produced != png.raster_bytes:
        raise _corrupt("png", f"image data inflates to {produced} bytes, its raster needs "
                              f"{png.raster_bytes}")


_BMP_BIT_DEPTHS = frozenset({1, 2, 4, 8, 16, 24, 32})


def _bmp_header(data: bytes) -> _Header:
    """BITMAPFILEHEADER + core (12-byte) or info (40+ byte) header; complete if the pixel array fits."""
    n = len(data)
    if n < 18:
        raise _truncated("bmp", "the file ends inside the file header", n)
    (offbits,) = struct.unpack_from("<I", data, 10)
    (dib_size,) = struct.unpack_from("<I", data, 14)
    if dib_size == 12:  # BITMAPCOREHEADER (OS/2 1.x): unsigned 16-bit sizes, never compressed
        if n < 26:
            raise _truncated("bmp", "the file ends inside the bitmap header", n)
        width, height, _planes, bpp = struct.unpack_from("<HHHH", data, 18)
        compression, size_image = 0, 0
    elif 40 <= dib_size <= 124:  # BITMAPINFOHEADER and its V2..V5 extensions
        if n < 14 + 40:
            raise _truncated("bmp", "the file ends inside the bitmap header", n)
        width, height, _planes, bpp, compression, size_image = struct.unpack_from("<iiHHII", data, 18)
        height = abs(height)  # negative height = top-down rows
    else:
        raise _corrupt("bmp", f"unknown bitmap header size {dib_size}")
    if width <= 0 or height <= 0:
        raise _corrupt("bmp", f"header gives an invalid size {width}x{height}")
    if bpp not in _BMP_BIT_DEPTHS:
        raise _corrupt("bmp", f"unsupported bit depth {bpp}")
    if compression in (4, 5):
        raise ImageError("unsupported-format", "BMP files that wrap a JPEG or PNG stream are not supported",
                         detected="BMP (embedded JPEG/PNG)")
    if compression in (0, 3, 6):  # BI_RGB, BI_BITFIELDS, BI_ALPHABITFIELDS: rows padded to 4 bytes
        need = offbits + ((width * bpp + 31) // 32) * 4 * height
    elif compression in (1, 2):  # RLE8 / RLE4: biSizeImage is the compressed size
        need = offbits + size_image
    else:
        raise _corrupt("bmp", f"unknown compression {compression}")
    return _Header(width, height, n >= need)


def _webp_header(data: bytes) -> _Header:
    """RIFF container; the first chunk is VP8 (lossy), VP8L (lossless) or VP8X (extended)."""
    n = len(data)
    if n < 30:  # RIFF header 12 + chunk header 8 + the 10 bytes that hold the size in every variant
        raise _truncated("webp", "the file ends inside the header", n)
    (riff_size,) = struct.unpack_from("<I", data, 4)
    fourcc = data[12:16]
    if fourcc == b"VP8 ":
        if data[23:26] != b"\x9d\x01\x2a":
            raise _corrupt("webp", "VP8 frame without its start code")
        w, h = struct.unpack_from("<HH", data, 26)
        width, height = w & 0x3FFF, h & 0x3FFF  # the top 2 bits are upscaling hints
    elif fourcc == b"VP8L":
        if data[20] != 0x2F:
            raise _corrupt("webp", "VP8L stream without its signature byte")
        (bits,) = struct.unpack_from("<I", data, 21)
        width, height = (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    elif fourcc == b"VP8X":
        width = int.from_bytes(data[24:27], "little") + 1
        height = int.from_bytes(data[27:30], "little") + 1
    else:
        raise _corrupt("webp", f"unknown first chunk {fourcc!r}")
    if width == 0 or height == 0:
        raise _corrupt("webp", f"header gives an invalid size {width}x{height}")
    return _Header(width, height, n >= 8 + riff_size)


_HEADER_PARSERS = {"jpeg": _jpeg_header, "png": _png_header, "bmp": _bmp_header, "webp": _webp_header}


# ---------------------------------------------------------------------------------------------- decoding


def _accepted_list(formats: Collection[str]) -> str:
    names = [_FORMAT_NAMES[f] for f in FORMATS if f in formats]
    return ", ".join(names[:-1]) + " or " + names[-1] if len(names) > 1 else names[0]


def probe(data: bytes, *, max_bytes: int = DEFAULT_MAX_BYTES, max_pixels: int = DEFAULT_MAX_PIXELS,
          max_aspect: float | None = DEFAULT_MAX_ASPECT, formats: Collection[str] = FORMATS) -> ImageInfo:
    """Every check `decode` makes, without decoding a pixel (docs/design/service.md §1.2 order of work).

    Args:
        data: the uploaded bytes.
        max_bytes: refuse longer inputs ("too-large").
        max_pixels: refuse images whose header gives width × height above this ("too-many-pixels").
        max_aspect: refuse images whose long side exceeds `max_aspect` × the short side ("degenerate");
            None disables the check.
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

    width, height, complete, costly = _HEADER_PARSERS[fmt](data)
    if width * height > max_pixels:
        raise ImageError("too-many-pixels",
                         f"image has {width}x{height} = {width * height} pixels, "
                         f"more than the limit of {max_pixels}",
                         width=width, height=height, max_pixels=max_pixels, format=fmt)
    if max_aspect is not None and max(width, height) > max_aspect * min(width, height):
        raise ImageError("degenerate",
                         f"image is {width}x{height}: its long side is more than {max_aspect:g} times "
                         f"its short side",
                         width=width, height=height, max_aspect=max_aspect, format=fmt)
    if not complete:
        end = {"jpeg": "no end-of-image marker (FF D9) after the last scan",
               "png": "no IEND chunk",
               "bmp": "the pixel array is shorter than the header says",
               "webp": "shorter than its RIFF header says"}[fmt]
        raise _truncated(fmt, end, n)
    if costly is not None:
        raise costly
    return ImageInfo(fmt, width, height)


def decode(data: bytes, *, max_bytes: int = DEFAULT_MAX_BYTES, max_pixels: int = DEFAULT_MAX_PIXELS,
           max_aspect: float | None = DEFAULT_MAX_ASPECT, formats: Collection[str] = FORMATS) -> np.ndarray:
    """Decode an uploaded JPEG, PNG, BMP or WebP to 8-bit RGB (docs/design/science.md §6).

    Grey images are replicated to three channels, alpha is dropped (not composited), 16-bit PNGs are
    scaled to 8 bits with rounding (v × 255 / 65535), and the EXIF orientation is applied, as OpenCV's
    `IMREAD_COLOR` does. All of `probe`'s checks run first, so nothing is decoded past a limit.

    Args:
        data: the uploaded bytes.
        max_bytes: byte limit ("too-large").
        max_pixels: pixel cap, checked on the header before decoding ("too-many-pixels").
        max_aspect: long side / short side limit ("degenerate"); None disables it.
        formats: accepted formats, a subset of `FORMATS`.

    Returns:
        (H, W, 3) uint8 RGB, C-contiguous; H and W after the EXIF rotation.

    Raises:
        ImageError: see `probe`; also "not-an-image" when OpenCV cannot decode a structurally complete
            file (corrupt data), "bomb" when PNG image data inflates past its raster.
    """
    if not isinstance(data, bytes):
        data = bytes(data)
    info = probe(data, max_bytes=max_bytes, max_pixels=max_pixels, max_aspect=max_aspect, formats=formats)
    if info.format == "png":
        _png_check_inflate(data)
    # IMREAD_COLOR_RGB: BGR->RGB inside the codec, grey/alpha to 3 channels, EXIF orientation applied.
    # For PNG also ask for 16-bit samples (IMREAD_ANYDEPTH keeps the orientation handling) so that 16-bit
    # files are scaled with rounding below instead of OpenCV's truncating `>> 8`. Only PNG: a 12-bit JPEG
    # would come back as 0..4095 in uint16 and need another scale.
    flags = cv2.IMREAD_COLOR_RGB
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
    if rgb.ndim == 2:
        rgb = cv2.cvtColor(rgb, cv2.COLOR_GRAY2RGB)
    return np.ascontiguousarray(rgb)


# ------------------------------------------------------------------------------------------ preprocessing


def _resize(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize with INTER_AREA on shrinking axes and INTER_LINEAR on enlarging ones
    (docs/design/science.md §6).

    INTER_AREA is the antialiased choice when shrinking (a box filter; torchvision's bilinear with
    antialias=True is a triangle filter, close to it); INTER_LINEAR when enlarging, where INTER_AREA
    degenerates towards nearest neighbour. Aspect-preserving resizes move both axes the same way; a
    squash may shrink one and enlarge the other, and then each axis gets its own pass.
    """
    h, w = img.shape[:2]
    if (w, h) == (width, height):
        return img
    if width <= w and height <= h:
        return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
    if width >= w and height >= h:
        return cv2.resize(img, (width, height), interpolation=cv2.INTER_LINEAR)
    if width < w:
        img = cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
    else:
        img = cv2.resize(img, (w, height), interpolation=cv2.INTER_AREA)
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_LINEAR)


def _fit(rgb: np.ndarray, mode: str, size: int, resize: int) -> np.ndarray:
    """(size, size, 3) uint8: Resize(resize) + CenterCrop(size), or a straight squash to size × size."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got shape {rgb.shape} dtype {rgb.dtype}")
    if mode == "squash":
        return _resize(rgb, size, size)
    h, w = rgb.shape[:2]
    # torchvision Resize(int): the short side becomes `resize`, the long side int(resize * long / short),
    # computed in floating point exactly as torchvision's _compute_resized_output_size does.
    if w <= h:
        new_w, new_h = resize, int(resize * h / w)
    else:
        new_w, new_h = int(resize * w / h), resize
    img = _resize(rgb, new_w, new_h)
    # torchvision CenterCrop: int(round(...)), Python's round-half-to-even (16.5 -> 16, 17.5 -> 18).
    top = round((new_h - size) / 2.0)  # round() of a float is already an int
    left = round((new_w - size) / 2.0)
    return img[top:top + size, left:left + size]


def _check_params(mode: str, size: int, resize: int, mean: Sequence[float],
                  std: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if size < 1:
        raise ValueError(f"size must be positive, got {size}")
    if mode == "crop" and resize < size:
        raise ValueError(f"resize ({resize}) must be at least size ({size}) in crop mode")
    m = np.asarray(mean, dtype=np.float32).reshape(-1)
    s = np.asarray(std, dtype=np.float32).reshape(-1)
    if m.shape != (3,) or s.shape != (3,):
        raise ValueError(f"mean and std need 3 values each, got {tuple(mean)} and {tuple(std)}")
    if np.any(s == 0):
        raise ValueError(f"std must be nonzero, got {tuple(std)}")
    return m.reshape(1, 3, 1, 1), s.reshape(1, 3, 1, 1)


def preprocess_batch(images: Sequence[np.ndarray], mode: str = "crop", size: int = 224,
                     mean: Sequence[float] = IMAGENET_MEAN, std: Sequence[float] = IMAGENET_STD,
                     resize: int = 256) -> np.ndarray:
    """Network input for a batch of decoded images (docs/design/science.md §6, Preprocessing).

    Per image: "crop" = Resize(`resize`) (short side to `resize`, long side int(resize·long/short)) then
    CenterCrop(`size`) with top = round((h−size)/2), left = round((w−size)/2); "squash" = resize straight
    to size × size (keeps the whole field of view; matters for tiny frames, e.g. 64×32 Nordland images
    lose 56 % of their width to the centre crop). Then, for the whole batch at once and in float32 as
    torchvision's ToTensor + Normalize: x / 255, − mean, / std per channel.

    Args:
        images: N (H_i, W_i, 3) uint8 RGB images (from `decode`); sizes may differ.
        mode: "crop" or "squash" (part of the encoder identity).
        size: output side (224).
        mean: per-channel mean of the [0, 1] input (ImageNet by default).
        std: per-channel standard deviation.
        resize: short side before the centre crop (256); ignored in "squash" mode.

    Returns:
        (N, 3, size, size) float32, C-contiguous (CHW per image, channels R, G, B).

    Raises:
        ValueError: an image is not (H, W, 3) uint8, or a parameter is invalid.
    """
    m, s = _check_params(mode, size, resize, mean, std)
    out = np.empty((len(images), 3, size, size), dtype=np.float32)
    for i, rgb in enumerate(images):
        # HWC uint8 -> CHW float32 in one casting copy into the batch buffer.
        out[i] = _fit(np.asarray(rgb), mode, size, resize).transpose(2, 0, 1)
    # Same float32 operations, in the same order, as ToTensor (div 255) and Normalize (sub, div).
    out /= np.float32(255.0)
    out -= m
    out /= s
    return out


def preprocess(rgb: np.ndarray, mode: str = "crop", size: int = 224,
               mean: Sequence[float] = IMAGENET_MEAN, std: Sequence[float] = IMAGENET_STD,
               resize: int = 256) -> np.ndarray:
    """Network input for one decoded image; see `preprocess_batch` for the steps (docs/design/science.md §6).

    Args:
        rgb: (H, W, 3) uint8 RGB.
        mode: "crop" or "squash".
        size: output side (224).
        mean: per-channel mean of the [0, 1] input.
        std: per-channel standard deviation.
        resize: short side before the centre crop (256).

    Returns:
        (3, size, size) float32, C-contiguous.
    """
    return preprocess_batch([rgb], mode=mode, size=size, mean=mean, std=std, resize=resize)[0]
