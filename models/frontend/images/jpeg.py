"""JPEG header walk: size, completeness and the scan count, without decoding (docs/design/service.md §1.2)."""

from __future__ import annotations

import re
import struct

import simplejpeg

from models.frontend.images.common import ImageError, _corrupt, _Header, _truncated

_JPEG_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
# The frames whose scans the walk follows (`_Scans`): sequential DCT (baseline, extended, arithmetic) and
# progressive DCT (Huffman, arithmetic). Lossless (SOF3, SOF11) and hierarchical frames (SOF5-7,
# SOF13-15, which libjpeg refuses outright) are left to the decoder.
_JPEG_SEQUENTIAL_SOF = frozenset({0xC0, 0xC1, 0xC9})
_JPEG_PROGRESSIVE_SOF = frozenset({0xC2, 0xCA})
# Inside entropy-coded data 0xFF is byte-stuffed (FF 00) and restart markers FF D0..D7 may occur; any
# other FF xx (xx not FF, a fill byte) is a real marker that ends the scan.
_JPEG_SCAN_END = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")


def _jpeg_header(data: bytes) -> _Header:
    """Walk the JPEG marker segments: SOFn gives the size; EOI (FF D9) must follow the last scan.

    Walking segments (rather than looking for FF D9 anywhere) matters because an EXIF thumbnail is a
    whole JPEG, EOI included, inside the APP1 segment of a truncated file. Progressive files have
    several scans; each scan's entropy-coded data is skipped with one C-level regex search. Scans are
    counted: libjpeg walks every block of the frame once per scan, even for an empty one. Each scan's
    header is read against the frame's components (`_Scans`), so that a file whose scans stop before
    the image is whole (a progressive file cut at a scan boundary with EOI appended) is `damaged`.
    """
    n = len(data)
    size: tuple[int, int] | None = None
    tracked: _Scans | None = None
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
            damaged = tracked.missing() if tracked is not None else None
            return _Header(size[0], size[1], True, _jpeg_scans_error(scans, size), damaged=damaged)
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
            if marker in _JPEG_SEQUENTIAL_SOF or marker in _JPEG_PROGRESSIVE_SOF:
                if pos + 8 > n or pos + 8 + 3 * data[pos + 7] > n:
                    break
                components = data[pos + 7]
                if components == 0 or length != 8 + 3 * components:  # libjpeg: JERR_EMPTY_IMAGE, BAD_LENGTH
                    raise _corrupt("jpeg", f"frame header (SOF) of length {length} for {components} "
                                           "components")
                tracked = _Scans(marker in _JPEG_PROGRESSIVE_SOF, data[pos + 8:pos + 8 + 3 * components:3])
        if marker == 0xDA:  # SOS: header segment, then entropy-coded data up to the next real marker
            if size is None:
                raise _corrupt("jpeg", "scan (SOS) before any frame header (SOF)")
            scans += 1
            if scans > JPEG_MAX_SCANS:  # stop walking: the answer is known
                return _Header(size[0], size[1], True, _jpeg_scans_error(scans, size))
            if tracked is not None and seg_end <= n:  # a header cut short: the file is truncated anyway
                tracked.scan(data[pos + 2:seg_end], scans)
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


_NEVER = 0xFF  # `_Scans.bits`: a coefficient no scan has delivered yet


