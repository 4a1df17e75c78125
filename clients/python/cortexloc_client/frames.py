"""What an observation's body is: encoded image bytes (JPEG, PNG, WebP, BMP) sent with their media type,
or a numpy array sent as a raw frame (`application/octet-stream` with `encoding`, `width`, `height`).

numpy is optional (`pip install 'cortexloc-client[numpy]'`); it is imported only when an array is given.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

if TYPE_CHECKING:
    import numpy as np

__all__ = ["ColourOrder", "Frame", "frame_body", "sniff_media_type"]

#: Channel order of an HxWx3 uint8 array: `rgb8` (PIL, imageio) or `bgr8` (OpenCV, most ROS cameras).
ColourOrder = Literal["rgb8", "bgr8"]

_MAGIC: tuple[tuple[bytes, int, str], ...] = (
    (b"\xff\xd8\xff", 0, "image/jpeg"),
    (b"\x89PNG\r\n\x1a\n", 0, "image/png"),
    (b"WEBP", 8, "image/webp"),
    (b"BM", 0, "image/bmp"),
)


@dataclass(frozen=True)
class Frame:
    """One observation body: the bytes, their Content-Type and the query parameters they need."""

    content: bytes
    media_type: str
    params: dict[str, str] = field(default_factory=dict)


def sniff_media_type(data: bytes) -> str:
    """The media type of encoded image bytes from their magic number; `application/octet-stream`
    (which the service sniffs itself) when unknown."""
    for magic, offset, media in _MAGIC:
        if data[offset:offset + len(magic)] == magic:
            return media
    return "application/octet-stream"


def frame_body(image: bytes | bytearray | memoryview | np.ndarray, colour: ColourOrder = "rgb8") -> Frame:
    """The request body for an image.

    Args:
        image: encoded bytes, or an array: (H, W, 3) uint8 in `colour` order, (H, W) uint8 (`mono8`) or
            (H, W) uint16 of either byte order (`mono16`, sent little-endian). Any memory layout (it is
            sent as a contiguous copy).
        colour: the channel order of an (H, W, 3) array; ignored otherwise.

    Raises:
        ValueError: an array of another shape or dtype.
    """
    if isinstance(image, (bytes, bytearray, memoryview)):
        data = bytes(image)
        return Frame(data, sniff_media_type(data))
    import numpy as np

    arr: Any = np.asarray(image)
    kind = (arr.dtype.kind, arr.dtype.itemsize)  # any byte order: (H, W) '>u2' from a big-endian camera
    if arr.ndim == 3 and arr.shape[2] == 3 and kind == ("u", 1):
        if colour not in ("rgb8", "bgr8"):
            raise ValueError(f"colour must be 'rgb8' or 'bgr8', not {colour!r}")
        encoding = colour
    elif arr.ndim == 2 and kind == ("u", 1):
        encoding = "mono8"
    elif arr.ndim == 2 and kind == ("u", 2):
        encoding, arr = "mono16", arr.astype("<u2", copy=False)
    else:
        raise ValueError(f"a frame is an (H, W, 3) uint8, (H, W) uint8 or (H, W) uint16 array, not "
                         f"{arr.shape} {arr.dtype}")
    height, width = arr.shape[:2]
    return Frame(np.ascontiguousarray(arr).tobytes(), "application/octet-stream",
                 {"encoding": encoding, "width": str(width), "height": str(height)})
