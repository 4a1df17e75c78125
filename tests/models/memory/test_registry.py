"""The memory registry (models/memory/registry.py): a map's `memory` option names one, beside the
backbones' registry; the pipeline never names a memory itself."""

from __future__ import annotations

import numpy as np
import pytest

from models import presets
from models.memory import registry
from models.memory.temporal_memory import StreamContext, TemporalMemory

TM = {"columnDimensions": 64, "cellsPerColumn": 4, "maxSegmentsPerCell": 2, "maxSynapsesPerSegment": 4,
      "activationThreshold": 2, "minThreshold": 1}


def test_tm_and_none_are_registered():
    assert registry.names() == ["tm", "none"]
    assert registry.get("tm").sequential and not registry.get("none").sequential
    with pytest.raises(ValueError, match="known: tm, none"):
        registry.get("lstm")
    with pytest.raises(ValueError, match="twice"):
        registry.register("tm", sequential=True)(lambda *a: np.zeros(0))


def test_none_is_the_code_itself_and_tm_the_temporal_memorys_cells():
    tm, ctx = TemporalMemory(presets.TmOptions.of(TM)), StreamContext()
    code = np.array([1, 5, 9])
    assert np.array_equal(registry.get("none").winners(tm, code, True, ctx), code)
    assert ctx.active_cells.size == 0  # the ablation leaves the context alone
    cells = registry.get("tm").winners(tm, code, True, ctx)
    assert np.array_equal(np.unique(cells // 4), code)  # one winner cell per active column
