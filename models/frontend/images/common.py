"""What every part of `models.frontend.images` shares: the limits, the formats, the one error type and
the parsers' result (docs/design/service.md §1.2, §2)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

# Re-exported: the limits live where the settings can read them without loading cv2.
from models.frontend.limits import DEFAULT_MAX_ASPECT as DEFAULT_MAX_ASPECT
from models.frontend.limits import DEFAULT_MAX_BYTES as DEFAULT_MAX_BYTES
from models.frontend.limits import DEFAULT_MAX_PIXELS as DEFAULT_MAX_PIXELS
from models.frontend.limits import DEFAULT_MIN_SIDE as DEFAULT_MIN_SIDE

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

FORMATS = ("jpeg", "png", "bmp", "webp")
MODES = ("crop", "squash")
ERROR_CODES = frozenset(
    {"empty", "too-large", "not-an-image", "truncated", "too-many-pixels", "unsupported-format", "degenerate",
     "bomb", "size-mismatch", "unsupported-encoding"}
)

_FORMAT_NAMES = {"jpeg": "JPEG", "png": "PNG", "bmp": "BMP", "webp": "WebP"}


class ImageError(ValueError):
    """An upload that is not a decodable image within the limits.

    The HTTP service maps `code` to a 4xx problem+json (docs/design/service.md §2): `too-large` -> 413
    payload-too-large, `too-many-pixels` -> 413 image-too-large, `unsupported-format` -> 415,
    `degenerate` (too long and thin, or too small) -> 422 degenerate-image, `bomb` -> 422
    decompression-bomb, `empty` / `not-an-image` / `truncated` -> 422 undecodable-image; for raw frames
    (`raw.py`) `size-mismatch` -> 422 raw-frame-size-mismatch, `unsupported-encoding` -> 415.

    Attributes:
        code: one of `ERROR_CODES`: "empty", "too-large", "not-an-image", "truncated", "too-many-pixels",
            "unsupported-format", "degenerate", "size-mismatch" and "unsupported-encoding" (raw
            frames: the body is not width x height x channels x bytes long; an encoding not known),
            "bomb" (a small file whose decoding would cost far more
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
        format: "jpeg", "png", "bmp", "webp", or "raw" (an uncompressed frame, `raw.RawFrame`).
        width: stored width in pixels (before any EXIF rotation, which may swap it with height).
        height: stored height in pixels.
    """

    format: str
    width: int
    height: int

    @property
    def pixels(self) -> int:
        return self.width * self.height


# The header parsers (jpeg, png, bmp_webp) each return a `_Header`. They raise ImageError("truncated")
# when the file ends before the dimensions, ImageError("not-an-image") when the structure is corrupt.
# `complete` says whether the file reaches its end marker, `damaged` holds a "not-an-image" error for a
# file that does but whose contents stop short of the image (a progressive JPEG's missing scans) and
# `costly` a "bomb" error; all are reported separately so that the pixel cap is checked first (a tiny file
# that claims 20000×20000 is "too-many-pixels", whatever follows its header).


class _Header(NamedTuple):
    width: int
    height: int
    complete: bool
    costly: ImageError | None = None  # raised by `probe` after the size and completeness checks
    bits_per_pixel: int | None = None  # where a format's pixels may hold more than 24 bits (PNG)
    damaged: ImageError | None = None  # raised by `probe` after the completeness check, before `costly`


def _check_shape(width: int, height: int, fmt: str, max_aspect: float | None,
                 min_side: int | None) -> None:
    """The shape rules of every frame, encoded or raw (docs/design/service.md §1.2): the long side at most
    `max_aspect` times the short one, the short side at least `min_side` pixels; None disables either.

    Raises:
        ImageError: "degenerate".
    """
    if max_aspect is not None and max(width, height) > max_aspect * min(width, height):
        raise ImageError("degenerate",
                         f"image is {width}x{height}: its long side is more than {max_aspect:g} times "
                         f"its short side",
                         width=width, height=height, max_aspect=max_aspect, format=fmt)
    if min_side is not None and min(width, height) < min_side:
        raise ImageError("degenerate",
                         f"image is {width}x{height}: its short side is under {min_side} pixels, too small "
                         "to be a view of a place", width=width, height=height, min_side=min_side, format=fmt)


def _truncated(fmt: str, detail: str, n: int) -> ImageError:
    return ImageError("truncated", f"{_FORMAT_NAMES[fmt]} image is truncated: {detail} ({n} bytes received)",
                      format=fmt, received_bytes=n)


def _corrupt(fmt: str, detail: str) -> ImageError:
    return ImageError("not-an-image", f"corrupt {_FORMAT_NAMES[fmt]} image: {detail}", format=fmt)

