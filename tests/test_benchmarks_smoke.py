"""The benchmarks' own checks, small, through their `cortexloc bench` / `cortexloc eval` commands where a
command runs them (benchmarks/__init__.py: the run logic of those commands).

benchmarks/bench_index.py compares `InvertedIndex.rank` with a packed-bit `np.bitwise_count` scan at
10^3..10^6 descriptors; here the same code runs on a few thousand, asserting that both return the same
top-10 (seq and overlap, ties to the older row) and that a noisy copy of a stored descriptor finds it.
Timings are never asserted (they live in the benchmark's JSON).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from benchmarks import bench_index, bench_localiser, bench_place
from benchmarks.bench_longrun import noisy
from models.localisation import LocaliserParams
from service.cli import app
from service.evaluation import stress

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


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
    from benchmarks import bench_startup

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


def test_every_benchmark_module_imports() -> None:
    """A module moved by a refactor breaks a benchmark only when its command runs; importing each module
    of benchmarks/ here (their work is under `main()`, nothing runs at import) catches it in `make test`."""
    import importlib

    modules = sorted(".".join(p.relative_to(BENCHMARKS.parent).with_suffix("").parts)
                     for p in BENCHMARKS.rglob("*.py") if p.name != "__init__.py")
    assert modules, "no benchmark modules found"
    failed = {}
    for name in modules:
        try:
            importlib.import_module(name)
        except Exception as exc:  # every failure is reported by name
            failed[name] = f"{type(exc).__name__}: {exc}"
    assert not failed, failed


def test_make_bench_runs_every_benchmark_as_a_command() -> None:
    """`cortexloc bench all` (`make bench`) runs each bench_*.py through its command: none is left out
    and each command exists (its `--help` answers)."""
    from benchmarks import run_all

    assert set(run_all.COMMANDS) == {p.stem for p in BENCHMARKS.glob("bench_*.py")}
    for argv in run_all.COMMANDS.values():
        result = CliRunner().invoke(app, [*argv, "--help"])
        assert result.exit_code == 0, (argv, result.output)


def test_the_index_benchmark_runs_as_a_command_and_writes_its_json(tmp_path: Path) -> None:
    """`cortexloc bench index` on a small map: the command hands its options to the benchmark, which
    prints its line and writes its JSON where `--out` says (figures unasserted)."""
    out = tmp_path / "index.json"
    result = CliRunner().invoke(app, ["bench", "index", "--sizes", "2000", "--sizes", "3000",
                                      "--queries", "4", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "2000 descriptors" in result.output and "3000 descriptors" in result.output
    written = json.loads(out.read_text())
    assert [r["descriptors"] for r in written["results"]] == [2000, 3000]


def test_the_fairness_benchmark_times_a_robot_alone_and_beside_a_flood(tmp_path: Path) -> None:
    """`cortexloc bench fairness` against a real server, tiny: both phases run, every robot frame gets a
    status, and the flood posted (figures unasserted: docs/benchmarks.md §16 has them)."""
    out = tmp_path / "fairness.json"
    result = CliRunner().invoke(app, ["bench", "fairness", "--frames", "2", "--gap", "0", "--clients", "2",
                                      "--side", "256", "--out", str(out)])
    assert result.exit_code == 0, result.output
    written = json.loads(out.read_text())
    assert written["alone"]["statuses"] == {"200": 2}
    assert sum(written["flooded"]["robot"]["statuses"].values()) == 2
    assert sum(written["flooded"]["flood_statuses"].values()) > 0


def test_the_tm_profile_still_ablates_the_kernel(tmp_path: Path) -> None:
    """bench_tm_profile.py removes parts of the step by editing a copy of the kernel's source; a kernel
    edit that moves one of those lines must fail here, not leave a variant that times the full step."""
    from benchmarks import bench_tm_profile

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
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    result = CliRunner().invoke(app, ["bench", "gpu", "--quick"])
    assert result.exit_code == 1 and "no CUDA device" in result.output


def test_the_loops_benchmark_counts_merges_over_the_rows_an_http_run_made() -> None:
    """bench_loops_http reads an HTTP run's rows by seq (any seqs, not 1..R) and their places from the
    store; `stress.merges` then counts places whose rows' labels differ by more than the tolerance and
    frames consolidated into a row of another label."""
    from benchmarks import bench_loops_http as b

    # rows 5, 6, 9 made by frames 0, 1, 3; row 9 joined row 6's place, which joined row 5's
    places = b.roots({5: None, 6: 5, 9: 6})
    assert places == {5: 5, 6: 5, 9: 5}
    labels = np.array([0, 1, 1, 40, 0])
    trace = b.merge_trace({5: 0, 6: 1, 9: 3}, {2: 6, 4: 9}, places, frames=5)
    # one place holds labels 0, 1 and 40: merged; frame 2 (label 1) into row 6 (label 1) is right,
    # frame 4 (label 0) into row 9 (label 40) is not
    assert b.stress.merges(labels, trace) == {"merged_places": 1, "wrong_consolidations": 1}
    assert b.roots({3: None, 4: 2}) == {3: 3, 4: 2}  # a join to a row not listed ends there


def test_the_loops_benchmark_scores_each_robots_second_lap_on_its_own_frames() -> None:
    """`by_robot`: each robot's lap-2 recall over its own frames, in both modes; the robots' recalls
    weighted by their true revisits give the route's. Two robots' laps of 30 places each: mapping calls
    every revisit of A's and every other one of B's, the localise mode every one."""
    from benchmarks import bench_loops_http as b

    labels = np.r_[np.arange(30), np.arange(100, 130), np.arange(30), np.arange(100, 130)]
    laps, robots = np.repeat([0, 0, 1, 1], 30), tuple("abab" [k // 30] for k in range(120))
    route = b.Route("robots", [b""] * 120, labels, laps, np.zeros((120, 2)), np.arange(120.0), robots)

    def run(called) -> dict:
        replies = [{"seq": i + 1, "place": None} for i in range(60)]
        for i in range(60, 120):
            row = i - 60 + 1  # the lap-1 row of the same label
            replies.append({"seq": None, "place": {"seq": row, "confidence": 0.95, "revisit": called(i),
                                                   "span": 1, "span_seqs": [row]}})
        return {"seed": 42, "asked": b.DEFAULT_SEED, "threshold": 0.91, "span_max": 3, "replies": replies}

    e = b.score_seed(route, run(lambda i: i < 90 or i % 2 == 0), run(lambda i: True), {})
    assert e["by_robot"]["a"] == {"recall": 1.0, "localise_recall": 1.0}
    assert e["by_robot"]["b"]["localise_recall"] == 1.0
    assert e["by_robot"]["b"]["recall"] == pytest.approx(0.5, abs=0.05)
    assert e["recall"] == pytest.approx((e["by_robot"]["a"]["recall"] + e["by_robot"]["b"]["recall"]) / 2)
    one = b.score_seed(b.Route("one", route.pngs, labels, laps, route.xy, route.stamps), run(lambda i: True),
                       run(lambda i: True), {})
    assert one["by_robot"] == {}  # one robot: the route's own figures say it


def test_the_loops_benchmark_drives_a_tiny_corridor_through_a_real_server(tmp_path: Path) -> None:
    """The whole command on a few dozen rendered frames (and a tiny Nordland loop where the data is
    here): a real `cortexloc serve` on loopback, a new map's seed, the table and the JSON's structure
    and counts that must agree. No figure is asserted but the seed."""
    from benchmarks import bench_loops_http as b
    from models.evaluation import datasets

    data = datasets.nordland_dir()
    routes = ["corridor"] + (["outdoor"] if (data / "summer").is_dir() else [])
    tiny = b.Sizes(lo=1000, lap=16, between=1494, gap=12, corridor=4.0, corridor_b=2.0)
    # with poses: the metadata path too (a pose the service refused would be a 400 here)
    result = b.run(data=data, routes=routes, seeds=[b.DEFAULT_SEED], sizes=tiny, concurrency=4, poses=True)
    assert result["config"]["poses"] is True
    json.loads(json.dumps(result))  # JSON all through
    assert set(result["routes"]) == set(routes)
    for name, r in result["routes"].items():
        assert r["revisits_true"] > 0  # lap 2 is a real return
        (e,) = r["seeds"]
        assert e["seed"] == 42 and e["asked"] == b.DEFAULT_SEED  # a map created with no seed option
        assert e["rows"] >= 1 and e["rows"] + e["consolidated"] <= e["frames"] == r["frames"]
        assert 0 <= e["merged_places"] <= e["rows"] and 0 <= e["wrong_consolidations"] <= e["consolidated"]
        assert 0 <= e["revisits_called"] <= e["frames"] and e["revisits_true"] == r["revisits_true"]
        for k in ("precision", "recall", "localise_recall", "recall_at_1", "recall_at_100p",
                  "localise_recall_at_1", "localise_recall_at_100p", "recall_at_100p_ungated",
                  "localise_recall_at_100p_ungated"):
            assert e[k] is None or 0.0 <= e[k] <= 1.0
        # a revisit called right is a right answer: recall at the default <= R@1; swept down to the
        # default's own precision-1 point, R@100P >= the recall there when that precision is 1
        assert e["recall"] is None or e["recall"] <= e["recall_at_1"]
        if e["precision"] == 1.0 and e["recall"] is not None:
            assert e["recall_at_100p"] >= e["recall"]
        for k in ("openseqslam_recall_at_100p", "openseqslam_recall_at_1"):
            assert r[k] is None or 0.0 <= r[k] <= 1.0
        w = r["worst"]
        assert w["met"] == all(w["checks"].values()) and w["recall_at_1"] == e["recall_at_1"]
        assert f"| {name} | {r['frames']} |" in b.table(result)


def test_the_loops_benchmark_poses_follow_the_route() -> None:
    """`--poses`: the corridor's frames carry their true positions (lap 2 where lap 1 was, the second
    corridor elsewhere), stamps increase, and a slower robot's copies lie between a frame and the next."""

    from benchmarks import bench_loops_http as b

    tiny = b.Sizes(corridor=3.0, corridor_b=1.0)
    r = b.indoor(tiny)
    assert len(r.pngs) == len(r.labels) == len(r.laps) == len(r.xy) == len(r.stamps)
    assert np.all(np.diff(r.stamps) > 0)
    lap1, lap2 = (r.laps == 0) & (r.labels < 10_000), r.laps == 1
    assert np.allclose(np.diff(r.xy[lap1, 0]), 0.12) and np.allclose(r.xy[lap1, 1], 0.0)
    assert np.all(np.abs(np.floor(r.xy[lap2, 0]) - r.labels[lap2]) == 0)  # labels are metres along A
    assert np.all(r.xy[r.labels >= 10_000, 1] >= 0) and np.all(r.xy[r.labels >= 10_000, 0] > 3.0)
    meta = json.loads(r.metadata(5))
    assert meta == {"stamp": round(float(r.stamps[5]), 3), "pose": {"x": 0.6, "y": 0.0}}
    slow = b.slower(b.Route("outdoor", r.pngs[:3], np.array([7, 8, 9]), np.zeros(3, np.int64),
                            np.array([[0.0, 0.0], [30.0, 0.0], [60.0, 0.0]]), np.array([0.0, 10.0, 20.0])))
    assert np.allclose(slow.xy[:, 0], [0, 10, 20, 30, 40, 50, 60, 60, 60])
    assert np.allclose(np.diff(slow.stamps), 10.0 / 3) and list(slow.labels) == [7, 7, 7, 8, 8, 8, 9, 9, 9]


