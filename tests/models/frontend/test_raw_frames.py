"""Raw sensor frames (`models.frontend.images.raw`) and thumbnails: the decoded RGB, the checks and
their order, one `ImageError` code per failure (docs/design/service.md §1.2)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from models.frontend import images
from models.frontend.images import ImageError, RawFrame


def scene(h: int = 48, w: int = 64) -> np.ndarray:
    """(h, w, 3) uint8 RGB with distinct channels, so a swapped order shows."""
    rng = np.random.default_rng(3)
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)


def raw(arr: np.ndarray, encoding: str) -> RawFrame:
    return RawFrame(np.ascontiguousarray(arr).tobytes(), encoding, arr.shape[1], arr.shape[0])


def test_bgr8_and_rgb8_of_one_picture_decode_alike() -> None:
    rgb = scene()
    assert np.array_equal(images.decode(raw(rgb, "rgb8")), rgb)
    assert np.array_equal(images.decode(raw(rgb[:, :, ::-1], "bgr8")), rgb)


def test_a_raw_frame_decodes_as_its_png_does() -> None:
    rgb = scene()
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    assert np.array_equal(images.decode(png.tobytes()), images.decode(raw(rgb, "rgb8")))


def test_grey_frames_become_three_equal_channels() -> None:
    grey = scene()[:, :, 0]
    out = images.decode(raw(grey, "mono8"))
    assert out.shape == (*grey.shape, 3) and all(np.array_equal(out[:, :, c], grey) for c in range(3))
    deep = grey.astype(np.uint16) * 257  # 8 bits spread over 16: scales back exactly
    deep[0, 0] = 65535
    out16 = images.decode(raw(deep.astype("<u2"), "mono16"))
    assert np.array_equal(out16[:, :, 0], np.round(deep / 257).astype(np.uint8))
    assert out16[0, 0, 0] == 255


@pytest.mark.parametrize(("frame", "code"), [
    (RawFrame(bytes(47), "mono8", 8, 6), "size-mismatch"),  # one byte short
    (RawFrame(bytes(48), "mono16", 8, 6), "size-mismatch"),  # mono8's size for mono16
    (RawFrame(b"", "rgb8", 0, 6), "size-mismatch"),
    (RawFrame(bytes(48), "yuv422", 8, 6), "unsupported-encoding"),
    (RawFrame(bytes(4000), "mono8", 1, 4000), "degenerate"),
])
def test_each_failure_has_its_code(frame: RawFrame, code: str) -> None:
    with pytest.raises(ImageError) as e:
        images.probe(frame)
    assert e.value.code == code
    with pytest.raises(ImageError):
        images.decode(frame)


def test_the_size_is_checked_before_the_limits() -> None:
    # 1 x 4000 is degenerate, but a body of the wrong length says first that it is not that frame.
    with pytest.raises(ImageError) as e:
        images.probe(RawFrame(bytes(10), "mono8", 1, 4000))
    assert e.value.code == "size-mismatch" and e.value.details["expected_bytes"] == 4000


def test_the_same_pixel_and_byte_limits_as_encoded_images() -> None:
    frame = RawFrame(bytes(64 * 64), "mono8", 64, 64)
    assert images.probe(frame) == images.ImageInfo("raw", 64, 64)
    with pytest.raises(ImageError) as e:
        images.probe(frame, max_pixels=64 * 63)
    assert e.value.code == "too-many-pixels"
    with pytest.raises(ImageError) as e:
        images.probe(frame, max_bytes=64 * 63)
    assert e.value.code == "too-large"


def test_a_thumbnail_is_a_small_jpeg_of_the_frame() -> None:
    rgb = cv2.resize(scene(6, 8), (320, 240), interpolation=cv2.INTER_CUBIC)
    jpeg = images.thumbnail(rgb)
    assert jpeg[:3] == b"\xff\xd8\xff"
    small = images.decode(jpeg)
    assert max(small.shape[:2]) == images.THUMBNAIL_SIDE and small.shape[:2] == (96, 128)
    tiny = images.decode(images.thumbnail(rgb[:20, :30]))
    assert tiny.shape[:2] == (20, 30)  # never enlarged
    expected = cv2.resize(rgb, (128, 96), interpolation=cv2.INTER_AREA).astype(int)
    assert np.abs(small.astype(int) - expected).mean() < 8  # the same picture, JPEG-close
