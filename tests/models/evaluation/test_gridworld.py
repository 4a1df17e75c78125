"""Grid-world trajectory, generator and published-data loader (docs/design/science.md §2)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from models.evaluation.datasets import GRID_PLACES_FILE, GRID_SDR_FILES, grid_dir
from models.evaluation.gridworld import GridData, generate, load_published, trajectory
from models.sdr import INDEX_DTYPE, from_dense, overlap

GRID_DIR = grid_dir()
PLACES_FILE = GRID_DIR / GRID_PLACES_FILE
AL1_FILE = GRID_DIR / GRID_SDR_FILES["a1n0"]
AL5_FILE = GRID_DIR / GRID_SDR_FILES["a5n05"]
needs_published = pytest.mark.skipif(
    not (PLACES_FILE.is_file() and AL1_FILE.is_file() and AL5_FILE.is_file()),
    reason=f"published grid-world data not found in {GRID_DIR} (set CORTEXLOC_SHARED_DATA)",
)


def _visits(data: GridData) -> dict[tuple[int, int], list[int]]:
    out: dict[tuple[int, int], list[int]] = {}
    for t, (x, y) in enumerate(data.places.tolist()):
        out.setdefault((x, y), []).append(t)
    return out


def _same_place_overlaps(data: GridData) -> np.ndarray:
    return np.array([overlap(data.sdrs[i], data.sdrs[j])
                     for steps in _visits(data).values()
                     for a, i in enumerate(steps) for j in steps[a + 1:]])


# --- trajectory (§2.1) --------------------------------------------------------------------------------


def test_trajectory_has_212_steps_over_26_places() -> None:
    path = trajectory()
    assert path.shape == (212, 2)
    assert np.issubdtype(path.dtype, np.integer)
    assert len({tuple(p) for p in path.tolist()}) == 26
    assert path[:3].tolist() == [[8, 3], [8, 4], [8, 5]]
    assert path[-5:].tolist() == [[8, 12], [8, 13], [8, 14], [8, 15], [8, 16]]
    # Steps 3..200 are the loop 11 times, steps 201..206 its left side once more.
    assert path[3].tolist() == [8, 6] and path[200].tolist() == [9, 6]
    assert path[201:207].tolist() == [[8, y] for y in range(6, 12)]


def test_trajectory_visit_counts() -> None:
    counts = Counter(tuple(p) for p in trajectory().tolist())
    left = {(8, y) for y in range(6, 12)}
    entry_exit = {(8, 3), (8, 4), (8, 5), (8, 12), (8, 13), (8, 14), (8, 15), (8, 16)}
    for place, n in counts.items():
        expected = 12 if place in left else 1 if place in entry_exit else 11
        assert n == expected, place
    loop = [p for p in counts if p not in entry_exit]
    assert len(loop) == 18
    assert all(8 <= x <= 12 and 6 <= y <= 11 and (x in (8, 12) or y in (6, 11)) for x, y in loop)


def test_trajectory_moves_one_cell_per_step() -> None:
    steps = np.abs(np.diff(trajectory(), axis=0)).sum(axis=1)
    assert (steps == 1).all()


@pytest.mark.parametrize("loops", [0, 1, 3, 11])
def test_trajectory_length_follows_loops(loops: int) -> None:
    assert len(trajectory(loops)) == 3 + 18 * loops + 6 + 5


def test_trajectory_rejects_negative_loops() -> None:
    with pytest.raises(ValueError):
        trajectory(-1)


# --- generator (§2.2) ---------------------------------------------------------------------------------


def _reference_generate(aliasing: int, noise: float, seed: int, mode: str) -> list[np.ndarray]:
    """The draw order of §2.2 written out literally, to pin it against refactoring."""
    rng = np.random.Generator(np.random.PCG64(seed))
    places = [tuple(p) for p in trajectory().tolist()]
    base: dict[tuple[int, int], np.ndarray] = {}
    for p in places:
        if p not in base:
            if mode == "bernoulli":
                base[p] = from_dense(rng.random(2048) < 40 / 2048)
            else:
                base[p] = np.sort(rng.choice(2048, size=40, replace=False))
    for i in range(aliasing):
        base[(12, 6 + i)] = base[(8, 6 + i)]
    out = []
    for p in places:
        ones = base[p]
        m = int(np.floor(noise * len(ones) + 0.5))
        if m:
            cleared = rng.choice(len(ones), size=m, replace=False)
            added = rng.integers(0, 2048, size=m)
            ones = np.union1d(np.delete(ones, cleared), added)
        out.append(ones)
    return out


@pytest.mark.parametrize(("aliasing", "noise", "mode"), [(0, 0.0, "bernoulli"), (5, 0.5, "bernoulli"),
                                                         (3, 0.25, "exact"), (6, 1.0, "bernoulli")])
def test_generate_follows_the_documented_draw_order(aliasing: int, noise: float, mode: str) -> None:
    data = generate(aliasing, noise, seed=7, mode=mode)
    ref = _reference_generate(aliasing, noise, 7, mode)
    assert len(data.sdrs) == len(ref) == 212
    for got, want in zip(data.sdrs, ref, strict=True):
        np.testing.assert_array_equal(got, want)


def test_generate_shapes_types_and_meta() -> None:
    data = generate(1, 0.0, seed=3)
    assert len(data) == 212 and data.width == 2048
    np.testing.assert_array_equal(data.places, trajectory())
    for s in data.sdrs:
        assert s.dtype == INDEX_DTYPE and s.ndim == 1
        assert (np.diff(s) > 0).all() and s.min() >= 0 and s.max() < 2048
    assert data.meta == {"source": "generated", "aliasing": 1, "noise": 0.0, "loops": 11, "seed": 3,
                         "mode": "bernoulli", "width": 2048, "mean_ones": 40}
    assert len(generate(0, 0.0, loops=2).sdrs) == 3 + 36 + 11


@pytest.mark.parametrize("aliasing", range(7))
def test_aliasing_copies_exactly_the_documented_places(aliasing: int) -> None:
    data = generate(aliasing, 0.0, seed=11)
    visits = _visits(data)
    for i in range(6):
        left, right = data.sdrs[visits[(8, 6 + i)][0]], data.sdrs[visits[(12, 6 + i)][0]]
        if i < aliasing:
            np.testing.assert_array_equal(left, right)
        else:
            assert overlap(left, right) < len(left) // 2
    # Every other pair of distinct places stays (almost) unrelated.
    twins = {frozenset({(8, 6 + i), (12, 6 + i)}) for i in range(aliasing)}
    first = {p: data.sdrs[steps[0]] for p, steps in visits.items()}
    for a in first:
        for b in first:
            if a < b and frozenset({a, b}) not in twins:
                assert overlap(first[a], first[b]) < 10, (a, b)


def test_aliasing_does_not_change_the_other_places() -> None:
    plain, aliased = generate(0, 0.0, seed=5), generate(5, 0.0, seed=5)
    twins = {(12, 6 + i) for i in range(5)}
    for p, s0, s5 in zip(plain.places.tolist(), plain.sdrs, aliased.sdrs, strict=True):
        if tuple(p) not in twins:
            np.testing.assert_array_equal(s0, s5)


def test_without_noise_every_visit_is_identical() -> None:
    data = generate(0, 0.0, seed=2)
    for steps in _visits(data).values():
        for t in steps[1:]:
            np.testing.assert_array_equal(data.sdrs[t], data.sdrs[steps[0]])


@pytest.mark.parametrize("noise", [0.1, 0.25, 0.5, 0.75])
def test_noise_keeps_about_one_minus_n_squared_of_the_bits(noise: float) -> None:
    shared, weights = [], []
    for seed in range(3):
        data = generate(0, noise, seed=seed)
        shared.append(_same_place_overlaps(data).mean())
        weights.append(np.mean([len(s) for s in data.sdrs]))
    # Chance collisions of the new bits add well under one bit at 40/2048 density.
    assert np.mean(shared) == pytest.approx((1 - noise) ** 2 * np.mean(weights), abs=1.5)


def test_noise_replaces_m_ones_and_never_adds_weight() -> None:
    noise = 0.5
    clean, noisy = generate(2, 0.0, seed=9), generate(2, noise, seed=9)
    for base, obs in zip(clean.sdrs, noisy.sdrs, strict=True):
        k = len(base)
        m = int(np.floor(noise * k + 0.5))
        assert k - m <= len(obs) <= k
        assert overlap(base, obs) >= k - m


def test_full_noise_leaves_only_chance_overlap() -> None:
    overlaps = _same_place_overlaps(generate(0, 1.0, seed=1))
    assert overlaps.mean() < 2.0


def test_generate_is_deterministic_per_seed_and_differs_across_seeds() -> None:
    a, b, c = generate(5, 0.5, seed=42), generate(5, 0.5, seed=42), generate(5, 0.5, seed=43)
    assert all(np.array_equal(x, y) for x, y in zip(a.sdrs, b.sdrs, strict=True))
    assert sum(np.array_equal(x, y) for x, y in zip(a.sdrs, c.sdrs, strict=True)) == 0


def test_exact_mode_has_weight_40() -> None:
    data = generate(3, 0.0, seed=4, mode="exact")
    assert {len(s) for s in data.sdrs} == {40}
    assert data.meta["mode"] == "exact"
    assert {len(s) for s in generate(0, 0.0, mode="exact", mean_ones=25).sdrs} == {25}


def test_bernoulli_weights_spread_around_40() -> None:
    weights = np.array([len(s) for seed in range(5) for s in generate(0, 0.0, seed=seed).sdrs])
    assert 38.0 < weights.mean() < 43.0
    assert weights.min() < 36 and weights.max() > 44  # not the fixed weight of `exact`
    assert weights.min() > 15 and weights.max() < 70


@pytest.mark.parametrize(("kwargs", "error"), [
    ({"aliasing": 7, "noise": 0.0}, ValueError),
    ({"aliasing": -1, "noise": 0.0}, ValueError),
    ({"aliasing": 1.5, "noise": 0.0}, TypeError),
    ({"aliasing": 0, "noise": -0.1}, ValueError),
    ({"aliasing": 0, "noise": 1.01}, ValueError),
    ({"aliasing": 0, "noise": float("nan")}, ValueError),
    ({"aliasing": 0, "noise": 0.0, "mode": "gaussian"}, ValueError),
    ({"aliasing": 0, "noise": 0.0, "mean_ones": 3000}, ValueError),
])
def test_generate_validates_arguments(kwargs: dict, error: type[Exception]) -> None:
    with pytest.raises(error):
        generate(**kwargs)


# --- published files (§2.3) ---------------------------------------------------------------------------


@needs_published
def test_load_published_a1_n0() -> None:
    data = load_published(AL1_FILE, PLACES_FILE)
    assert len(data) == 212 and data.width == 2048
    np.testing.assert_array_equal(data.places, trajectory())
    assert data.meta == {"source": "published", "sdr_file": AL1_FILE.name, "places_file": PLACES_FILE.name}
    weights = np.array([len(s) for s in data.sdrs])
    assert weights.min() == 28 and weights.max() == 53  # §2.2
    visits = _visits(data)
    for steps in visits.values():
        assert all(np.array_equal(data.sdrs[t], data.sdrs[steps[0]]) for t in steps)
    # a = 1: only the bottom corners are twins.
    np.testing.assert_array_equal(data.sdrs[visits[(12, 6)][0]], data.sdrs[visits[(8, 6)][0]])
    assert not np.array_equal(data.sdrs[visits[(12, 7)][0]], data.sdrs[visits[(8, 7)][0]])


@needs_published
def test_load_published_a5_n05_revisit_overlap() -> None:
    data = load_published(AL5_FILE, PLACES_FILE)
    overlaps = _same_place_overlaps(data)
    assert overlaps.mean() == pytest.approx(10.3, abs=0.05)
    assert overlaps.min() == 2 and overlaps.max() == 20
    visits = _visits(data)
    # Noisy twins share about as many bits as two visits of one place; y = 11 is not aliased.
    twin = [overlap(data.sdrs[visits[(8, 6 + i)][0]], data.sdrs[visits[(12, 6 + i)][0]]) for i in range(6)]
    assert min(twin[:5]) >= 4 and twin[5] <= 2


@needs_published
def test_generator_statistics_resemble_the_published_files() -> None:
    published = [len(s) for s in load_published(AL1_FILE, PLACES_FILE).sdrs]
    generated = [len(s) for s in generate(1, 0.0, seed=0).sdrs]
    assert abs(np.mean(published) - np.mean(generated)) < 4
    assert abs(np.std(published) - np.std(generated)) < 3
    pub_overlap = _same_place_overlaps(load_published(AL5_FILE, PLACES_FILE)).mean()
    gen_overlap = _same_place_overlaps(generate(5, 0.5, seed=0)).mean()
    assert abs(pub_overlap - gen_overlap) < 2


# --- loader errors: tiny files in tmp_path --------------------------------------------------------------


def _write(path: Path, text: str) -> Path:
    path.write_bytes(text.encode("ascii"))
    return path


def _row(ones: list[int], width: int = 8) -> str:
    return ",".join("1" if i in ones else "0" for i in range(width))


@pytest.fixture
def small_files(tmp_path: Path) -> tuple[Path, Path]:
    places = _write(tmp_path / "gt.txt", "# each row: x y\n8,3\n8,4\n8,5\n")
    sdrs = _write(tmp_path / "obs.txt", "\n".join([_row([0, 3]), _row([1]), _row([2, 7])]) + "\n")
    return sdrs, places


def test_loader_reads_small_files(small_files: tuple[Path, Path]) -> None:
    sdrs, places = small_files
    data = load_published(sdrs, places, width=8)
    assert [s.tolist() for s in data.sdrs] == [[0, 3], [1], [2, 7]]
    assert all(s.dtype == INDEX_DTYPE for s in data.sdrs)
    assert data.places.tolist() == [[8, 3], [8, 4], [8, 5]]


def test_loader_accepts_crlf_and_a_missing_final_newline(tmp_path: Path) -> None:
    places = _write(tmp_path / "gt.txt", "# each row: x y\r\n1,2\r\n3,4")
    sdrs = _write(tmp_path / "obs.txt", _row([5]) + "\r\n" + _row([]))
    data = load_published(sdrs, places, width=8)
    assert [s.tolist() for s in data.sdrs] == [[5], []]


@pytest.mark.parametrize(("text", "line", "what"), [
    (_row([0]) + "\n" + _row([1]) + ",0\n" + _row([2]) + "\n", 2, "expected 8"),
    (_row([0]) + "\n" + _row([1]) + "\n" + _row([2]).replace("0", "2", 1) + "\n", 3, "value 1"),
    (_row([0]) + "\n\n" + _row([2]) + "\n", 2, "got 1"),
    ("", 1, "no observation"),
])
def test_loader_names_file_and_line_for_bad_observations(
    small_files: tuple[Path, Path], text: str, line: int, what: str
) -> None:
    sdrs, places = small_files
    _write(sdrs, text)
    with pytest.raises(ValueError, match=rf"obs\.txt: line {line}: .*{what}"):
        load_published(sdrs, places, width=8)


@pytest.mark.parametrize(("text", "line"), [
    ("8,3\n8,4\n8,5\n", 1),  # no header
    ("# x y\n8,3\n8;4\n8,5\n", 3),
    ("# x y\n8,3\n8,4\n8,five\n", 4),
    ("# x y\n8,3,1\n8,4\n8,5\n", 2),
    ("# x y\n", 2),
])
def test_loader_names_file_and_line_for_bad_places(
    small_files: tuple[Path, Path], text: str, line: int
) -> None:
    sdrs, places = small_files
    _write(places, text)
    with pytest.raises(ValueError, match=rf"gt\.txt: line {line}:"):
        load_published(sdrs, places, width=8)


def test_loader_rejects_unequal_lengths(small_files: tuple[Path, Path]) -> None:
    sdrs, places = small_files
    _write(places, "# x y\n8,3\n8,4\n8,5\n8,6\n")
    with pytest.raises(ValueError, match=r"gt\.txt: line 5: place without an observation"):
        load_published(sdrs, places, width=8)
    _write(places, "# x y\n8,3\n8,4\n")
    with pytest.raises(ValueError, match=r"obs\.txt: line 3: observation without a place"):
        load_published(sdrs, places, width=8)


def test_loader_default_width_is_2048(small_files: tuple[Path, Path]) -> None:
    sdrs, places = small_files
    with pytest.raises(ValueError, match=r"obs\.txt: line 1: expected 2048"):
        load_published(sdrs, places)