def test_the_loops_benchmarks_two_robots_post_each_as_its_own_stream() -> None:
    """`robots`: A's summer lap, then B's on ground A never drove, then both in winter, each robot its own
    stream while mapping and while localising (docs/results.md §10.25); one robot's routes keep theirs."""
    from benchmarks import bench_loops_http as b
    from models.evaluation import datasets

    one = b.indoor(b.Sizes(corridor=2.0, corridor_b=1.0))
    assert {one.stream(i, True) for i in range(len(one.pngs))} == {"robot"}
    assert one.stream(0, False) == "query"
    data = datasets.nordland_dir()
    if not (data / "winter").is_dir():
        pytest.skip(f"no Nordland data at {data}")
    tiny = b.Sizes(lo=1000, lap=6, gap=4)
    r = b.build("robots", data, tiny)
    assert list(r.labels) == [*range(1000, 1006), *range(1010, 1016)] * 2
    assert list(r.laps) == [0] * 12 + [1] * 12 and np.all(np.diff(r.stamps) > 0)
    localising = [r.stream(i, r.laps[i] == 0) for i in (0, 6, 12, 18)]
    assert localising == ["robot-a", "robot-b", "query-a", "query-b"]
    assert [r.stream(i, True) for i in (12, 18)] == ["robot-a", "robot-b"]  # mapping: a stream per robot
    assert b.drifted(r, 0.0, 0.0).robots == r.robots


