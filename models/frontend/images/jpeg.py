"""JPEG header walk: size, completeness and the scan count, without decoding (docs/design/service.md §1.2)."""

from __future__ import annotations

import re
import struct

import simplejpeg

from models.frontend.images.common import ImageError, _corrupt, _Header, _truncated

_JPEG_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
# Inside entropy-coded data 0xFF is byte-stuffed (FF 00) and restart markers FF D0..D7 may occur; any
# other FF xx (xx not FF, a fill byte) is a real marker that ends the scan.
_JPEG_SCAN_END = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")


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


#: libjpeg's warnings that say scan data is missing or wrong (jerror.h: JWRN_HIT_MARKER, JWRN_JPEG_EOF,
#: JWRN_HUFF_BAD_CODE, JWRN_ARITH_BAD_CODE, JWRN_MUST_RESYNC, and JWRN_EXTRANEOUS_DATA before a restart
#: marker: a restart interval's blocks were read off bytes that were not theirs). On each, libjpeg fills
#: or guesses the blocks and goes on; OpenCV returns that frame without a word. Its other warnings (an
#: unknown JFIF revision, a bad ICC marker, bytes between a complete last scan and EOI, sequential SOS
#: parameters out of range) leave every block decoded, and cameras write files that raise them.
_JPEG_DAMAGE = re.compile(r"premature end of data segment|Premature end of JPEG file|bad Huffman code|"
                          r"bad arithmetic code|instead of RST|extraneous bytes before marker 0xd[0-7]\b")


def _jpeg_check_scan_data(data: bytes) -> None:
    """Entropy-decode every scan once, at 1/8 scale, and refuse a file whose scan data is damaged.

    A USB camera's MJPEG stream, a dropped packet in a driver or a cut in a bag gives a structurally
    whole file (EOI in place, so the header walk passes) whose scan data breaks off or goes wrong part way:
    libjpeg fills the rest of the frame with flat blocks, and that frame would be learned as a view
    (docs/design/service.md §1.2). libjpeg-turbo, the codec OpenCV decodes with, runs here through
    simplejpeg, which turns its warnings into errors (`strict`). At 1/8 scale the inverse DCT is a DC
    term, so the check costs less than OpenCV's decode of the file (`cortexloc bench profile-encoder`:
    `jpeg_scan_check` beside `imdecode`), within the same limits.
    It finds what libjpeg finds: a cut that the Huffman decoder happens to read through to the end (a
    byte or a few lost near a scan's end, say) decodes as a wrong but whole frame, here as in OpenCV.

    Raises:
        ImageError: "not-an-image" when libjpeg reports damaged scan data. Any other complaint is left to
            OpenCV's decode, as before: this check only adds refusals of frames it knows are damaged.
    """
    try:
        # grey: libjpeg still entropy-decodes every component's scans (it must, to read the stream; a cut in
        # a chroma scan is refused, tests/models/frontend/test_images.py), and skips the colour conversion
        # min_factor scales only with a minimum size to scale down to (1x1 here: the smallest, 1/8)
        simplejpeg.decode_jpeg(data, colorspace="GRAY", min_height=1, min_width=1, min_factor=8,
                               fastdct=True, fastupsample=True, strict=True)
    except ValueError as e:
        why = str(e).strip()
        if _JPEG_DAMAGE.search(why):
            raise _corrupt("jpeg", f"its scan data is damaged ({why}); a decoder would fill the missing "
                                   "blocks with flat colour") from e
