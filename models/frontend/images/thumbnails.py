"""A small JPEG of a decoded frame, for people to look at (docs/design/service.md §4.2): never read by
the memory, so its size and quality only trade disk for legibility."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["THUMBNAIL_QUALITY", "THUMBNAIL_SIDE", "thumbnail"]

#: The longest side of a thumbnail in pixels (the one home of this size).
THUMBNAIL_SIDE = 128
THUMBNAIL_QUALITY = 80


def thumbnail(rgb: np.ndarray, side: int = THUMBNAIL_SIDE) -> bytes:
    """(H, W, 3) uint8 RGB -> JPEG bytes whose longest side is `side` (never enlarged)."""
    h, w = rgb.shape[:2]
    scale = min(1.0, side / max(h, w))
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    small = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA) if scale < 1.0 else rgb
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(small, cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, THUMBNAIL_QUALITY])
    if not ok:  # cv2 fails only on an empty or malformed array, which decode never returns
        raise ValueError(f"cannot encode a thumbnail of shape {rgb.shape}")
    return buf.tobytes()