class _Scans:
    """What a sequential or progressive frame's scans have delivered, read from their headers (SOS).

    A decoder that meets EOI early returns the frame anyway: libjpeg leaves a component no scan named
    flat, and a progressive frame's coefficients that no scan delivered (or refined) zero, without a
    warning. A progressive file cut at a scan boundary with EOI appended was learned from its first scan
    alone (an outside probe). So by EOI:

    - sequential frames: every frame component must have appeared in some scan. Their Ss, Se, Ah and Al
      are not checked: libjpeg ignores them (a warning) and cameras write files with zeros there.
    - progressive frames: every component's coefficients 0..63 must have been delivered and refined
      down to bit 0 (per component and coefficient, the last scan's Al is 0), each scan refining from
      the bit the earlier ones left (its Ah is their Al: ITU-T T.81 B.2.3; libjpeg warns "inconsistent
      progression sequence" and decodes on, so a scan lost from the middle goes unseen there).

    Component ids are matched to the frame's as libjpeg-turbo's `get_sos` does (the first unclaimed
    frame component of that id among the first four, which also resolves files whose ids repeat).
    What libjpeg refuses outright (a bad SOS length or component id, progressive Ss/Se/Ah/Al out of
    range) is refused here as corrupt, as OpenCV's decode would refuse it.
    """

    def __init__(self, progressive: bool, ids: bytes) -> None:
        self.progressive = progressive
        self.ids = ids  # the frame's component ids, in frame order
        self.scanned = [False] * len(ids)
        # progressive: per component, the Al of the last scan that carried each coefficient
        self.bits = [bytearray([_NEVER]) * 64 for _ in ids]
        self.problem: str | None = None  # the first scan out of sequence

    def scan(self, header: bytes, number: int) -> None:
        """One SOS header (after its length): Ns, Ns x (Cs, Td/Ta), Ss, Se, Ah/Al."""
        ns = header[0] if header else 0
        if len(header) != 4 + 2 * ns or not 1 <= ns <= 4:  # libjpeg: JERR_BAD_LENGTH
            raise _corrupt("jpeg", f"scan {number} has a header (SOS) of {len(header) + 2} bytes for {ns} "
                                   "components")
        claimed: list[int | None] = [None] * 4  # libjpeg's cur_comp_info, indexed as it indexes it
        members = []
        for i in range(ns):
            cid = header[1 + 2 * i]
            found = next((ci for ci in range(min(len(self.ids), 4))
                          if self.ids[ci] == cid and claimed[ci] is None), None)
            if found is None or found in claimed[:i]:  # libjpeg: JERR_BAD_COMPONENT_ID
                raise _corrupt("jpeg", f"scan {number} names component {cid}, which the frame has not")
            claimed[i] = found
            members.append(found)
            self.scanned[found] = True
        if not self.progressive:
            return
        ss, se, ah, al = header[1 + 2 * ns], header[2 + 2 * ns], *divmod(header[3 + 2 * ns], 16)
        # libjpeg's checks (jdphuff.c, jdarith.c: JERR_BAD_PROGRESSION, fatal)
        if (se != 0 if ss == 0 else (ss > se or se > 63 or ns != 1)) or (ah != 0 and al != ah - 1) or al > 13:
            raise _corrupt("jpeg", f"scan {number} has invalid progressive parameters (Ss {ss}, Se {se}, "
                                   f"Ah {ah}, Al {al})")
        for ci in members:
            band = self.bits[ci][ss:se + 1]
            # the bit each coefficient stands at; a first scan (Ah 0) may also repeat a whole-precision one
            wrong = band.translate(None, b"\x00\xff") if ah == 0 else band.replace(bytes([ah]), b"")
            if wrong and self.problem is None:
                k = next(k for k, b in enumerate(band, ss) if (b not in (0, _NEVER) if ah == 0 else b != ah))
                now = "was never sent" if self.bits[ci][k] == _NEVER else f"stands at bit {self.bits[ci][k]}"
                self.problem = (f"scan {number} (component {self.ids[ci]}, coefficients {ss}..{se}, Ah {ah}) "
                                f"does not follow on from the scans before it: coefficient {k} {now}")
            self.bits[ci][ss:se + 1] = bytes([al]) * (se - ss + 1)

    def missing(self) -> ImageError | None:
        """At EOI: the error naming what the scans left out, or None when the image is whole."""
        if self.problem is not None:
            return self._error(self.problem)
        if not self.progressive:
            never = [str(self.ids[ci]) for ci, seen in enumerate(self.scanned) if not seen]
            return self._error(f"no scan holds component {', '.join(never)}") if never else None
        gaps = []
        for ci, bits in enumerate(self.bits):
            runs, k = [], 0
            while k < 64:  # runs of coefficients that stand at the same bit
                end = k
                while end + 1 < 64 and bits[end + 1] == bits[k]:
                    end += 1
                if bits[k]:
                    what = "never sent" if bits[k] == _NEVER else f"refined only to bit {bits[k]}"
                    runs.append(f"{k if k == end else f'{k}..{end}'} {what}")
                k = end + 1
            if runs:
                gaps.append(f"component {self.ids[ci]} coefficients {', '.join(runs)}")
        return self._error("; ".join(gaps)) if gaps else None

    @staticmethod
    def _error(what: str) -> ImageError:
        return _corrupt("jpeg", f"its scans do not hold the whole image ({what}); a decoder would "
                                "return the frame with that detail left out")


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