def test_the_loops_benchmarks_speed_and_fault_routes_change_only_what_they_name() -> None:
    """`dropped` loses every other mapping frame, `station` stops at one file on both laps, `faster` and
    `slower` drive lap 2 at twice and half the mapped speed (docs/results.md §10.27): each keeps its
    frames' labels, laps and poses together, stamps one per post, and leaves the other lap as it was."""
    from benchmarks import bench_loops_http as b

    img = np.random.default_rng(0).integers(0, 255, (8, 8, 3), np.uint8)
    pngs = [stress.variant(img, "noise:4", i) for i in range(12)]
    labels = np.array([*range(100, 106)] * 2)
    laps = np.array([0] * 6 + [1] * 6)
    r = b.Route("outdoor", pngs, labels, laps, np.stack([labels * 280.0, np.zeros(12)], axis=1),
                10.0 * np.arange(12))

    def whole(x: b.Route) -> None:
        assert len(x.pngs) == len(x.labels) == len(x.laps) == len(x.xy) == len(x.stamps)
        assert np.all(np.diff(x.stamps) > 0) and np.allclose(x.xy[:, 0], x.labels * 280.0)

    dropped = b.dropped(r)
    whole(dropped)
    assert list(dropped.labels) == [100, 102, 104, *range(100, 106)] and dropped.pngs[3:] == pngs[6:]
    faster, slower = b.lap2_pace(r, 2.0), b.lap2_pace(r, 0.5)
    for x in (faster, slower):
        whole(x)
        assert x.pngs[:6] == pngs[:6] and list(x.labels[:6]) == list(labels[:6])
    assert faster.name == "faster" and list(faster.labels[6:]) == [100, 102, 104]
    assert faster.pngs[6:] == [pngs[6], pngs[8], pngs[10]]
    assert slower.name == "slower" and list(slower.labels[6:]) == [v for v in range(100, 106) for _ in (0, 1)]
    assert slower.pngs[6::2] == pngs[6:] and all(c not in pngs for c in slower.pngs[7::2])  # noisy copies
    stop = b.station(r, 102, dwell=5, ramp=(2,))
    whole(stop)
    lap1 = list(stop.labels[stop.laps == 0])
    assert lap1 == [100, 101, 101, *[102] * 5, 103, 103, 104, 105] == list(stop.labels[stop.laps == 1])
    assert stop.pngs[0] == pngs[0] and stop.pngs[3] == pngs[2] and len(set(stop.pngs[3:8])) == 5


