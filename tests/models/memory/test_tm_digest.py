"""The Temporal Memory's outputs are pinned bit for bit: winner cells of every step and the synapse state
after it, as digests recorded from the kernel before it was made faster (issue 25). A faster kernel must
compute exactly what docs/design/science.md §3.3-§3.6 computed before, including every random draw.

The digests depend on NumPy's PCG64 stream as drawn through numba (§3.6), so they hold for one NumPy and
numba build; the test skips on another.
"""

from __future__ import annotations

import hashlib

import numba
import numpy as np
import pytest

from models import presets
from models.evaluation.bench import random_sequence
from models.memory.temporal_memory import TemporalMemory

RECORDED_WITH = ("2.4.6", "0.68.1")

# Each scenario binds every rule: segments are evicted (LRU), synapses overrun and decay, repeated
# stretches are predicted and punished, and inference steps interleave with learning.
SCENARIOS = {
    "numenta-caps": ("numenta-defaults", {"columnDimensions": 256, "cellsPerColumn": 4,
                                          "maxSegmentsPerCell": 8, "maxSynapsesPerSegment": 32,
                                          "predictedSegmentDecrement": 0.01}, 40),
    "service": ("cortexloc-default", {"columnDimensions": 512, "maxSegmentsPerCell": 1}, 77),
    "grid": ("cortexloc-grid", {"columnDimensions": 256, "maxSegmentsPerCell": 4,
                                "maxSynapsesPerSegment": 16}, 20),
}

DIGESTS = {
    "numenta-caps": "c4b6a17f63a6942046c307220897a1b90e98ba4941c7a6cb20c895413abcb784",
    "service": "73bc87a67143c070469d30f79debe592bc857bb7e751bff67a43315f142c76e3",
    "grid": "523f4934716b6807dce91f74dc76b4ec46ae9a3dc629563465050bc5e068ac04",
}


def digest(name: str, steps: int = 400) -> str:
    preset, overrides, active = SCENARIOS[name]
    tm = TemporalMemory(presets.TmOptions.of(presets.tm_params(preset, overrides)))
    cols = tm.n_columns
    rng = np.random.Generator(np.random.PCG64(5))
    loop = random_sequence(30, cols, active, seed=3)
    h = hashlib.sha256()
    for i in range(steps):
        if i % 90 < 60:  # a repeated loop, with one column in ten replaced
            x = loop[i % 30].copy()
            swap = rng.random(x.size) < 0.1
            x[swap] = rng.integers(0, cols, int(swap.sum()))
        else:  # novel input
            x = rng.choice(cols, active, replace=False)
        learn = i % 7 != 3
        if i % 45 == 0:
            tm.reset()
        h.update(tm.compute(x, learn=learn).tobytes())
        h.update(np.array(list(tm.context.stats.as_dict().values()), np.int64).tobytes())
    state = tm.state_dict()
    for k in sorted(state):
        if k not in ("numpy_version", "numba_version"):
            h.update(k.encode())
            h.update(np.ascontiguousarray(state[k]).tobytes())
    size = tm.size()
    # The caps bind in every scenario, so the eviction and overrun paths are part of the digest.
    assert size["evictions"] + size["overrun_destroyed"] + size["decay_destroyed"] > 0, size
    return h.hexdigest()


@pytest.mark.skipif((np.__version__, numba.__version__) != RECORDED_WITH,
                    reason=f"digests recorded with numpy/numba {RECORDED_WITH}")
@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_kernel_matches_the_recorded_digest(name):
    assert digest(name) == DIGESTS[name]


if __name__ == "__main__":
    for n in SCENARIOS:
        print(n, digest(n))
