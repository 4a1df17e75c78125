"""Where the evaluation data lives: `../shared/data` beside the repository, or $CORTEXLOC_SHARED_DATA.

The data is read in place, never copied into the repository; on a machine without it, callers say so
(tests skip with the path they looked at).
"""

from __future__ import annotations

import os
from pathlib import Path

GRID_SDR_FILES = {"a1n0": "seq_multi_loop_noise0_al1.txt", "a5n05": "seq_multi_loop_noise05_al5.txt"}
GRID_PLACES_FILE = "seq_multi_loop_noNoise_gt.txt"


def shared_data_dir() -> Path:
    """The shared data folder ($CORTEXLOC_SHARED_DATA, else ../shared/data next to the repository)."""
    env = os.environ.get("CORTEXLOC_SHARED_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2].parent / "shared" / "data"


def grid_dir() -> Path:
    """Folder of the CBA 2020 published grid-world files."""
    return shared_data_dir() / "gridworld_cba2020"


def nordland_dir() -> Path:
    """Folder of nordland_tiny_64x32 (summer/ and winter/, frame-aligned by file name)."""
    return shared_data_dir() / "nordland_tiny_64x32"