def test_the_loops_benchmark_drifted_odometry_drifts_as_odometry_does() -> None:
    """`--drift S,H`: the posted poses keep the route's path length to within the scale noise and wander
    from the truth more the farther the robot drove; none at S = H = 0."""
    from benchmarks import bench_loops_http as b

    r = b.indoor(b.Sizes(corridor=6.0, corridor_b=2.0))
    assert np.allclose(b.drifted(r, 0.0, 0.0).xy, r.xy)
    d = b.drifted(r, 0.03, 0.5)
    true_steps, odo_steps = (np.hypot(*np.diff(x, axis=0).T) for x in (r.xy, d.xy))
    moved = true_steps > 0
    assert np.all(np.abs(odo_steps[moved] / true_steps[moved] - 1) < 0.2)  # 3 % scale noise, per step
    error = np.hypot(*(d.xy - r.xy).T)
    assert error[0] == 0 and error[-1] > error[len(error) // 4] > 0  # the error grows along the drive
    assert (d.pngs, list(d.labels), list(d.stamps)) == (r.pngs, list(r.labels), list(r.stamps))


def test_the_growth_benchmark_runs_every_route_asked_for(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """`cortexloc bench growth --quick --routes exact,noise8,winter` in process: a summary per route, in
    the order asked, and the JSON holds each (a second route once failed: a name the first one's
    summary rebound). No figure is asserted but the bounds a pass's counts keep."""
    from benchmarks import bench_growth as b
    from models.evaluation import datasets

    if not (datasets.nordland_dir() / "winter").is_dir():
        pytest.skip(f"no Nordland data at {datasets.nordland_dir()}")
    written: dict = {}
    monkeypatch.setattr(b, "write_json", lambda name, payload: written.update(payload))
    b.main(passes=3, lo=894, frames=100, seed=42, quick=True, http=False, routes=b.ROUTES)
    printed = [line for line in capsys.readouterr().out.splitlines() if line.startswith("{'route'")]
    assert [line.split("'")[3] for line in printed] == list(b.ROUTES)
    assert list(written["results"]) == list(b.ROUTES)
    for r in written["results"].values():
        passes = r["passes"]
        assert len(passes) == 3 and passes[0]["rows"] == passes[0]["held"] == 100  # a new map's first pass
        for p in passes:
            assert p["held"] <= p["rows"] <= 100  # rows made this pass; held: less those joined away


def test_the_growth_benchmark_builds_its_map_with_the_localiser_options_asked_for(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`--localiser` (an ablation): `consolidate` 1 never consolidates, so a second exact pass of the
    route is a row a frame where at the defaults it is visits; a value that is no JSON object is a
    usage error before anything runs."""
    from benchmarks import bench_growth as b
    from models.evaluation import datasets

    bad = CliRunner().invoke(app, ["bench", "growth", "--quick", "--localiser", "[1]"])
    assert bad.exit_code == 2 and "JSON object" in bad.output
    if not (datasets.nordland_dir() / "summer").is_dir():
        pytest.skip(f"no Nordland data at {datasets.nordland_dir()}")
    written: list[dict] = []
    monkeypatch.setattr(b, "write_json", lambda name, payload: written.append(payload))
    for options in (None, {"consolidate": 1.0}):
        b.main(passes=2, lo=894, frames=30, seed=42, quick=False, http=False, routes=("exact",),
               localiser=options)
    default, never = (w["results"]["exact"]["passes"][1] for w in written)
    assert written[1]["localiser"] == {"consolidate": 1.0}
    assert never["visits"] == 0 and never["rows"] == 30 and default["visits"] > 0


def test_the_parked_experiment_stands_within_stand_metres_and_totals_its_lines(
        capsys: pytest.CaptureFixture[str]) -> None:
    """`cortexloc eval parked`: a file 10 m on and a frame a second; the stop's poses within the default
    `stand_metres` of each other (so the rule applies) and under `move_metres` of its file's; `sum` adds
    every line's revisits per ground, mode and phase and names the windows with a wrong one."""
    from benchmarks.experiments import parked
    from models.localisation import LocaliserOptions

    files, phase = [5, 6, 7, 7, 7, 7, 8], [0, 0, 0, 1, 1, 1, 2]
    motions = parked.poses(files, phase, 100.0)
    xs = [m.pose[0] for m in motions]
    assert xs[1] - xs[0] == xs[2] - xs[1] == 10.0 and [m.stamp for m in motions] == list(map(float, range(7)))
    stop = xs[3:6]
    assert max(stop) - min(stop) < LocaliserOptions().stand_metres and abs(stop[0] - xs[2]) < 1.0

    def line(seed: int, wrong: int) -> dict:
        counts = {p: {"called": 2, "wrong": 0} for p in parked.PHASES}
        counts["parked"] = {"called": 3, "wrong": wrong}
        return {"half": "tune", "lo": 0, "seed": seed,
                **{g: {m: counts for m in parked.MODES} for g in parked.GROUNDS}}

    parked.total([line(1, 0), line(7, 3)])
    out = capsys.readouterr().out.splitlines()
    new_poses = next(x for x in out if x.startswith("new poses "))
    assert '"parked": {"called": 6, "wrong": 3}' in new_poses
    assert "windows with a wrong revisit: 1" in new_poses
    assert out[-1].endswith("lines: 2")
