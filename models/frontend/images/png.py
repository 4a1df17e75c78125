"""PNG chunk walk and the bounded inflate check: size, completeness and decoding cost, without decoding
(docs/design/service.md §1.2)."""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

from models.frontend.images.common import ImageError, _corrupt, _Header, _truncated

# Colour type -> samples per pixel, and the bit depths the PNG specification allows with it.
_PNG_COLOUR_TYPES = {0: (1, (1, 2, 4, 8, 16)), 2: (3, (8, 16)), 3: (1, (1, 2, 4, 8)), 4: (2, (8, 16)),
                     6: (4, (8, 16))}
# Adam7 passes: first column, first row, column step, row step.
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))
# Real files have a handful of chunks plus IDATs of 8-64 kB (libpng writes 8 kB: 1,280 for 10 MB); the
# cap keeps the Python walk under ~20 ms.
_PNG_MAX_CHUNKS = 16384
_INFLATE_STEP = 1 << 22
# An animated PNG (APNG): its animation control, frame control and frame data chunks. The checks here
# judge the default image (IHDR, IDAT), but OpenCV decodes the first animation frame, from fdAT chunks
# they never see (an outside probe: a first frame that was a decompression bomb was learned as black).
_APNG_CHUNKS = frozenset({b"acTL", b"fcTL", b"fdAT"})


@dataclass(frozen=True)
class _PngLayout:
    """What the chunk walk found: the raster and where its compressed data lies."""

    width: int
    height: int
    raster_bytes: int  # exact size of the filtered scanlines the IDAT stream must inflate to
    bits_per_pixel: int  # samples x bit depth: up to 64 (16-bit RGBA)
    idat: tuple[tuple[int, int], ...]  # (start, end) of each IDAT chunk's data
    complete: bool  # the walk reached IEND


def _animated() -> ImageError:
    return ImageError("unsupported-format", "animated PNG (APNG) images are not supported; send a single "
                      "frame as a PNG without animation chunks (acTL, fcTL, fdAT)", detected="PNG (animated)")


def _png_raster_bytes(width: int, height: int, bits_per_pixel: int, interlaced: bool) -> int:
    """Filtered scanline bytes: one filter byte plus the packed pixels per row, per Adam7 pass if any."""
    def rows(w: int, h: int) -> int:
        return h * (1 + (w * bits_per_pixel + 7) // 8) if w and h else 0

    if not interlaced:
        return rows(width, height)
    return sum(rows(max(0, -(-(width - x0) // dx)), max(0, -(-(height - y0) // dy)))
               for x0, y0, dx, dy in _ADAM7)


def _png_layout(data: bytes) -> _PngLayout:
    """Walk the chunks: IHDR first (size, depth, colour type, interlace), then every IDAT, up to IEND.
    An animation chunk anywhere is refused ("unsupported-format"): a robot sends single frames."""
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
        if ctype in _APNG_CHUNKS:
            raise _animated()
        if ctype == b"IDAT":
            idat.append((pos + 8, min(pos + 8 + length, n)))
        elif ctype == b"IEND":
            complete = pos + 12 + length <= n
            break
        pos += 12 + length  # length, type, data, CRC
    else:
        raise _corrupt("png", f"more than {_PNG_MAX_CHUNKS} chunks")
    raster = _png_raster_bytes(width, height, samples * depth, bool(interlace))
    return _PngLayout(width, height, raster, samples * depth, tuple(idat), complete)


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
    return _Header(png.width, png.height, png.complete, costly, png.bits_per_pixel)


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

