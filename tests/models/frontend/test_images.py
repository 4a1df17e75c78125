"""Image decoding and preprocessing (docs/design/science.md §6 "Front end"; docs/design/service.md §1.2, §3
input checks).

Every input is generated here (NumPy + cv2.imencode, skimage's bundled photo); nothing is downloaded.
"""

from __future__ import annotations

import io
import struct
import zlib

import cv2
import numpy as np
import pytest

from models.frontend import images
from models.frontend.images import (
    ImageError,
    decode,
    decoding,
    preprocess,
    preprocess_batch,
    probe,
    probing,
)
from models.frontend.images import png as png_mod

# ----------------------------------------------------------------------------------------------- helpers


def _encode(rgb: np.ndarray, ext: str, params: list[int] | None = None) -> bytes:
    """Encode an RGB (or grey, or RGBA, any depth) array; OpenCV wants BGR(A) channel order."""
    if rgb.ndim == 3 and rgb.shape[2] == 3:
        arr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    elif rgb.ndim == 3 and rgb.shape[2] == 4:
        arr = cv2.cvtColor(rgb, cv2.COLOR_RGBA2BGRA)
    else:
        arr = rgb
    ok, buf = cv2.imencode(ext, arr, params or [])
    assert ok
    return buf.tobytes()


def _random_rgb(h: int = 48, w: int = 64, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def _blocks_rgb(h: int = 64, w: int = 96) -> np.ndarray:
    """Large flat colour blocks: survives lossy compression, asymmetric under every rotation."""
    img = np.zeros((h, w, 3), np.uint8)
    img[: h // 2, : w // 2] = (255, 0, 0)
    img[: h // 2, w // 2:] = (0, 255, 0)
    img[h // 2:, : w // 3] = (0, 0, 255)
    img[h // 2:, w // 3:] = (255, 255, 0)
    return img


def _smooth_rgb(h: int = 120, w: int = 160) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    return np.dstack([x * 255 // (w - 1), y * 255 // (h - 1), (x + y) * 255 // (w + h - 2)]).astype(np.uint8)


def _png_chunk(ctype: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + ctype + data + struct.pack(">I", zlib.crc32(ctype + data))


def _png_claiming(width: int, height: int) -> bytes:
    """A tiny, well-formed-looking PNG whose IHDR claims width × height (8-bit RGB)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (probing._PNG_SIGNATURE + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", zlib.compress(b""))
            + _png_chunk(b"IEND", b""))


def _with_exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """Insert an APP1 Exif segment holding only the Orientation tag (0x0112) right after SOI."""
    ifd = struct.pack(">H", 1) + struct.pack(">HHIHH", 0x0112, 3, 1, orientation, 0) + struct.pack(">I", 0)
    tiff = b"MM\x00\x2a" + struct.pack(">I", 8) + ifd
    payload = b"Exif\x00\x00" + tiff
    app1 = b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload
    return jpeg[:2] + app1 + jpeg[2:]


def _code(data: bytes, **kw) -> str:
    with pytest.raises(ImageError) as info:
        decode(data, **kw)
    return info.value.code


@pytest.fixture
def no_decoding(monkeypatch):
    """Fail the test if OpenCV is asked to decode anything."""
    def refuse(*args, **kwargs):
        raise AssertionError("cv2.imdecode was called")
    monkeypatch.setattr(decoding.cv2, "imdecode", refuse)


# ---------------------------------------------------------------------------------------------- decoding


@pytest.mark.parametrize(("ext", "params"), [
    (".png", None),
    (".bmp", None),
    (".webp", [cv2.IMWRITE_WEBP_QUALITY, 101]),  # quality > 100 = lossless WebP (VP8L)
])
def test_lossless_formats_decode_to_the_exact_source(ext, params):
    rgb = _random_rgb()
    out = decode(_encode(rgb, ext, params))
    assert out.dtype == np.uint8 and out.shape == rgb.shape and out.flags.c_contiguous
    np.testing.assert_array_equal(out, rgb)


@pytest.mark.parametrize(("ext", "params"), [
    (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 95]),
    (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 90, cv2.IMWRITE_JPEG_PROGRESSIVE, 1]),  # several scans
    (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 90, cv2.IMWRITE_JPEG_RST_INTERVAL, 2]),  # FF D0..D7 inside the scan
    (".webp", [cv2.IMWRITE_WEBP_QUALITY, 95]),  # lossy WebP (VP8)
])
def test_lossy_formats_decode_close_to_the_source(ext, params):
    from skimage import data as skdata

    rgb = np.ascontiguousarray(skdata.chelsea())  # a real photo, (300, 451, 3) RGB
    out = decode(_encode(rgb, ext, params))
    assert out.shape == rgb.shape and out.dtype == np.uint8
    assert np.abs(out.astype(int) - rgb.astype(int)).mean() < 4.0


@pytest.mark.parametrize("ext", [".png", ".bmp", ".jpg", ".webp"])
def test_channel_order_is_rgb(ext):
    red = np.zeros((16, 16, 3), np.uint8)
    red[..., 0] = 255
    out = decode(_encode(red, ext)).astype(int)
    assert (out[..., 0] > 240).all() and (out[..., 1:] < 15).all()


def test_grey_png_becomes_three_equal_channels():
    grey = _random_rgb()[..., 0].copy()
    out = decode(_encode(grey, ".png"))
    assert out.shape == (*grey.shape, 3)
    for c in range(3):
        np.testing.assert_array_equal(out[..., c], grey)


def test_rgba_png_drops_alpha():
    rgb = _random_rgb()
    alpha = np.random.default_rng(1).integers(1, 256, rgb.shape[:2], dtype=np.uint8)
    out = decode(_encode(np.dstack([rgb, alpha]), ".png"))
    np.testing.assert_array_equal(out, rgb)


@pytest.mark.parametrize("channels", [1, 3])
def test_16_bit_png_is_scaled_to_8_bits_with_rounding(channels):
    rng = np.random.default_rng(2)
    a = rng.integers(0, 65536, (32, 40, channels), dtype=np.uint16)
    a[0, 0], a[0, 1] = 0, 65535
    src = a[..., 0] if channels == 1 else a
    out = decode(_encode(src, ".png"))
    expected = np.round(a.astype(np.float64) / 257.0).astype(np.uint8)
    expected = np.broadcast_to(expected, (32, 40, 3))
    np.testing.assert_array_equal(out, expected)
    assert out[0, 0, 0] == 0 and out[0, 1, 0] == 255


@pytest.mark.parametrize(("orientation", "displayed"), [
    (1, lambda a: a),
    (3, lambda a: np.rot90(a, 2)),
    (6, lambda a: np.rot90(a, -1)),  # stored image must be rotated 90° clockwise to display
    (8, lambda a: np.rot90(a, 1)),
])
def test_jpeg_exif_orientation_is_applied(orientation, displayed):
    rgb = _blocks_rgb()
    data = _with_exif_orientation(_encode(rgb, ".jpg", [cv2.IMWRITE_JPEG_QUALITY, 95]), orientation)
    info = probe(data)
    assert (info.width, info.height) == (96, 64)  # the header gives the stored size
    out = decode(data)
    expected = displayed(rgb)
    assert out.shape == expected.shape
    assert np.abs(out.astype(int) - expected.astype(int)).mean() < 3.0


def test_jpeg_with_bytes_after_eoi_is_accepted():
    rgb = _blocks_rgb()
    out = decode(_encode(rgb, ".jpg") + b"\x00" * 64 + b"trailer")
    assert out.shape == rgb.shape


def test_probe_reads_sizes_from_every_header():
    rgb = _random_rgb(37, 53)
    for ext, params, fmt in [(".png", None, "png"), (".bmp", None, "bmp"), (".jpg", None, "jpeg"),
                             (".webp", [cv2.IMWRITE_WEBP_QUALITY, 80], "webp"),
                             (".webp", [cv2.IMWRITE_WEBP_QUALITY, 101], "webp")]:
        assert probe(_encode(rgb, ext, params)) == images.ImageInfo(fmt, 53, 37), ext
    vp8x = b"RIFF" + struct.pack("<I", 22) + b"WEBP" + b"VP8X" + struct.pack("<I", 10) + b"\x00" * 4
    vp8x += (1919).to_bytes(3, "little") + (1079).to_bytes(3, "little")
    assert probe(vp8x) == images.ImageInfo("webp", 1920, 1080)


# -------------------------------------------------------------------------------------------------- errors


def test_error_is_a_value_error_with_code_and_details():
    with pytest.raises(ValueError) as info:
        decode(b"")
    assert isinstance(info.value, ImageError)
    assert info.value.code == "empty" and "empty" in str(info.value)


def test_random_bytes_are_not_an_image():
    data = b"\x13" + np.random.default_rng(3).integers(0, 256, 4096, dtype=np.uint8).tobytes()
    with pytest.raises(ImageError) as info:
        decode(data)
    assert info.value.code == "unsupported-format"  # no image signature at all (415 in the service)
    assert "13" in str(info.value)  # names the first bytes


@pytest.mark.parametrize(("head", "name"), [
    (b"GIF89a\x10\x00\x10\x00\x80\x00\x00", "GIF"),
    (b"GIF87a\x10\x00\x10\x00\x80\x00\x00", "GIF"),
    (b"II*\x00\x08\x00\x00\x00" + b"\x00" * 32, "TIFF"),
    (b"MM\x00*\x00\x00\x00\x08" + b"\x00" * 32, "TIFF"),
    (b"\x00\x00\x00\x1cftypavif" + b"\x00" * 32, "AVIF"),
])
def test_other_formats_are_unsupported(head, name, no_decoding):
    with pytest.raises(ImageError) as info:
        decode(head)
    assert info.value.code == "unsupported-format"
    assert info.value.details["detected"] == name and name in str(info.value)


def test_formats_can_be_narrowed(no_decoding):
    bmp = _encode(_random_rgb(), ".bmp")
    with pytest.raises(ImageError) as info:
        probe(bmp, formats=("jpeg", "png"))
    assert info.value.code == "unsupported-format" and "JPEG or PNG" in str(info.value)


@pytest.mark.parametrize(("ext", "params"), [
    (".png", None), (".jpg", None), (".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]),
    (".bmp", None), (".webp", [cv2.IMWRITE_WEBP_QUALITY, 80]), (".webp", [cv2.IMWRITE_WEBP_QUALITY, 101]),
])
@pytest.mark.parametrize("keep", [0.5, 0.95])
def test_truncated_files_are_refused(ext, params, keep, no_decoding):
    from skimage import data as skdata

    data = _encode(np.ascontiguousarray(skdata.chelsea()), ext, params)
    assert _code(data[: int(len(data) * keep)]) == "truncated"


def test_truncated_jpeg_is_refused_even_with_an_exif_thumbnail_eoi(no_decoding):
    # A JPEG inside APP1 (like an EXIF thumbnail) brings its own FF D9 before the main image's scan.
    thumb = _encode(_blocks_rgb(16, 16), ".jpg")
    payload = b"Exif\x00\x00" + thumb
    main = _encode(_blocks_rgb(), ".jpg")
    data = main[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + main[2:]
    assert probe(data) == images.ImageInfo("jpeg", 96, 64)  # the thumbnail's SOF is not the image's
    assert _code(data[: len(data) - 200]) == "truncated"


def _cut_scan(data: bytes, start: int, length: int) -> bytes:
    """`data` with `length` bytes of the first scan's entropy-coded data taken out, EOI kept."""
    sos = data.index(b"\xff\xda")
    begin = sos + 2 + int.from_bytes(data[sos + 2:sos + 4], "big") + start
    return data[:begin] + data[begin + length:]


@pytest.mark.parametrize(("params", "cut", "why"), [
    ([cv2.IMWRITE_JPEG_QUALITY, 90], (2000, 3000), "premature end of data segment"),
    # within the first of its scans (~2.8 kB): a cut that takes the next scan's header is the header
    # walk's to find (test_a_progressive_jpeg_missing_a_scan_from_the_middle_is_refused)
    ([cv2.IMWRITE_JPEG_PROGRESSIVE, 1], (1000, 1000), "bad Huffman code"),
    ([cv2.IMWRITE_JPEG_RST_INTERVAL, 4], (2000, 3000), "extraneous bytes before marker 0xd4"),
])
def test_a_jpeg_whose_scan_data_breaks_off_is_refused_though_opencv_decodes_it(params, cut, why):
    from skimage import data as skdata

    whole = _encode(np.ascontiguousarray(skdata.chelsea()), ".jpg", params)
    damaged = _cut_scan(whole, *cut)
    assert probe(damaged) == probe(whole)  # structurally whole: the header walk finds EOI
    filled = cv2.imdecode(np.frombuffer(damaged, np.uint8), cv2.IMREAD_COLOR_RGB)
    assert filled is not None and filled.shape == decode(whole).shape  # the hazard: OpenCV says nothing
    with pytest.raises(ImageError) as info:
        decode(damaged)
    assert info.value.code == "not-an-image" and why in str(info.value) and "damaged" in str(info.value)
    assert _code(_cut_scan(whole, 500, 100)) == "not-an-image"


def test_a_jpeg_whose_header_claims_more_rows_than_its_scan_holds_is_refused():
    data = bytearray(_encode(_smooth_rgb(), ".jpg"))
    sof = data.index(b"\xff\xc0")
    height, width = struct.unpack_from(">HH", data, sof + 5)
    struct.pack_into(">HH", data, sof + 5, 2 * height, width)  # OpenCV: the lower half filled flat
    assert cv2.imdecode(np.frombuffer(bytes(data), np.uint8), cv2.IMREAD_COLOR_RGB).shape[0] == 2 * height
    assert _code(bytes(data)) == "not-an-image"


def test_a_cut_in_any_first_scan_of_a_progressive_jpeg_is_refused_chroma_scans_too():
    """The check decodes grey: libjpeg must still read the Cb and Cr scans (a refinement scan's
    correction bits carry no structure that libjpeg could find a cut in, so those are left out)."""
    from skimage import data as skdata

    whole = _encode(np.ascontiguousarray(skdata.chelsea()), ".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
    starts = [i for i in range(len(whole) - 1) if whole[i:i + 2] == b"\xff\xda"]
    first_scans = set()
    for k, sos in enumerate(starts):
        length, count = int.from_bytes(whole[sos + 2:sos + 4], "big"), whole[sos + 4]
        components = tuple(whole[sos + 5 + 2 * c] for c in range(count))
        if whole[sos + 2 + length - 1] >> 4:  # Ah > 0: a refinement scan
            continue
        begin, end = sos + 2 + length, starts[k + 1] if k + 1 < len(starts) else len(whole) - 2
        middle = (begin + end) // 2
        assert _code(whole[:middle] + whole[middle + 8:]) == "not-an-image", components
        first_scans.add(components)
    assert {(2,), (3,)} <= first_scans  # the chroma components' own scans were among them


def _scan_starts(data: bytes) -> list[int]:
    """Offsets of every SOS marker (none of these test files holds FF DA inside a segment)."""
    return [i for i in range(len(data) - 1) if data[i:i + 2] == b"\xff\xda"]


def _pil_jpeg(rgb: np.ndarray, mode: str = "RGB", **kw) -> bytes:
    """A JPEG written by Pillow's libjpeg (its own scan scripts and Huffman optimisation)."""
    image = pytest.importorskip("PIL.Image")
    out = io.BytesIO()
    image.fromarray(rgb).convert(mode).save(out, "JPEG", **kw)
    return out.getvalue()


def _chelsea() -> np.ndarray:
    from skimage import data as skdata

    return np.ascontiguousarray(skdata.chelsea())


_PROGRESSIVE_JPEGS = {
    "opencv": lambda: _encode(_chelsea(), ".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]),
    "opencv-grey": lambda: _encode(_chelsea()[..., 1].copy(), ".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]),
    "pillow": lambda: _pil_jpeg(_chelsea(), progressive=True),
    "pillow-optimised": lambda: _pil_jpeg(_chelsea(), progressive=True, optimize=True),
    "pillow-cmyk": lambda: _pil_jpeg(_chelsea(), "CMYK", progressive=True),
}


@pytest.mark.parametrize("make", _PROGRESSIVE_JPEGS.values(), ids=_PROGRESSIVE_JPEGS.keys())
def test_a_progressive_jpeg_cut_at_a_scan_boundary_is_refused(make, no_decoding):
    """Found from outside: cut before its second scan with EOI appended, a progressive file was learned
    from its first (DC) scan alone, a blur of the view; libjpeg warns of nothing there."""
    whole = make()
    starts = _scan_starts(whole)
    assert len(starts) > 2
    assert probe(whole).format == "jpeg"
    for k in range(1, len(starts)):
        cut = whole[:starts[k]] + b"\xff\xd9"
        with pytest.raises(ImageError) as info:
            probe(cut)
        assert info.value.code == "not-an-image", k
        assert "do not hold the whole image" in str(info.value) and "component" in str(info.value)


def test_a_progressive_jpeg_cut_at_a_scan_boundary_is_what_opencv_decodes_without_a_word():
    whole = _PROGRESSIVE_JPEGS["opencv"]()
    cut = whole[:_scan_starts(whole)[1]] + b"\xff\xd9"  # the DC scan alone, at 1 bit short
    out = cv2.imdecode(np.frombuffer(cut, np.uint8), cv2.IMREAD_COLOR_RGB)
    assert out is not None and out.shape == _chelsea().shape  # the hazard: a whole-looking frame
    with pytest.raises(ImageError) as info:
        decode(cut)
    assert str(info.value) == (
        "corrupt JPEG image: its scans do not hold the whole image (component 1 coefficients 0 refined only "
        "to bit 1, 1..63 never sent; component 2 coefficients 0 refined only to bit 1, 1..63 never sent; "
        "component 3 coefficients 0 refined only to bit 1, 1..63 never sent); a decoder would return the "
        "frame with that detail left out")


def test_a_progressive_jpeg_missing_a_scan_from_the_middle_is_refused(no_decoding):
    """Without any one of its scans the file still ends in EOI, and the last scans still bring each
    coefficient to bit 0; what is missing shows as a refinement from a bit the scans before it never
    left (ITU-T T.81 B.2.3), or a band never sent."""
    whole = _PROGRESSIVE_JPEGS["opencv"]()
    starts = [*_scan_starts(whole), len(whole) - 2]
    for k in range(len(starts) - 1):
        with pytest.raises(ImageError) as info:
            probe(whole[:starts[k]] + whole[starts[k + 1]:])
        assert info.value.code == "not-an-image", k
    dropped = whole[:starts[5]] + whole[starts[6]:]  # Y's AC refinement from bit 2 to bit 1
    with pytest.raises(ImageError) as info:
        probe(dropped)
    assert "scan 9 (component 1, coefficients 1..63, Ah 1) does not follow on from the scans before it: " \
           "coefficient 1 stands at bit 2" in str(info.value)


def test_a_sequential_jpeg_whose_frame_has_a_component_no_scan_holds_is_refused(no_decoding):
    """A sequential frame may send its components in separate scans; cut after the first with EOI
    appended, libjpeg leaves the others flat. Here: a grey file whose frame header claims three."""
    grey = bytearray(_encode(_chelsea()[..., 1].copy(), ".jpg"))
    sof = grey.index(b"\xff\xc0")
    assert grey[sof + 9] == 1  # one component: id, sampling, table
    three = bytes(grey[:sof + 2] + struct.pack(">H", 17) + grey[sof + 4:sof + 9] + b"\x03"
                  + grey[sof + 10:sof + 13] + b"\x02\x11\x00\x03\x11\x00" + grey[sof + 13:])
    with pytest.raises(ImageError) as info:
        probe(three)
    assert info.value.code == "not-an-image" and "no scan holds component 2, 3" in str(info.value)


def test_a_jpeg_scan_naming_a_component_the_frame_lacks_is_refused(no_decoding):
    data = bytearray(_encode(_blocks_rgb(), ".jpg"))
    sos = data.index(b"\xff\xda")
    data[sos + 5] = 9  # the first component's id: the frame's are 1, 2, 3
    with pytest.raises(ImageError) as info:
        probe(bytes(data))
    assert info.value.code == "not-an-image" and "names component 9" in str(info.value)


def _exif_thumbnail(main: bytes, thumb: bytes) -> bytes:
    payload = b"Exif\x00\x00" + thumb
    return main[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + main[2:]


def _sequential_zeros(jpeg: bytes) -> bytes:
    """Ss, Se, Ah/Al all zero in a baseline file's scan header, as some cameras write them."""
    sos = jpeg.index(b"\xff\xda")
    end = sos + 2 + int.from_bytes(jpeg[sos + 2:sos + 4], "big")
    return jpeg[:end - 3] + b"\x00\x00\x00" + jpeg[end:]


_STANDARD_JPEGS = {
    "opencv-baseline": lambda: _encode(_chelsea(), ".jpg"),
    "opencv-optimised": lambda: _encode(_chelsea(), ".jpg", [cv2.IMWRITE_JPEG_OPTIMIZE, 1]),
    "opencv-grey": lambda: _encode(_chelsea()[..., 0].copy(), ".jpg"),
    "opencv-restarts": lambda: _encode(_chelsea(), ".jpg", [cv2.IMWRITE_JPEG_RST_INTERVAL, 3]),
    "opencv-progressive-restarts": lambda: _encode(_chelsea(), ".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1,
                                                                        cv2.IMWRITE_JPEG_RST_INTERVAL, 3]),
    "opencv-444": lambda: _encode(_chelsea(), ".jpg", [cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                                                       cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]),
    "pillow-baseline": lambda: _pil_jpeg(_chelsea()),
    "pillow-optimised": lambda: _pil_jpeg(_chelsea(), optimize=True),
    "pillow-cmyk": lambda: _pil_jpeg(_chelsea(), "CMYK"),
    "pillow-grey-progressive": lambda: _pil_jpeg(_chelsea(), "L", progressive=True),
    "pillow-progressive-444": lambda: _pil_jpeg(_chelsea(), progressive=True, subsampling=0),
    "exif-thumbnail": lambda: _exif_thumbnail(_encode(_chelsea(), ".jpg"),
                                              _encode(_blocks_rgb(16, 16), ".jpg")),
    "progressive-with-progressive-thumbnail": lambda: _exif_thumbnail(
        *(_encode(a, ".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]) for a in (_chelsea(), _blocks_rgb(16, 16)))),
    "sequential-scan-parameters-zero": lambda: _sequential_zeros(_encode(_chelsea(), ".jpg")),
    **{f"progressive-{name}": make for name, make in _PROGRESSIVE_JPEGS.items()},
}


@pytest.mark.parametrize("make", _STANDARD_JPEGS.values(), ids=_STANDARD_JPEGS.keys())
def test_whole_jpegs_of_every_common_kind_pass_the_scan_walk(make):
    data = make()
    out = decode(data)
    assert out.shape == _chelsea().shape
    expected = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR_RGB)
    np.testing.assert_array_equal(out, expected)


def test_the_scan_data_check_decodes_at_an_eighth(monkeypatch):
    """It reads every scan, but writes an eighth of the rows and columns (a review found it decoding the
    whole frame: simplejpeg scales only given a minimum size)."""
    from models.frontend.images import jpeg as jpeg_mod

    shapes = []
    real = jpeg_mod.simplejpeg.decode_jpeg

    def spy(*args, **kw):
        out = real(*args, **kw)
        shapes.append(out.shape[:2])
        return out

    monkeypatch.setattr(jpeg_mod.simplejpeg, "decode_jpeg", spy)
    decode(_encode(_smooth_rgb(480, 640), ".jpg"))
    assert shapes == [(60, 80)]


def test_a_jpeg_with_warnings_that_leave_every_block_decoded_is_accepted():
    rgb = _smooth_rgb()
    whole = _encode(rgb, ".jpg", [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert whole[6:11] == b"JFIF\x00"
    revision = whole[:11] + b"\x07" + whole[12:]  # JFIF 7.x: libjpeg warns of an unknown revision
    padded = whole[:-2] + b"\x00" * 16 + whole[-2:]  # bytes between the complete scan and EOI
    for data in (revision, padded):
        out = decode(data)
        assert np.abs(out.astype(int) - decode(whole).astype(int)).max() == 0


@pytest.mark.parametrize("data", [b"\xff\xd8", b"\x89PNG\r\n", b"RIFF\x00\x00\x00\x00WE"])
def test_a_body_cut_inside_the_signature_is_truncated(data):
    assert _code(data) == "truncated"


def test_png_header_claiming_a_huge_image_is_refused_without_decoding(no_decoding):
    data = _png_claiming(20000, 20000)
    assert len(data) < 100
    with pytest.raises(ImageError) as info:
        decode(data)
    err = info.value
    assert err.code == "too-many-pixels"
    assert str(err) == "image has 20000x20000 = 400000000 pixels, more than the limit of 25000000"
    assert err.details["width"] == 20000 and err.details["height"] == 20000
    assert err.details["max_pixels"] == 25_000_000


def test_jpeg_sof_claiming_a_huge_image_is_refused_without_decoding(no_decoding):
    data = bytearray(_encode(_blocks_rgb(), ".jpg"))
    sof = data.index(b"\xff\xc0")
    data[sof + 5:sof + 9] = struct.pack(">HH", 30000, 30000)  # height, width
    with pytest.raises(ImageError) as info:
        decode(bytes(data))
    assert info.value.code == "too-many-pixels"
    assert "30000x30000 = 900000000 pixels" in str(info.value)


@pytest.mark.parametrize(("depth", "colour", "refused"), [
    (16, 6, True),    # 16-bit RGBA: 8 bytes a pixel
    (8, 6, True),     # 8-bit RGBA: 4
    (16, 2, True),    # 16-bit RGB: 6
    (16, 0, False),   # 16-bit grey (a depth camera's): 2
    (8, 2, False),    # 8-bit RGB: the 3 bytes the cap is sized for
])
def test_a_png_whose_pixels_decode_past_the_caps_bytes_is_refused_without_decoding(depth, colour, refused,
                                                                                   no_decoding):
    # Found from outside: a 194 kB 16-bit RGBA PNG at the pixel cap held every map's decode for seconds.
    ihdr = struct.pack(">IIBBBBB", 100, 100, depth, colour, 0, 0, 0)
    data = (probing._PNG_SIGNATURE + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", zlib.compress(b""))
            + _png_chunk(b"IEND", b""))
    if refused:
        with pytest.raises(ImageError) as info:
            probe(data, max_pixels=100 * 100)
        assert info.value.code == "too-many-pixels" and info.value.details["bits_per_pixel"] == depth * {
            6: 4, 2: 3}[colour] and "30000 (10000 pixels of 3 bytes)" in str(info.value)
        assert probe(data, max_pixels=100 * 100 * 3).width == 100  # the cap's bytes are what bind it
    else:
        assert probe(data, max_pixels=100 * 100) == images.ImageInfo("png", 100, 100)


def test_pixel_cap_is_a_parameter():
    data = _encode(_random_rgb(40, 50), ".png")
    assert decode(data, max_pixels=2000).shape == (40, 50, 3)
    assert _code(data, max_pixels=1999) == "too-many-pixels"


def test_over_max_bytes_is_too_large(no_decoding):
    data = _encode(_random_rgb(), ".png")
    with pytest.raises(ImageError) as info:
        decode(data, max_bytes=len(data) - 1)
    assert info.value.code == "too-large"
    assert info.value.details == {"received_bytes": len(data), "max_bytes": len(data) - 1}
    assert f"{len(data)} bytes" in str(info.value)


def _bmp_rle(grey: np.ndarray, *, rle4: bool = False, size_image: int | None = None,
             last_eol: bool = True) -> tuple[bytes, list[int]]:
    """An RLE8 (values 0..255) or RLE4 (0..15) bitmap of `grey` with a grey palette, and where each row's
    data ends (after its end of line). Each row opens with an absolute run of 5 pixels, then encoded
    runs; an end of line after every row (the last: `last_eol`), then the end of bitmap."""
    h, w = grey.shape
    rows, ends = b"", []
    for y in range(h - 1, -1, -1):  # bottom-up
        row = grey[y].tolist()
        if rle4:
            packed = bytes((row[i] << 4) | (row[i + 1] if i + 1 < 5 else 0) for i in range(0, 5, 2))
            out = bytearray(b"\x00\x05" + packed + b"\x00")  # 5 nibbles in 3 bytes, padded to 4
        else:
            out = bytearray(b"\x00\x05" + bytes(row[:5]) + b"\x00")  # 5 bytes, padded to 6
        x = 5
        while x < w:
            n = 1
            while x + n < w and n < 255 and row[x + n] == row[x]:
                n += 1
            out += bytes((n, (row[x] << 4) | row[x] if rle4 else row[x]))
            x += n
        if last_eol or y:
            out += b"\x00\x00"
        rows += out
        ends.append(len(rows))
    data = rows + b"\x00\x01"
    colours = 16 if rle4 else 256
    palette = b"".join(bytes((v, v, v, 0)) for v in (np.arange(colours) * 255 // (colours - 1)).tolist())
    offbits = 14 + 40 + len(palette)
    header = b"BM" + struct.pack("<IHHI", offbits + len(data), 0, 0, offbits) + struct.pack(
        "<IiiHHIIiiII", 40, w, h, 1, 4 if rle4 else 8, 2 if rle4 else 1,
        len(data) if size_image is None else size_image, 2835, 2835, colours, 0)
    return header + palette + data, [offbits + e for e in ends]


def _posterised(levels: int) -> np.ndarray:
    """96x64 blocks of `levels` grey levels: runs long enough for RLE."""
    return cv2.resize(np.random.default_rng(4).integers(0, levels, (8, 12), dtype=np.uint8), (96, 64),
                      interpolation=cv2.INTER_NEAREST)


@pytest.mark.parametrize("rle4", [False, True])
@pytest.mark.parametrize("last_eol", [True, False])
def test_a_whole_rle_bmp_decodes_to_its_pixels(rle4, last_eol):
    grey = _posterised(16 if rle4 else 256)
    data, _ = _bmp_rle(grey, rle4=rle4, last_eol=last_eol)
    expected = grey * 17 if rle4 else grey
    np.testing.assert_array_equal(decode(data), np.dstack([expected] * 3))


@pytest.mark.parametrize("rle4", [False, True])
def test_an_rle_bmp_cut_part_way_is_refused_even_with_its_end_of_bitmap(rle4, no_decoding):
    """Found from outside: an RLE8 bitmap cut after 120 of its 480 rows with an end of bitmap (00 01)
    appended, biSizeImage 0, was learned with the missing rows black."""
    grey = _posterised(16 if rle4 else 256)
    data, ends = _bmp_rle(grey, rle4=rle4, size_image=0)
    for rows in (1, 16, 62):
        for cut in (data[:ends[rows - 1]] + b"\x00\x01", data[:ends[rows - 1] + 7] + b"\x00\x01",
                    data[:ends[rows - 1]]):
            with pytest.raises(ImageError) as info:
                probe(cut)
            assert info.value.code == "truncated"
            assert f"its RLE data ends in row {rows + 1} of 64" in str(info.value)
    assert probe(data[:ends[62]] + b"\x00\x01").height == 64  # into the last row: whole as far as it tells


def test_an_rle_bmp_cut_with_its_end_of_bitmap_is_what_opencv_decodes_without_a_word():
    grey = _posterised(256)
    data, ends = _bmp_rle(grey, size_image=0)
    cut = data[:ends[15]] + b"\x00\x01"
    out = cv2.imdecode(np.frombuffer(cut, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert out is not None and out.shape == grey.shape  # the hazard: rows 16.. filled, no error
    assert _code(cut) == "truncated"


def test_an_rle_bmp_whose_rows_a_delta_skips_is_whole():
    grey = _posterised(256)
    data, ends = _bmp_rle(grey, size_image=0)
    # rows 3..10 (from the bottom) skipped by one delta down 8 rows, back at column 0
    skipped = data[:ends[2]] + b"\x00\x02\x00\x08" + data[ends[10]:]
    out = decode(skipped)[::-1, :, 0]  # bottom-up, as the rows were written
    np.testing.assert_array_equal(out[:3], grey[::-1][:3])
    np.testing.assert_array_equal(out[11:], grey[::-1][11:])
    assert _code(skipped[:ends[2]] + b"\x00\x02\x00\x08" + b"\x00\x01") == "truncated"


def test_degenerate_aspect_ratio_is_refused():
    assert _code(_encode(np.zeros((1, 4000, 3), np.uint8), ".png")) == "degenerate"
    data = _encode(np.zeros((16, 4000, 3), np.uint8), ".png")
    with pytest.raises(ImageError) as info:
        decode(data)
    assert info.value.details["max_aspect"] == 16 and "more than 16 times its short side" in str(info.value)
    assert decode(data, max_aspect=None).shape == (16, 4000, 3)
    assert decode(_encode(np.zeros((16, 256, 3), np.uint8), ".png")).shape == (16, 256, 3)  # 16x is allowed
    assert _code(_encode(np.zeros((16, 257, 3), np.uint8), ".png")) == "degenerate"


@pytest.mark.parametrize(("width", "height"), [(1, 1), (2, 2), (8, 8), (16, 8), (8, 16), (15, 15), (15, 200)])
def test_a_frame_whose_short_side_is_under_16_pixels_is_refused(width, height, no_decoding):
    """Found from outside: 1x1, 2x2, 8x8 and 16x8 frames were learned as views, and a 2x2 checkerboard
    matched real views at confidence 0.725."""
    board = ((np.indices((height, width)).sum(0) % 2) * 255).astype(np.uint8)
    for data in (_encode(np.dstack([board] * 3), ".png"), _encode(board, ".jpg"),
                 images.RawFrame(board.tobytes(), "mono8", width, height)):
        with pytest.raises(ImageError) as info:
            probe(data)
        err = info.value
        assert err.code == "degenerate" and err.details["min_side"] == images.DEFAULT_MIN_SIDE == 16
        assert (err.details["width"], err.details["height"]) == (width, height)
        assert f"image is {width}x{height}: its short side is under 16 pixels" in str(err)
        assert probe(data, min_side=None).width == width


@pytest.mark.parametrize(("width", "height"), [(16, 16), (64, 32), (32, 64), (16, 256)])
def test_a_frame_whose_short_side_is_16_pixels_or_more_is_accepted(width, height):
    rgb = _random_rgb(height, width)
    assert decode(_encode(rgb, ".png")).shape == (height, width, 3)
    assert decode(images.RawFrame(rgb.tobytes(), "rgb8", width, height)).shape == (height, width, 3)


def _apng(width: int, height: int, first_frame: bytes) -> bytes:
    """An animated PNG of two frames whose default image (IDAT) is flat grey and whose first animation
    frame (fcTL + fdAT) is `first_frame`, deflated rows with their filter bytes."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    grey = zlib.compress((b"\x00" + b"\x80" * 3 * width) * height)

    def fctl(seq: int) -> bytes:  # sequence, size, offset, delay 1/10 s, dispose none, blend source
        return _png_chunk(b"fcTL", struct.pack(">IIIIIHHBB", seq, width, height, 0, 0, 1, 10, 0, 0))

    return (probing._PNG_SIGNATURE + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"acTL", struct.pack(">II", 2, 0))
            + _png_chunk(b"IDAT", grey) + fctl(0) + _png_chunk(b"fdAT", struct.pack(">I", 1) + first_frame)
            + fctl(2) + _png_chunk(b"fdAT", struct.pack(">I", 3) + grey) + _png_chunk(b"IEND", b""))


def test_an_animated_png_is_refused(no_decoding):
    """Found from outside: the checks judge an APNG's default image (IDAT), OpenCV decodes its first
    animation frame (fdAT), which they never see: one of 2 GiB of deflated zeros was learned as black."""
    bomb = zlib.compress(bytes(64 << 20), 9)  # 64 MB of zeros for a 64x48 frame of 9,264 raster bytes
    for data in (_apng(64, 48, bomb), _apng(64, 48, zlib.compress(bytes(48 * (1 + 64 * 3))))):
        with pytest.raises(ImageError) as info:
            probe(data)
        err = info.value
        assert err.code == "unsupported-format" and err.details["detected"] == "PNG (animated)"
        assert "animated PNG" in str(err)


def test_an_animated_png_from_pillow_is_refused():
    image = pytest.importorskip("PIL.Image")
    frames = [image.fromarray(_random_rgb(seed=s)) for s in range(2)]
    out = io.BytesIO()
    image.new("RGB", (64, 48)).save(out, "PNG", save_all=True, append_images=frames, default_image=True)
    assert _code(out.getvalue()) == "unsupported-format"


def test_an_animated_webp_is_refused_by_its_flag_or_its_chunks(no_decoding):
    image = pytest.importorskip("PIL.Image")
    frames = [image.fromarray(_random_rgb(seed=s)) for s in range(3)]
    out = io.BytesIO()
    frames[0].save(out, "WEBP", save_all=True, append_images=frames[1:], duration=100, loop=0)
    animated = out.getvalue()
    assert animated[12:16] == b"VP8X" and animated[20] & 0x02
    unflagged = animated[:20] + bytes([animated[20] & ~0x02]) + animated[21:]  # ANIM, ANMF still there
    for data in (animated, unflagged):
        with pytest.raises(ImageError) as info:
            probe(data)
        assert info.value.code == "unsupported-format" and info.value.details["detected"] == "WebP (animated)"
        assert "animated WebP" in str(info.value)


def test_a_still_extended_webp_is_accepted():
    image = pytest.importorskip("PIL.Image")
    rgba = np.dstack([_random_rgb(), np.full((48, 64), 128, np.uint8)])
    out = io.BytesIO()
    image.fromarray(rgba).save(out, "WEBP", quality=90, exif=b"Exif\x00\x00MM\x00*\x00\x00\x00\x08\x00\x00")
    data = out.getvalue()
    assert data[12:16] == b"VP8X" and b"ALPH" in data and b"EXIF" in data
    assert decode(data).shape == (48, 64, 3)


def test_structurally_complete_but_corrupt_png_is_not_an_image():
    data = bytearray(_encode(_random_rgb(), ".png"))
    idat = data.index(b"IDAT")
    data[idat + 4:idat + 40] = b"\x00" * 36  # garbage deflate stream, CRC now wrong
    assert _code(bytes(data)) == "not-an-image"


# ------------------------------------------------------------------------------------------ preprocessing

IDENTITY = {"mean": (0.0, 0.0, 0.0), "std": (1.0, 1.0, 1.0)}


def _unnormalise(x: np.ndarray, mean=images.IMAGENET_MEAN, std=images.IMAGENET_STD) -> np.ndarray:
    """(3, S, S) normalised -> (S, S, 3) in 0..255."""
    return ((x * np.asarray(std)[:, None, None] + np.asarray(mean)[:, None, None]) * 255.0).transpose(1, 2, 0)


@pytest.mark.parametrize("mode", ["crop", "squash"])
def test_preprocess_shape_dtype_and_normalisation(mode):
    x = preprocess(_random_rgb(300, 451), mode=mode)
    assert x.shape == (3, 224, 224) and x.dtype == np.float32 and x.flags.c_contiguous
    mean_img = np.broadcast_to(np.round(np.asarray(images.IMAGENET_MEAN) * 255), (100, 150, 3))
    z = preprocess(np.ascontiguousarray(mean_img, dtype=np.uint8), mode=mode)
    assert np.abs(z).max() < 0.5 / 255 / 0.224 + 1e-6  # only the rounding of the mean to 8 bits remains
    black = preprocess(np.zeros((50, 60, 3), np.uint8), mode=mode)
    white = preprocess(np.full((50, 60, 3), 255, np.uint8), mode=mode)
    for c in range(3):
        m, s = images.IMAGENET_MEAN[c], images.IMAGENET_STD[c]
        np.testing.assert_allclose(black[c], -m / s, rtol=1e-6)
        np.testing.assert_allclose(white[c], (1 - m) / s, rtol=1e-6)


def test_preprocess_matches_the_float32_tensor_arithmetic():
    rgb = _random_rgb(224, 224)  # square of the crop size after Resize(256): exercise only normalisation
    x = preprocess(rgb, mode="squash")
    mean = np.asarray(images.IMAGENET_MEAN, np.float32)[:, None, None]
    std = np.asarray(images.IMAGENET_STD, np.float32)[:, None, None]
    expected = (rgb.transpose(2, 0, 1).astype(np.float32) / np.float32(255) - mean) / std
    np.testing.assert_array_equal(x, expected)


def test_preprocess_writes_into_a_row_of_the_batch_it_is_given():
    """The encoder prepares each frame straight into its row of the backbone's batch (no second copy)."""
    batch = np.full((3, 3, 224, 224), 7.0, np.float32)
    rgb = _random_rgb(300, 451)
    x = preprocess(rgb, mode="crop", out=batch[1])
    assert np.shares_memory(x, batch)
    np.testing.assert_array_equal(batch[1], preprocess(rgb, mode="crop"))
    assert (batch[0] == 7.0).all() and (batch[2] == 7.0).all()  # its neighbours untouched
    rows = preprocess_batch([rgb, rgb], mode="squash", out=batch[1:])
    assert rows.base is batch and np.array_equal(batch[2], preprocess(rgb, mode="squash"))
    for wrong in (np.empty((3, 224, 224), np.float64), np.empty((3, 224, 225), np.float32),
                  np.empty((3, 448, 224), np.float32)[:, ::2]):
        with pytest.raises(ValueError, match="out must be"):
            preprocess(rgb, out=wrong)


def _gradient(h: int, w: int) -> np.ndarray:
    """Channel 0 = 4·x, channel 1 = 8·y (the layout of a 64 wide × 32 high Nordland frame)."""
    y, x = np.mgrid[0:h, 0:w]
    return np.dstack([4 * x, 8 * y, np.zeros_like(x)]).astype(np.uint8)


def test_crop_keeps_the_central_part_of_a_64x32_frame():
    img = _gradient(32, 64)  # short side 32 -> 256 (×8), long side 64 -> 512; crop left 144, top 16
    v = _unnormalise(preprocess(img, mode="crop"))
    # INTER_LINEAR at ×8: output column j samples source x = (j + 0.5) / 8 − 0.5.
    x_first, x_last = (144 + 0.5) / 8 - 0.5, (144 + 223 + 0.5) / 8 - 0.5  # 17.56 and 45.44
    y_first, y_last = (16 + 0.5) / 8 - 0.5, (16 + 223 + 0.5) / 8 - 0.5  # 1.56 and 29.44
    np.testing.assert_allclose(v[:, 0, 0], 4 * x_first, atol=1.0)
    np.testing.assert_allclose(v[:, -1, 0], 4 * x_last, atol=1.0)
    np.testing.assert_allclose(v[0, :, 1], 8 * y_first, atol=1.0)
    np.testing.assert_allclose(v[-1, :, 1], 8 * y_last, atol=1.0)
    # 56 % of the width is lost: nothing left of the outer source columns.
    assert v[..., 0].min() > 4 * 17 and v[..., 0].max() < 4 * 46


def test_squash_keeps_the_whole_frame():
    img = _gradient(32, 64)
    v = _unnormalise(preprocess(img, mode="squash"))
    assert v[..., 0].min() < 4 and v[..., 0].max() > 4 * 63 - 4
    assert v[..., 1].min() < 8 and v[..., 1].max() > 8 * 31 - 8
    assert np.all(np.diff(v[0, :, 0]) >= -1e-3)  # monotone left to right, nothing cut


@pytest.mark.parametrize(("w", "left"), [(256, 16), (257, 16), (259, 18)])
def test_centre_crop_offsets_round_half_to_even(w, left):
    # Short side already 256 and int(256·w/256) = w: no resampling, so the crop is exact pixels.
    img = _random_rgb(256, w, seed=w)
    x = preprocess(img, mode="crop", **IDENTITY)
    expected = img[16:240, left:left + 224].transpose(2, 0, 1).astype(np.float32) / np.float32(255)
    np.testing.assert_array_equal(x, expected)


def test_portrait_images_crop_symmetrically():
    img = _gradient(32, 64).transpose(1, 0, 2)[..., ::-1].copy()  # 32 wide × 64 high, y-gradient in ch 2
    v = _unnormalise(preprocess(img, mode="crop"))
    assert v[..., 2].min() > 4 * 17 and v[..., 2].max() < 4 * 46


def test_resize_size_follows_torchvision():
    # 451 × 300 -> long side int(256·451/300) = int(384.85) = 384; the crop is then taken at left 80.
    img = np.zeros((300, 451, 3), np.uint8)
    img[:, 225] = 255  # a one-pixel line at the centre column
    v = _unnormalise(preprocess(img, mode="crop", **IDENTITY), mean=(0, 0, 0), std=(1, 1, 1))
    col = int(np.argmax(v[112, :, 0]))
    assert col == pytest.approx(384 * 225.5 / 451 - 80, abs=1.0)


def test_shrinking_is_antialiased():
    # A 1-pixel checkerboard shrunk 3×: INTER_AREA averages 3×3 blocks (4/9 or 5/9 white); plain
    # bilinear would sample single pixels and keep the full 0/255 contrast.
    board = ((np.indices((768, 768)).sum(0) % 2) * 255).astype(np.uint8)
    v = _unnormalise(preprocess(np.dstack([board] * 3), mode="crop", **IDENTITY), mean=(0, 0, 0),
                     std=(1, 1, 1))
    assert v.min() > 100 and v.max() < 155


def test_squash_of_a_wide_image_shrinks_one_axis_and_enlarges_the_other():
    img = _gradient(32, 64)
    wide = np.ascontiguousarray(np.repeat(img, 10, axis=1))  # 640 × 32
    x = preprocess(wide, mode="squash", size=112)
    assert x.shape == (3, 112, 112) and np.isfinite(x).all()


def test_preprocess_batch_stacks_mixed_sizes():
    imgs = [_random_rgb(300, 451, 0), _random_rgb(32, 64, 1), _random_rgb(500, 400, 2)]
    for kw in ({}, {"mode": "squash", "size": 112}):
        batch = preprocess_batch(imgs, **kw)
        size = kw.get("size", 224)
        assert batch.shape == (3, 3, size, size) and batch.dtype == np.float32 and batch.flags.c_contiguous
        for i, img in enumerate(imgs):
            np.testing.assert_array_equal(batch[i], preprocess(img, **kw))
    assert preprocess_batch([]).shape == (0, 3, 224, 224)


@pytest.mark.parametrize("bad", [
    np.zeros((10, 10), np.uint8),
    np.zeros((10, 10, 4), np.uint8),
    np.zeros((10, 10, 3), np.float32),
    np.zeros((0, 10, 3), np.uint8),
])
def test_preprocess_refuses_non_rgb_input(bad):
    with pytest.raises(ValueError):
        preprocess(bad)


@pytest.mark.parametrize("kw", [{"mode": "stretch"}, {"size": 300}, {"mean": (0.5, 0.5)},
                                {"std": (1.0, 0.0, 1.0)}])
def test_preprocess_refuses_bad_parameters(kw):
    with pytest.raises(ValueError):
        preprocess(_random_rgb(), **kw)


def test_decode_then_preprocess_end_to_end():
    from skimage import data as skdata

    rgb = np.ascontiguousarray(skdata.chelsea())
    x = preprocess_batch([decode(_encode(rgb, ".png")), decode(_encode(rgb, ".jpg"))])
    assert x.shape == (2, 3, 224, 224)
    assert np.abs(x[0] - x[1]).mean() < 0.05


def test_hostile_jpeg_marker_floods_are_refused_cheaply():
    # Millions of empty segments would otherwise be walked one by one under the GIL.
    flood = b"\xff\xd8" + b"\xff\xfe\x00\x02" * 100_000
    with pytest.raises(images.ImageError) as e:
        images.decode(flood)
    assert e.value.code == "not-an-image" and "marker segments" in str(e.value)
    fill = b"\xff\xd8" + b"\xff" * 1_000_000
    with pytest.raises(images.ImageError) as e:
        images.decode(fill)
    assert e.value.code == "truncated"


# ------------------------------------------------------------------------------------- decoding cost


def test_png_bomb_is_refused_from_its_chunks_without_inflating(png_bomb, no_decoding, monkeypatch):
    # The bomb at 1/100 scale, same ratio: 100x100 (30,100 raster bytes), 100 MB of zeros.
    data = png_bomb(100, 100, 100 << 20)
    assert len(data) < 120_000
    monkeypatch.setattr(png_mod.zlib, "decompressobj", None)  # the header walk alone must refuse it
    for split in (1, 300):  # one IDAT, or many
        with pytest.raises(ImageError) as info:
            probe(png_bomb(100, 100, 100 << 20, idat_chunks=split))
        err = info.value
        assert err.code == "bomb" and err.details["raster_bytes"] == 30_100
        assert err.details["compressed_bytes"] > 100_000
        assert "100x100" in str(err)


def test_png_bomb_in_a_large_raster_is_stopped_at_the_raster_size(png_bomb, no_decoding, monkeypatch):
    # 1000x1000 RGB needs 3,001,000 bytes; 64 MB of zeros compress to less than that, so the chunk walk
    # cannot tell; the bounded inflate stops after the raster instead of inflating all 64 MB.
    data = png_bomb(1000, 1000, 64 << 20)
    assert probe(data).width == 1000
    inflated = []
    real = png_mod.zlib.decompressobj

    class Counting:
        def __init__(self) -> None:
            self.z = real()

        def decompress(self, buf, max_length=0):
            out = self.z.decompress(buf, max_length)
            inflated.append(len(out))
            return out

        def __getattr__(self, name):
            return getattr(self.z, name)

    monkeypatch.setattr(png_mod.zlib, "decompressobj", Counting)
    with pytest.raises(ImageError) as info:
        decode(data)
    assert info.value.code == "bomb" and info.value.details["raster_bytes"] == 3_001_000
    assert sum(inflated) <= 3_001_000 + png_mod._INFLATE_STEP


@pytest.mark.parametrize("interlace", [0, 1])
@pytest.mark.parametrize(("colour", "depth", "samples"), [(0, 1, 1), (0, 16, 1), (2, 8, 3), (3, 4, 1),
                                                           (4, 8, 2), (6, 16, 4)])
def test_png_image_data_must_inflate_to_exactly_its_raster(colour, depth, samples, interlace, make_png):
    # Exactly the raster decodes; one byte more is refused before OpenCV (libpng would inflate it all),
    # one byte less is corrupt. Odd sizes exercise the Adam7 pass arithmetic and sub-byte packing.
    w, h = 21, 17
    exact = png_mod._png_raster_bytes(w, h, samples * depth, bool(interlace))
    plte = _png_chunk(b"PLTE", bytes(3 * 16)) if colour == 3 else b""

    def png(n: int) -> bytes:
        data = make_png(w, h, zlib.compress(bytes(n)), colour=colour, depth=depth, interlace=interlace)
        return data[:33] + plte + data[33:]

    assert decode(png(exact)).shape == (h, w, 3)
    assert _code(png(exact + 1)) == "bomb"
    assert _code(png(exact - 1)) == "not-an-image"


def test_jpeg_with_too_many_scans_is_refused_without_decoding(no_decoding):
    data = _encode(_blocks_rgb(), ".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
    sos = [i for i in range(len(data) - 1) if data[i:i + 2] == b"\xff\xda"]
    assert 1 < len(sos) <= images.JPEG_MAX_SCANS  # a real progressive file passes
    assert probe(data).format == "jpeg"
    last_scan = data[sos[-1]:-2]  # an empty refinement scan still costs a pass over every block
    flood = data[:-2] + last_scan * images.JPEG_MAX_SCANS + b"\xff\xd9"
    with pytest.raises(ImageError) as info:
        decode(flood)
    assert info.value.code == "bomb" and info.value.details["max_scans"] == images.JPEG_MAX_SCANS
