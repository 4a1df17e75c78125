"""The retrieval benchmark's own check, small: the index and the brute-force popcount agree.

benchmarks/bench_index.py compares `InvertedIndex.rank` with a packed-bit `np.bitwise_count` scan at
10^3..10^6 descriptors; here the same code runs on a few thousand, asserting that both return the same
top-10 (seq and overlap, ties to the older row) and that a noisy copy of a stored descriptor finds it.
Timings are never asserted (they live in the benchmark's JSON).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_index
import bench_localiser
import bench_place
from bench_longrun import noisy

from models.localisation.localiser import LocaliserParams


def test_descriptor_generators_keep_constant_weight() -> None:
    rng = np.random.default_rng(0)
    sets = bench_index.random_sets(rng, 500)
    assert sets.shape == (500, bench_index.WEIGHT)
    assert bool(np.all(np.diff(sets, axis=1) > 0)) and sets.min() >= 0 and sets.max() < bench_index.N_CELLS
    q = bench_index.noisy_query(rng, sets[0], 30)
    assert q.size == 40 and np.unique(q).size == 40 and np.intersect1d(q, sets[0]).size == 30
    x = noisy(sets[1].astype(np.int64), 4, bench_index.N_CELLS, rng)
    assert x.size == 40 and np.unique(x).size == 40 and np.intersect1d(x, sets[1]).size == 36


def test_packed_popcount_counts_overlaps() -> None:
    rng = np.random.default_rng(1)
    sets = bench_index.random_sets(rng, 50)
    packed = bench_index.pack(sets)
    q = sets[7].astype(np.int64)
    top = bench_index.brute_top(packed, q, k=50)
    expected = {i: np.intersect1d(sets[i], q).size for i in range(50)}
    assert top[0] == (7, 40)
    assert all(expected[r] == o for r, o in top)
    assert [o for _, o in top] == sorted((o for _, o in top), reverse=True)


def test_index_and_brute_force_return_the_same_top10() -> None:
    r = bench_index.bench_size(3_000, queries=15, keep=30, seed=3)
    assert r["same_top10"] == 15
    assert r["target_in_top10"] == 15
    assert r["index"]["postings"] == 3_000 * bench_index.WEIGHT


def test_startup_benchmark_builds_a_map_and_reopens_it_from_its_snapshot(tmp_path, monkeypatch,
                                                                           tiny_default_preset) -> None:
    """bench_startup drives the service's own MapRuntime: a tiny map keeps it cheap, and a change of
    that interface breaks here rather than in a two-hour `make bench`."""
    import bench_startup

    monkeypatch.setenv("CORTEXLOC_WEIGHTS_DIR", str(tmp_path / "no-weights"))
    built = bench_startup.build(tmp_path / "data", 60, short_tail=5, long_tail=30)
    assert built["snapshots_at"] == [30, 55]
    opened = bench_startup.open_once(tmp_path / "data")
    assert opened["state"] == "ready" and opened["observations"] == 60
    assert opened["replayed"] == 5  # only the rows after the newest snapshot


def test_localiser_benchmark_follows_its_route_with_a_state_that_ignores_the_map_size() -> None:
    small, large = bench_localiser.bench_size(500, 40), bench_localiser.bench_size(50_000, 40)
    assert small["recall_at_1"] > 0.9 and large["recall_at_1"] > 0.9
    assert small["state_bytes"] == large["state_bytes"]


def test_place_benchmark_localises_through_the_index_with_a_fixed_state() -> None:
    small, large = bench_place.bench_size(500, 30), bench_place.bench_size(20_000, 30)
    assert small["recall_at_1"] > 0.9 and large["recall_at_1"] > 0.9
    assert small["state_bytes"] == large["state_bytes"]
    # one index pass serves the localiser's top_k plus the `exclusion` rows a stream's own trail may take
    # and the rows of its short-term memory (none: the benchmark's stream never learned); the graph holds
    # predecessor, successor and trail links, one int64 each per row (and row 0)
    conf = LocaliserParams()
    assert large["candidates"] == conf.top_k + conf.exclusion
    assert large["graph_bytes"] == 3 * 8 * (20_000 + 1)


def test_every_benchmark_script_imports() -> None:
    """A module moved by a refactor breaks a benchmark only at `make bench` time; importing each script
    here (their work is under `main()`, nothing runs at import) catches it in `make test`."""
    import importlib

    scripts = sorted(p.stem for p in (Path(__file__).resolve().parents[1] / "benchmarks").glob("bench_*.py"))
    assert scripts, "no benchmark scripts found"
    failed = {}
    for name in scripts:
        try:
            importlib.import_module(name)
        except Exception as exc:  # every failure is reported by name
            failed[name] = f"{type(exc).__name__}: {exc}"
    assert not failed, failed


def test_the_tm_profile_still_ablates_the_kernel(tmp_path: Path) -> None:
    """bench_tm_profile.py removes parts of the step by editing a copy of the kernel's source; a kernel
    edit that moves one of those lines must fail here, not leave a variant that times the full step."""
    import bench_tm_profile

    for name, edits in bench_tm_profile.VARIANTS.items():
        bench_tm_profile.patched_copy(tmp_path / name, edits)
        src = (tmp_path / name / bench_tm_profile.SYN).read_text()
        for _, new in edits:
            assert new in src
    broken = [(bench_tm_profile.SELECT[0] + "# gone", "")]
    with pytest.raises(RuntimeError, match="cannot ablate"):
        bench_tm_profile.patched_copy(tmp_path / "broken", broken)


def test_bench_gpu_says_it_needs_a_gpu_where_there_is_none(monkeypatch: pytest.MonkeyPatch) -> None:
    """bench_gpu (docs/benchmarks.md §15) runs on a GPU machine only; on the CPU machines of CI and
    development it stops with a message, not a traceback, and writes nothing."""
    import sys

    import bench_gpu
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(sys, "argv", ["bench_gpu.py"])
    with pytest.raises(SystemExit, match="no CUDA device"):
        bench_gpu.main()
