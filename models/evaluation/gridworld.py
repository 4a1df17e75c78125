"""Grid-world simulation and the published grid-world data (docs/design/science.md §2).

The simulator emits 2048-bit SDRs that are fed to the Temporal Memory as active columns directly, with
no Spatial Pooler (§1). Everything here is deterministic given its arguments: one PCG64 generator per
data set with a fixed draw order (§2.2 DECISION), so a (seed, settings) pair names a data set.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from models.sdr import INDEX_DTYPE, from_dense

WIDTH = 2048
MEAN_ONES = 40
MODES = ("bernoulli", "exact")
MAX_ALIASING = 6

ENTRY: tuple[tuple[int, int], ...] = ((8, 3), (8, 4), (8, 5))
# Perimeter of x in [8, 12], y in [6, 11]: up the left side, right along the top, down the right side,
# left along the bottom (§2.1). The two vertical sides are walked in opposite directions, which is what
# makes the aliasing of §2.2 confusing for a sequence memory.
LOOP: tuple[tuple[int, int], ...] = (
    (8, 6), (8, 7), (8, 8), (8, 9), (8, 10), (8, 11),
    (9, 11), (10, 11), (11, 11), (12, 11),
    (12, 10), (12, 9), (12, 8), (12, 7), (12, 6),
    (11, 6), (10, 6), (9, 6),
)  # fmt: skip
# After the last full loop the robot walks the left side once more before leaving (§2.1 step 3).
TAIL = LOOP[:6]
EXIT: tuple[tuple[int, int], ...] = ((8, 12), (8, 13), (8, 14), (8, 15), (8, 16))


@dataclass(frozen=True)
class GridData:
    """One grid-world observation sequence.

    Attributes:
        sdrs: T SDRs, each a sorted (w_t,) int32 index array in [0, width): the observation of step t.
        places: (T, 2) int64, the grid cell (x, y) of each step; ground truth is place identity (§8.4).
        width: number of bits of every SDR (2048).
        meta: how the data was made: generator settings (aliasing, noise, loops, seed, mode, width,
            mean_ones) or, for published files, source "published" and the file names.
    """

    sdrs: list[np.ndarray]
    places: np.ndarray
    width: int
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.sdrs)


def trajectory(loops: int = 11) -> np.ndarray:
    """The robot's path through the grid (§2.1).

    Args:
        loops: number of full loops around the rectangle (the published data uses 11).

    Returns:
        (3 + 18·loops + 6 + 5, 2) int64 array of (x, y) places; (212, 2) for loops = 11.
    """
    if loops < 0:
        raise ValueError(f"loops must be >= 0, got {loops}")
    path = list(ENTRY) + list(LOOP) * loops + list(TAIL) + list(EXIT)
    return np.asarray(path, dtype=np.int64)


def _base_sdr(rng: np.random.Generator, mode: str, width: int, mean_ones: int) -> np.ndarray:
    if mode == "bernoulli":
        # Independent bits reproduce the spread of weights in the published files (28-53 ones, §2.2).
        return from_dense(rng.random(width) < mean_ones / width)
    return np.sort(rng.choice(width, size=mean_ones, replace=False)).astype(INDEX_DTYPE)


def _add_noise(sdr: np.ndarray, noise: float, rng: np.random.Generator, width: int) -> np.ndarray:
    k = len(sdr)
    m = int(np.floor(noise * k + 0.5))
    if m == 0:
        # No draws at all, so noise-free data consumes nothing from the generator after the base SDRs.
        return sdr
    cleared = rng.choice(k, size=m, replace=False)
    # With replacement, and a new one may land on a kept one: the weight can drop, as in the data (§2.2).
    added = rng.integers(0, width, size=m)
    kept = np.delete(sdr, cleared)
    return np.union1d(kept, added).astype(INDEX_DTYPE)


def generate(
    aliasing: int,
    noise: float,
    loops: int = 11,
    seed: int = 0,
    mode: str = "bernoulli",
    width: int = WIDTH,
    mean_ones: int = MEAN_ONES,
) -> GridData:
    """Simulate one grid-world data set (§2.2).

    Draw order (DECISION, §2.2), all from one `Generator(PCG64(seed))`: the base SDR of every visited
    place in order of first visit (bernoulli: `random(width)`; exact: `choice(width, mean_ones,
    replace=False)`); aliasing copies without draws; then per step, in step order, the m cleared ones
    (`choice(k, m, replace=False)` over the positions of the place SDR's ones) and the m new positions
    (`integers(0, width, m)`). Steps with m = 0 draw nothing.

    Args:
        aliasing: a in [0, 6]; places (12, 6+i), i < a, get the SDR of (8, 6+i).
        noise: n in [0, 1]; each step clears m = floor(n·k + 0.5) of the k ones and sets m random bits.
        loops: number of full loops (§2.1).
        seed: generator seed.
        mode: "bernoulli" (each bit one with probability mean_ones/width) or "exact" (mean_ones ones).
        width: SDR width in bits.
        mean_ones: expected (bernoulli) or exact weight of a place SDR.

    Returns:
        GridData with T = 3 + 18·loops + 11 observations and their (T, 2) places.
    """
    if isinstance(aliasing, bool) or not isinstance(aliasing, int | np.integer):
        raise TypeError(f"aliasing must be an integer, got {aliasing!r}")
    if not 0 <= aliasing <= MAX_ALIASING:
        raise ValueError(f"aliasing must be in [0, {MAX_ALIASING}], got {aliasing}")
    if not 0.0 <= noise <= 1.0:  # also rejects NaN
        raise ValueError(f"noise must be in [0, 1], got {noise}")
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if width < 1 or not 0 <= mean_ones <= width:
        raise ValueError(f"need width >= 1 and 0 <= mean_ones <= width, got {width}, {mean_ones}")

    places = trajectory(loops)
    rng = np.random.Generator(np.random.PCG64(seed))

    base: dict[tuple[int, int], np.ndarray] = {}
    for x, y in places.tolist():
        if (x, y) not in base:
            base[(x, y)] = _base_sdr(rng, mode, width, mean_ones)
    # The aliased places are drawn above and then overwritten, so a place's SDR never depends on `a`.
    for i in range(aliasing):
        twin, source = (12, 6 + i), (8, 6 + i)
        if twin in base:  # with loops = 0 the right side is never visited
            base[twin] = base[source].copy()

    sdrs = [_add_noise(base[(x, y)], noise, rng, width) for x, y in places.tolist()]
    meta = {
        "source": "generated",
        "aliasing": int(aliasing),
        "noise": float(noise),
        "loops": int(loops),
        "seed": int(seed),
        "mode": mode,
        "width": int(width),
        "mean_ones": int(mean_ones),
    }
    return GridData(sdrs=sdrs, places=places, width=width, meta=meta)


def _read_lines(path: Path) -> list[str]:
    with open(path, encoding="ascii", errors="strict", newline=None) as fh:
        text = fh.read()
    lines = text.split("\n")
    # A final newline ends the last line; it does not start an empty one.
    if lines and lines[-1] == "":
        lines.pop()
    return lines


def _parse_places(path: Path) -> np.ndarray:
    try:
        lines = _read_lines(path)
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not an ASCII text file ({exc})") from exc
    if not lines or not lines[0].lstrip().startswith("#"):
        raise ValueError(f"{path}: line 1: expected one comment header line starting with '#'")
    rows: list[tuple[int, int]] = []
    for lineno, line in enumerate(lines[1:], start=2):
        fields = line.split(",")
        if len(fields) != 2:
            raise ValueError(f"{path}: line {lineno}: expected 2 comma-separated integers 'x,y', "
                             f"got {len(fields)} fields")
        try:
            rows.append((int(fields[0]), int(fields[1])))
        except ValueError:
            msg = f"{path}: line {lineno}: expected integers 'x,y', got {line.strip()!r}"
            raise ValueError(msg) from None
    if not rows:
        raise ValueError(f"{path}: line 2: no place rows after the header")
    return np.asarray(rows, dtype=np.int64)


def _parse_sdrs(path: Path, width: int) -> list[np.ndarray]:
    try:
        lines = _read_lines(path)
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not an ASCII text file ({exc})") from exc
    if not lines:
        raise ValueError(f"{path}: line 1: no observation rows")
    allowed = {"0", "1"}
    sdrs: list[np.ndarray] = []
    for lineno, line in enumerate(lines, start=1):
        fields = [f.strip() for f in line.split(",")]
        if len(fields) != width:
            raise ValueError(f"{path}: line {lineno}: expected {width} comma-separated 0/1 values, "
                             f"got {len(fields)}")
        if not allowed.issuperset(fields):
            col = next(i for i, f in enumerate(fields) if f not in allowed)
            raise ValueError(f"{path}: line {lineno}: value {col + 1} is {fields[col]!r}, expected 0 or 1")
        sdrs.append(np.flatnonzero(np.asarray(fields) == "1").astype(INDEX_DTYPE))
    return sdrs


def load_published(sdr_file: str | Path, places_file: str | Path, *, width: int = WIDTH) -> GridData:
    """Load a published observation file and its place file (§2.3).

    Args:
        sdr_file: T lines of `width` comma-separated 0/1 values, no header (e.g.
            `seq_multi_loop_noise0_al1.txt`).
        places_file: one comment line, then T lines `x,y` (`seq_multi_loop_noNoise_gt.txt`).
        width: bits per observation (2048 in the published files).

    Returns:
        GridData with T SDRs and (T, 2) places; meta names the source files.

    Raises:
        ValueError: naming the file and the 1-based line of the first malformed or unmatched row.
    """
    sdr_path, places_path = Path(sdr_file), Path(places_file)
    places = _parse_places(places_path)
    sdrs = _parse_sdrs(sdr_path, width)
    if len(sdrs) > len(places):
        raise ValueError(f"{sdr_path}: line {len(places) + 1}: observation without a place; "
                         f"{places_path} has {len(places)} place rows, this file {len(sdrs)}")
    if len(places) > len(sdrs):
        # +2: one header line, and the first unmatched row is one past the observations.
        raise ValueError(f"{places_path}: line {len(sdrs) + 2}: place without an observation; "
                         f"{sdr_path} has {len(sdrs)} rows, this file {len(places)}")
    meta = {"source": "published", "sdr_file": sdr_path.name, "places_file": places_path.name}
    return GridData(sdrs=sdrs, places=places, width=width, meta=meta)
