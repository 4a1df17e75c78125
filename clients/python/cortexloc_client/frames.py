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

#: Channel order of an (H, W, 3) or (H, W, 4) uint8 array, named as ROS `sensor_msgs/Image` encodings (so a
#: node may pass `msg.encoding`): `rgb8` / `rgba8` (PIL, imageio) or `bgr8` / `bgra8` (OpenCV, most ROS
#: cameras). The alpha channel is dropped (a camera's is padding), so `rgba8` means the same as `rgb8`.
ColourOrder = Literal["rgb8", "bgr8", "rgba8", "bgra8"]
_ORDER: dict[str, str] = {"rgb8": "rgb8", "rgba8": "rgb8", "bgr8": "bgr8", "bgra8": "bgr8"}
#: What `colour` may be beside a one-channel array, where it is ignored: a colour order (a default, a
#: camera's setting) or a mono encoding's ROS name, so that `colour=msg.encoding` works for every frame.
_MONO_COLOURS = (*_ORDER, "mono8", "mono16")

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
        image: encoded bytes, or an array: (H, W, 3) uint8 in `colour` order, (H, W, 4) uint8 in `colour`
            order with alpha last (the alpha channel is dropped), (H, W) or (H, W, 1) uint8 (`mono8`),
            or (H, W) or (H, W, 1) uint16 of either byte order (`mono16`, sent little-endian). Any
            memory layout (it is sent as a contiguous copy).
        colour: the channel order of an (H, W, 3) or (H, W, 4) array (`ColourOrder`). Ignored for a
            one-channel array, where it may also be `mono8` or `mono16` (a ROS encoding's name), and
            for encoded bytes; any other value is refused even there (a typo would otherwise pass
            unseen until a colour frame came).

    Raises:
        ValueError: an array of another shape or dtype, one without pixels (a zero height or width),
            or a `colour` it does not take.
    """
    if isinstance(image, (bytes, bytearray, memoryview)):
        data = bytes(image)
        return Frame(data, sniff_media_type(data))
    import numpy as np

    arr: Any = np.asarray(image)
    shape = arr.shape
    kind = (arr.dtype.kind, arr.dtype.itemsize)  # any byte order: (H, W) '>u2' from a big-endian camera
    if arr.ndim == 3 and arr.shape[2] == 1:  # a one-channel image as OpenCV and cv_bridge may hand it
        arr = arr[:, :, 0]
    if arr.ndim == 3 and arr.shape[2] in (3, 4) and kind == ("u", 1):
        if colour not in _ORDER:
            raise ValueError(f"colour must be one of {', '.join(_ORDER)}, not {colour!r}")
        encoding, arr = _ORDER[colour], arr[:, :, :3]
    elif arr.ndim == 2 and kind in (("u", 1), ("u", 2)):
        if colour not in _MONO_COLOURS:
            raise ValueError(f"colour must be one of {', '.join(_MONO_COLOURS)} (ignored for a one-channel "
                             f"array), not {colour!r}")
        encoding = "mono8" if kind == ("u", 1) else "mono16"
        arr = arr.astype("<u2", copy=False) if encoding == "mono16" else arr
    else:
        raise ValueError(f"a frame is an (H, W, 3) or (H, W, 4) uint8, or an (H, W) or (H, W, 1) uint8 or "
                         f"uint16 array, not {shape} {arr.dtype}")
    height, width = arr.shape[:2]
    if not (height and width):  # the service would refuse it (400 about `width` or `height`)
        raise ValueError(f"a frame has at least one pixel: this array is {shape} {arr.dtype}")
    return Frame(np.ascontiguousarray(arr).tobytes(), "application/octet-stream",
                 {"encoding": encoding, "width": str(width), "height": str(height)})
