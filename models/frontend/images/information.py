"""How much a decoded frame can say about where it was taken: its contrast (docs/design/science.md §11.7).

A near-black tunnel frame, a lens cap, a blank wall or an overexposed frame is one flat level plus a
few bright or dark specks (a lamp, the camera's timestamp overlay): the backbone still gives it a code,
and two such frames of different places share most of it. The measure is the spread between the 5th
and 95th percentile of the frame's luma, as a fraction of the 8-bit range: specks covering under 5 %
of the frame do not count, nor does sensor noise of a few levels; noise of σ 8 (a camera's gain
turned up in a tunnel) does: it spreads a flat frame's range by about 26 levels, and such frames
measure as informative (docs/results.md §11, a limit left as it is). Measured on Nordland
(docs/results.md §10.5): near-black tunnel frames 0-0.02, every frame with visible structure (dim
winter frames included) 0.04 or more. The front end measures; the localiser decides what it means
(`models.localisation.localiser.MIN_CONTRAST`).
"""

from __future__ import annotations

import cv2
import numpy as np

#: The longer side the frame is measured at (INTER_AREA): the cost is one small resize whatever the frame.
SIDE = 64


def contrast(rgb: np.ndarray) -> float:
    """The frame's robust contrast: (p95 − p5) of its luma / 255, in [0, 1].

    Args:
        rgb: (H, W, 3) uint8 RGB, a decoded frame (`decode`), or (H, W) uint8 grey.
    """
    img = np.asarray(rgb)
    grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    h, w = grey.shape[:2]
    scale = SIDE / max(h, w)
    if scale < 1.0:
        grey = cv2.resize(grey, (max(1, round(w * scale)), max(1, round(h * scale))),
                          interpolation=cv2.INTER_AREA)
    lo, hi = np.percentile(grey, (5.0, 95.0))
    return float(hi - lo) / 255.0
