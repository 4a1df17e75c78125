"""Stream adaptation: subtract a running mean of the features before hashing.

Why: backbone features of one camera share a large common component (lighting, season, the camera
itself). sLSBH keeps the n largest and n smallest projections, so that common component picks the same
bits for every frame: on Nordland (random AlexNet weights, s = 0.02) a summer and a winter frame of
different places share 12 of 40 bits on average and the same place only 16 (docs/results.md §7). The
Temporal Memory then sees near-identical codes everywhere and predicts by chance (science.md §3.8).
Subtracting the stream's own recent mean removes what all recent frames share, as retinal adaptation
does, and is causal: frame t uses frames <= t only, so a robot can run it online.
"""

from __future__ import annotations

import numpy as np


def running_mean_subtract(x: np.ndarray, tau: int) -> np.ndarray:
    """Each row minus the running mean of the rows up to and including it, re-normalised.

    The mean is the plain average over the first `tau` rows, then an exponential moving average with
    time constant `tau` (weight 1/tau for the newest row). The first row has no history and is kept.

    Args:
        x: (n, D) features of one stream in time order.
        tau: time constant in frames (>= 1).

    Returns:
        (n, D) float32, rows L2-normalised (a row equal to the mean stays zero).
    """
    if tau < 1:
        raise ValueError(f"tau must be >= 1, got {tau}")
    x = np.asarray(x, dtype=np.float32)
    out = np.empty_like(x)
    mean = np.zeros(x.shape[1], dtype=np.float64)
    for i, row in enumerate(x):
        mean += (row - mean) / min(i + 1, tau)
        out[i] = row - mean if i else row
    norms = np.linalg.norm(out, axis=1, keepdims=True)
    return out / np.where(norms > 0, norms, 1.0)
