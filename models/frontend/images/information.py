"""How much a decoded frame can say about where it was taken: its contrast (docs/design/science.md §11.7).

A near-black tunnel frame, a lens cap, a blank wall or an overexposed frame is one flat level plus a
few bright or dark specks (a lamp, the camera's timestamp overlay) and the sensor's noise: the backbone
still gives it a code, and two such frames of different places share most of it. The measure is the
spread between the 5th and 95th percentile of the frame's luma, as a fraction of the 8-bit range, less
what the frame's own sensor noise explains: specks covering under 5 % of the frame do not count, nor
does pixel noise (a camera's gain turned up in a tunnel), whose level is estimated from the frame
itself (Immerkær's operator, "Fast noise variance estimation", CVIU 64(2), 1996) and taken off the
spread in quadrature. On Nordland (docs/results.md §10.5, §11; tests/models/frontend/test_information.py)
near-black tunnel frames measure under the localiser's floor with or without pixel noise of σ 8, and
frames with visible structure (dim winter frames included) over it. The front end measures; the
localiser decides what it means (`models.localisation.localiser.MIN_CONTRAST`).
"""

from __future__ import annotations

import cv2
import numpy as np

#: The longer side the frame is measured at (INTER_AREA): the cost is one small resize whatever the frame.
SIDE = 64

# Immerkær's noise operator: the difference of two Laplacians, blind to a frame's planes and ramps (the
# scene's slow changes), so what it sees on a flat frame is the sensor's noise.
_NOISE = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
# the 5-95 % spread of Gaussian noise of σ 1: 2 × 1.645
_NOISE_SPREAD = 3.29


def contrast(rgb: np.ndarray) -> float:
    """The frame's robust contrast: (p95 − p5) of its luma, less the spread its estimated pixel noise
    alone would give (in quadrature), / 255, in [0, 1].

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
    spread = float(hi - lo)
    return float(np.sqrt(max(0.0, spread * spread - (_NOISE_SPREAD * _noise_sigma(grey)) ** 2))) / 255.0


def _noise_sigma(grey: np.ndarray) -> float:
    """The σ of the pixel noise of `grey` ((H, W) uint8 or float), in grey levels (Immerkær 1996): 0 on a
    frame under 3 pixels a side."""
    h, w = grey.shape[:2]
    if h < 3 or w < 3:
        return 0.0
    r = cv2.filter2D(np.asarray(grey, np.float32), -1, _NOISE)[1:-1, 1:-1]
    return float(np.sqrt(np.pi / 2.0) * np.abs(r).sum() / (6.0 * (w - 2) * (h - 2)))
