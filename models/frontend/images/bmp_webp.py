"""BMP and WebP headers: size and completeness, without decoding (docs/design/service.md §1.2)."""

from __future__ import annotations

import re
import struct

from models.frontend.images.common import ImageError, _corrupt, _Header, _truncated

_BMP_BIT_DEPTHS = frozenset({1, 2, 4, 8, 16, 24, 32})


def _bmp_header(data: bytes) -> _Header:
    """BITMAPFILEHEADER + core (12-byte) or info (40+ byte) header; complete if the pixel array fits (an
    RLE bitmap's rows are walked after the caps, `_bmp_check_rle`)."""
    offbits, width, height, bpp, compression, size_image = _bmp_fields(data)
    n = len(data)
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


def _bmp_fields(data: bytes) -> tuple[int, int, int, int, int, int]:
    """The headers' pixel offset, width, height (its magnitude: negative is top-down), bit depth,
    compression and biSizeImage."""
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
    return offbits, width, height, bpp, compression, size_image


def _rle_row(nibbles: bool) -> re.Pattern[bytes]:
    """What may stand inside one row of an RLE8 (RLE4: `nibbles`) bitmap, matched in C: encoded runs
    (count > 0, value), a delta that stays in the row (00 02 dx 00) and absolute runs (00, count >= 3,
    the pixels padded to 16 bits; grouped by their padded length, shortest first, so the regex tries
    about one alternative per 2 bytes of a run). Not: an end of line (00 00), a delta down, an end of
    bitmap (00 01)."""
    lengths: dict[int, list[int]] = {}
    for count in range(3, 256):
        size = (count + 1) // 2 if nibbles else count
        lengths.setdefault(size + (size & 1), []).append(count)
    runs = b"|".join(b"[%s-%s].{%d}" % (re.escape(bytes([c[0]])), re.escape(bytes([c[-1]])), size)
                     for size, c in sorted(lengths.items()))
    return re.compile(rb"(?:[\x01-\xff].|\x00(?:\x02.\x00|" + runs + rb"))*", re.DOTALL)


_RLE8_ROW = _rle_row(nibbles=False)
_RLE4_ROW = _rle_row(nibbles=True)


def _bmp_check_rle(data: bytes) -> None:
    """Refuse an RLE8/RLE4 bitmap whose data ends (end of bitmap, or of the file) before its last row.

    A bitmap cut part way with an end of bitmap (00 01) appended, biSizeImage 0, is whole by its header,
    and OpenCV returns it with the missing rows black (an outside probe).
    The walk counts rows: each ends with an end of line (00 00) or is passed by a delta down (00 02 dx
    dy); by the time the data stops, all rows but the last must be ended. The last may end with the end
    of bitmap itself (encoders write it without an end of line), so a cut inside the last row, at most
    a row, goes unseen. Run after the pixel and aspect caps: one Python turn per row (a regex skips the
    runs within one), so a header's claimed height costs no more than the caps allow, and the walk is
    one pass over the file's bytes.

    Raises:
        ImageError: "truncated".
    """
    offbits, _width, height, _bpp, compression, _size = _bmp_fields(data)
    if compression not in (1, 2):
        return
    row = _RLE4_ROW if compression == 2 else _RLE8_ROW
    n, pos, rows = len(data), offbits, 0
    while rows < height:  # each turn ends a row or more, or stops the walk
        pos = row.match(data, pos).end()
        escape = data[pos:pos + 2]
        if escape == b"\x00\x00":  # end of line
            rows, pos = rows + 1, pos + 2
        elif escape == b"\x00\x02" and pos + 4 <= n:  # a delta down (one that stays in the row was matched)
            rows, pos = rows + data[pos + 3], pos + 4
        else:  # end of bitmap, the end of the data, or a run the data cuts short
            break
    if rows < height - 1:
        raise _truncated("bmp", f"its RLE data ends in row {rows + 1} of {height}", n)


# An extended (VP8X) WebP's flags: bit 1 says the file is an animation (ANIM, then one ANMF chunk per
# frame). OpenCV decodes an animation's first frame, which the checks here never judged: a robot sends
# single frames, so animations are refused, by the flag or by the chunks.
_VP8X_ANIMATION = 0x02
_WEBP_ANIMATION_CHUNKS = frozenset({b"ANIM", b"ANMF"})
# A still extended WebP has a handful of chunks (VP8X, ICCP, ALPH, VP8/VP8L, EXIF, XMP); the cap keeps
# the walk short whatever the file holds.
_WEBP_MAX_CHUNKS = 64


def _webp_has_animation_chunk(data: bytes) -> bool:
    """Whether an ANIM or ANMF chunk is among the first `_WEBP_MAX_CHUNKS` chunks of the RIFF container
    (each: FourCC, little-endian size, data padded to an even length). The flag is what libwebp goes by;
    the chunks are a second look, so a file that hides them past the cap is no animation to it either."""
    pos, end = 12, min(len(data), 8 + int.from_bytes(data[4:8], "little"))
    for _ in range(_WEBP_MAX_CHUNKS):
        if pos + 8 > end:
            break
        if data[pos:pos + 4] in _WEBP_ANIMATION_CHUNKS:
            return True
        size = int.from_bytes(data[pos + 4:pos + 8], "little")
        pos += 8 + size + (size & 1)
    return False


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
        if data[20] & _VP8X_ANIMATION or _webp_has_animation_chunk(data):
            raise ImageError("unsupported-format", "animated WebP images are not supported; send a single "
                             "frame as a still WebP", detected="WebP (animated)")
        width = int.from_bytes(data[24:27], "little") + 1
        height = int.from_bytes(data[27:30], "little") + 1
    else:
        raise _corrupt("webp", f"unknown first chunk {fourcc!r}")
    if width == 0 or height == 0:
        raise _corrupt("webp", f"header gives an invalid size {width}x{height}")
    return _Header(width, height, n >= 8 + riff_size)

