"""ONNX Runtime computes the torch reference's codes on real frames (issue 24): the shared Nordland route,
the service default backbone and preset (service/evaluation/runtime_parity.py,
docs/design/science.md §6.1)."""

from __future__ import annotations

import pytest

from models.evaluation.datasets import nordland_dir

pytestmark = pytest.mark.skipif(not (nordland_dir() / "winter").is_dir(),
                                reason=f"shared Nordland data not found at {nordland_dir()} "
                                       "(set CORTEXLOC_SHARED_DATA)")

#: Two of the five 200-frame windows of the cross-season tables, the hardest `tune` one and the last of
#: `test` (3 minutes for all five held `make test` up on 2 cores); all five, and tune and test whole
#: (894 frames each), are run by `cortexloc eval runtime-parity` (docs/benchmarks.md §10).
WINDOWS = ["1-200", "1589-1788"]


@pytest.fixture(scope="module")
def result():
    from service.evaluation.runtime_parity import parity

    return parity(WINDOWS)


def test_codes_on_real_frames_overlap_at_least_99_percent(result):
    assert result["frames"] == 2 * 200 * len(WINDOWS)
    assert result["overlap_mean"] >= 0.99, result


def test_service_recall_at_1_within_0_01_of_torch_on_every_window(result):
    for window, r in result["windows"].items():
        assert abs(r["onnxruntime"] - r["torch"]) <= 0.01, (window, r)
