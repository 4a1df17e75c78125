"""Stream adaptation: subtract a running mean of the features before hashing.

Why: backbone features of one camera share a large common component (lighting, season, the camera
itself). sLSBH keeps the n largest and n smallest projections, so that common component picks the same
bits for every frame: on Nordland (random AlexNet weights, s = 0.02) a summer and a winter frame of
different places share 12 of 40 bits on average and the same place only 16 (docs/results.md §7). The
Temporal Memory then sees near-identical codes everywhere and predicts by chance
(docs/design/science.md §3.8). Subtracting the stream's own recent mean removes what all recent frames share,
as retinal adaptation does, and is causal: frame t uses frames <= t only, so a robot can run it online.

The service adapts each stream in projection space (y = x·P, k values instead of D features): the
projection is linear, so the running mean of y is the projection of the running mean of x, and the
positive scale of the L2 normalisation does not change which entries are largest. The sLSBH code of
an adapted projection is therefore the code of the adapted features.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class RunningMean:
    """One stream's running mean: the mean of the first `tau` vectors, then an EMA with weight 1/tau.

    Attributes:
        tau: time constant in frames (>= 1).
        count: vectors seen so far.
        mean: (m,) float64 running mean, None before the first vector.
    """

    tau: int
    count: int = 0
    mean: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.tau < 1:
            raise ValueError(f"tau must be >= 1, got {self.tau}")

    def subtract(self, v: np.ndarray) -> np.ndarray:
        """Update the mean with `v` (m,), then return v minus it (`v` itself for the first vector)."""
        v = np.asarray(v, dtype=np.float64)
        if self.mean is None:
            self.mean = np.zeros_like(v)
        self.count += 1
        self.mean += (v - self.mean) / min(self.count, self.tau)
        return v - self.mean if self.count > 1 else v.copy()

    def state(self) -> np.ndarray:
        """(1 + m,) float64: count, then the mean (empty mean before the first vector)."""
        mean = np.zeros(0) if self.mean is None else self.mean
        return np.concatenate([[float(self.count)], mean])

    @classmethod
    def from_state(cls, tau: int, state: np.ndarray) -> RunningMean:
        count = int(state[0])
        return cls(tau, count, np.array(state[1:], dtype=np.float64) if count else None)


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
    running = RunningMean(tau)
    x = np.asarray(x, dtype=np.float32)
    out = np.empty_like(x)
    for i, row in enumerate(x):
        out[i] = running.subtract(row)
    norms = np.linalg.norm(out, axis=1, keepdims=True)
    return out / np.where(norms > 0, norms, 1.0)
