"""`cortexloc eval passes` (service/evaluation/passes.py): each pass is driven through the pipeline as the
map writer drives it."""

from __future__ import annotations

import numpy as np
import pytest

from service.evaluation import passes
from service.settings import Settings


def test_a_pass_gives_the_pipeline_each_frames_contrast(monkeypatch: pytest.MonkeyPatch) -> None:
    """The writer passes every frame's contrast as measured at decode (docs/design/science.md §11.7): a
    flat frame is judged as flat (no evidence, a visit of a flat row). The evaluation gives the same;
    before, it gave none and measured flat frames as textured ones."""
    seen: list[float | None] = []
    real = passes.observe

    def spy(*args, **kwargs):
        seen.append(kwargs.get("contrast"))
        return real(*args, **kwargs)

    monkeypatch.setattr(passes, "observe", spy)
    feats = np.random.default_rng(0).normal(size=(8, 32)).astype(np.float32)
    contrast = np.array([0.5, 0.0, 0.4, 0.01, 0.3, 0.3, 0.0, 0.2])
    d = passes.Driver(32, memory="tm", localiser={},
                      map_conf={"backbone": "alexnet", "preset": Settings().default_preset, "seed": 1})
    out = d.drive(passes.Shown(feats, contrast), np.arange(8), "pass-0", learn=True)
    assert seen == pytest.approx(contrast.tolist())
    assert out.rows + out.visits == 8
