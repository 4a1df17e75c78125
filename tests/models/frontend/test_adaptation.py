"""Stream adaptation (models.frontend.adaptation): removes what recent frames share, causally."""

from __future__ import annotations

import numpy as np
import pytest

from models.evaluation import sequences
from models.frontend import slsbh
from models.frontend.adaptation import RunningMean, running_mean_subtract


def _stream(n: int = 200, d: int = 256, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    common = 10.0 * rng.normal(size=d)  # one camera's shared component, much larger than the places
    return (common + rng.normal(size=(n, d))).astype(np.float32)


def test_removes_the_shared_component():
    x = _stream()
    xn = x / np.linalg.norm(x, axis=1, keepdims=True)
    y = running_mean_subtract(x, tau=20)
    off_diag = ~np.eye(len(x), dtype=bool)
    # Later frames (after warm-up) of different places: almost identical before, unrelated after.
    assert (xn @ xn.T)[off_diag].mean() > 0.9
    assert abs((y[40:] @ y[40:].T)[off_diag[40:, 40:]].mean()) < 0.1
    np.testing.assert_allclose(np.linalg.norm(y, axis=1), 1.0, rtol=1e-5)


def test_is_causal_and_keeps_the_first_frame():
    x = _stream(n=50)
    y = running_mean_subtract(x, tau=10)
    x2 = x.copy()
    x2[30:] += 5.0  # the future changes
    np.testing.assert_array_equal(running_mean_subtract(x2, tau=10)[:30], y[:30])
    np.testing.assert_allclose(y[0], x[0] / np.linalg.norm(x[0]), rtol=1e-6)


def test_rejects_a_bad_time_constant():
    with pytest.raises(ValueError, match="tau"):
        running_mean_subtract(_stream(n=3), tau=0)


def test_adapting_projections_gives_the_codes_of_adapted_features():
    """The service adapts y = x·P (k values), not x (D values); linearity makes the codes equal."""
    x = _stream(n=40, d=256)
    hasher = slsbh.Hasher(slsbh.make_projection(256, 64, seed=3), 0.1)
    np.testing.assert_array_equal(sequences.codes(hasher, x, adapt_tau=8),
                                  hasher(running_mean_subtract(x, tau=8)))


def test_state_round_trip_continues_identically():
    rng = np.random.default_rng(4)
    vs = rng.normal(size=(12, 8))
    a = RunningMean(5)
    for v in vs[:6]:
        a.subtract(v)
    b = RunningMean.from_state(5, a.state())
    assert RunningMean.from_state(5, RunningMean(5).state()).mean is None
    for v in vs[6:]:
        np.testing.assert_array_equal(a.subtract(v), b.subtract(v))
