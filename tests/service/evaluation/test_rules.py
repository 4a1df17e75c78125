"""`cortexloc eval rules` (service/evaluation/rules.py, issue 37 items 2-5): each rule switched off for
one run only, the jobs in their order, the threshold's choice, and a smoke run on tiny windows of the
real Nordland frames (skipped without ../shared/data)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from models.evaluation import datasets
from models.localisation import LocaliserOptions, PlaceMap, trail
from models.localisation import localiser as loc
from service.cli import app
from service.evaluation import rules, service_path, stress

NORDLAND = datasets.nordland_dir()
needs_data = pytest.mark.skipif(not (NORDLAND / "summer").is_dir(), reason=f"no Nordland data at {NORDLAND}")


@pytest.fixture(autouse=True)
def _tiny_default_preset():
    """The rules are costed at the service's defaults: the map preset too, not the tiny one of the other
    service tests (tests/service/conftest.py)."""


def test_a_rule_is_switched_off_for_the_run_only_and_every_rule_is_known() -> None:
    owners = {"echo": (trail.OwnTrail, "laid_behind"), "joins": (PlaceMap, "explained"),
              "null-rows": (loc.SequenceLocaliser, "_jump_level"), "flat-visits": (service_path, "observe")}
    for rule, (owner, name) in owners.items():
        before = getattr(owner, name)
        with rules.switched_off(rule):
            assert getattr(owner, name) is not before, rule
        assert getattr(owner, name) is before, rule
    with pytest.raises(RuntimeError), rules.switched_off("echo"):
        raise RuntimeError("a run that fails still restores the rule")
    assert trail.OwnTrail.laid_behind is owners["echo"][0].__dict__["laid_behind"]
    assert set(rules.OPTIONS) | set(rules.PATCHES) | {"all", "low-information"} == set(rules.RULES)
    for options in rules.OPTIONS.values():  # each is a valid localiser option
        loc.SequenceLocaliser(LocaliserOptions.of(options))


def test_with_flat_visits_off_a_flat_learned_frame_makes_a_row_of_its_own() -> None:
    """The `flat-visits` rule off: a flat learned frame is never consolidated (before: the patch took no
    keyword, and `observe` calls `consolidation` with `neighbours` and `flat`: the run failed)."""
    from models.pipeline import MapModel, Stream
    from models.presets import TmOptions

    tm = {"columnDimensions": 128, "cellsPerColumn": 4, "maxSegmentsPerCell": 4,
          "maxSynapsesPerSegment": 16, "activationThreshold": 3, "minThreshold": 2, "seed": 3}
    m = MapModel.new(TmOptions.of(tm), LocaliserOptions.of(None), max_observations=100, memory="none", s=0.1)
    codes: dict[int, np.ndarray] = {}
    frames = np.random.default_rng(0).normal(size=(10, 64)).astype(np.float32)
    with rules.switched_off("flat-visits"):
        for stream, st in (("a", Stream()), ("b", Stream())):  # a route, then again with a tunnel
            for i, y in enumerate(frames):
                seq = len(codes) + 1
                step = service_path.observe(m, st, y, learn=True, stream=stream, top_k=0, seq=seq,
                                            code_of=codes.__getitem__, threshold=1.0,
                                            contrast=0.0 if stream == "b" and i >= 7 else None)
                codes[seq] = step.code
                assert step.visit is None or (stream == "b" and i < 7)
    assert step.place is not None  # past the warm-up: consolidation was asked


def test_jobs_run_seed_by_seed_every_rule_on_first_and_the_ablation_with_rules_off_last() -> None:
    jobs = rules.jobs_of((42, 1), ("all", "span"), ("tm", "none"), windows=1)
    assert len(jobs) == 2 * 2 * 4
    first = jobs[:12]
    assert {(j.memory, j.rule) for j in first} == {("tm", "all"), ("tm", "span"), ("none", "all")}
    assert [j.seed for j in first] == [42] * 6 + [1] * 6
    assert {(j.memory, j.rule) for j in jobs[12:]} == {("none", "span")}
    assert {(j.half, j.lo) for j in jobs} == {("tune", 0), ("test", 894)}
    assert len(rules.jobs_of((42,), ("all",), ("tm",))) == 14  # every window of both halves


def _line(half: str, seed: int, conf: list[float], inside: list[int]) -> dict:
    n = len(conf)
    loc_ = {"r1": 1.0, "r5": 1.0, "auc": 0.5, "precision": 1.0, "recall": 1.0, "right_called": 1.0,
            "query_auc": 1.0, "r100p": 1.0,
            "answers": {"conf": conf, "named": [1] * n, "span": [1] * n, "inside": inside}}
    best = list(range(stress.WINDOW)) * 2
    return {"half": half, "lo": 0, "seed": seed, "memory": "tm", "rule": "all",
            "localise": {k: loc_ for k in rules.KINDS},
            "learn": {"recall": 1.0, "precision": 1.0, "r1": 1.0, "false_revisits": 0, "merged_places": 0,
                      "wrong_consolidations": 0,
                      "answers": {"best": [-1] * stress.WINDOW + best[:stress.WINDOW],
                                  "conf": [0.0] * (2 * stress.WINDOW)}}}


def test_the_threshold_is_the_lowest_that_keeps_every_kind_and_seed_precise_on_tune_only() -> None:
    # three wrong revisits at 0.9 (precision 0.985): the threshold must pass them; `test` (all wrong) is
    # never looked at
    conf = [0.95] * 197 + [0.9] * 3
    inside = [1] * 197 + [0] * 3
    lines = [_line("tune", s, conf, inside) for s in (42, 1)] + [_line("test", 42, conf, [0] * 200)]
    chosen, table = rules.choose_threshold(lines)
    assert chosen == 0.905
    pooled = rules.answers_of(lines, "tune", "tm", "winter")
    assert rules.at_threshold(pooled, 0.9)[0] == pytest.approx(394 / 400)
    assert any(row.startswith("| 0.905 |") for row in table)


@needs_data
def test_the_command_costs_rules_on_tiny_windows_and_its_tables_come_back_from_the_lines(tmp_path,
                                                                                         monkeypatch):
    """Two 30-file windows (one per half), one seed, every rule on and the echo rule off, with and
    without the memory: every line holds both modes; `--tables` makes the same tables from the lines."""
    monkeypatch.setattr(stress, "HALVES", {"tune": (0, 30), "test": (894, 924)})
    monkeypatch.setattr(stress, "WINDOW", 30)
    out = tmp_path / "rules.jsonl"
    r = CliRunner().invoke(app, ["eval", "rules", "--data", str(NORDLAND), "--out", str(out), "--seeds", "42",
                                 "--rules", "all,echo", "--memories", "tm,none"])
    assert r.exit_code == 0, r.output
    lines = [json.loads(s) for s in out.read_text().splitlines()]
    assert sorted((x["half"], x["memory"], x["rule"]) for x in lines) == sorted(
        (h, m, rule) for h in ("tune", "test") for m, rule in (("tm", "all"), ("tm", "echo"), ("none", "all"),
                                                                 ("none", "echo")))
    for x in lines:
        assert set(x["localise"]) == (set(rules.KINDS) if x["rule"] == "all" else {"winter"})
        for e in x["localise"].values():
            assert 0.0 <= e["r1"] <= 1.0 and 0.0 <= e["r5"] <= 1.0 and e["r1"] <= e["r5"] + 1e-9
        assert {"recall", "precision", "false_revisits", "merged_places"} <= set(x["learn"])
        if x["rule"] == "all":
            a = x["localise"]["winter"]["answers"]
            assert len(a["conf"]) == len(a["span"]) == len(a["inside"]) > 0
            assert np.all(np.asarray(a["span"]) >= 1)
    assert "| tm | echo |" in r.output and "### Threshold (item 2)" in r.output
    again = CliRunner().invoke(app, ["eval", "rules", "--tables", str(out)])
    assert again.exit_code == 0 and again.output == out.with_suffix(".md").read_text()
    bad = CliRunner().invoke(app, ["eval", "rules", "--data", str(NORDLAND), "--out", str(out),
                                   "--rules", "nope"])
    assert bad.exit_code == 2 and "unknown rules" in bad.output


def test_the_starts_table_has_a_row_per_window_and_kind_and_a_column_per_start() -> None:
    lines = [{"half": "test", "lo": 1494, "kind": "winter", "start": s, "share": v}
             for s, v in ((0, 0.98), (23, 0.977))]
    table = rules.starts_table(lines)
    assert "| start 0 | start 23 |" in table and "| test 1495-1694 | winter | 0.980 | 0.977 |" in table
    # exit 2 with what it takes, before any work (a window outside its half once evaluated other files
    # under its own name, or crashed; a start past the window gave nan)
    for bad, said in ((["--windows", "test"], "--windows"), (["--windows", "test:x"], "--windows"),
                      (["--windows", "north:994"], "halves"), (["--windows", "test:0"], "894 to 1588"),
                      (["--windows", "test:1700"], "894 to 1588"), (["--starts", "0,200"], "0 to 199"),
                      (["--starts", "-1"], "0 to 199"), (["--starts", "0,x"], "--starts"),
                      (["--kinds", "spring"], "winter, flat, noise")):
        r = CliRunner().invoke(app, ["eval", "starts", "--data", ".", *bad])
        assert r.exit_code == 2 and said in " ".join(r.output.split()), (bad, r.output)
    with pytest.raises(ValueError, match="0 to 199"):
        rules.start_shares(data=Path("."), starts=(250,))


@needs_data
def test_a_lap_started_part_way_into_its_window_still_finds_its_rows() -> None:
    """`cortexloc eval starts` (docs/results.md §11): a winter lap that starts 23 files into a held-out
    window, not at its map's first row, names the right row on most frames, as one started at the first
    row does (a stream's first frame ranked by its columns, docs/design/science.md §11.2 step 1)."""
    r = CliRunner().invoke(app, ["eval", "starts", "--data", str(NORDLAND), "--windows", "test:1494",
                                 "--kinds", "winter", "--starts", "0,23"])
    assert r.exit_code == 0, r.output
    row = next(line for line in r.output.splitlines() if line.startswith("| test 1495-1694 | winter"))
    shares = [float(v) for v in row.strip("| \n").split(" | ")[2:]]
    assert len(shares) == 2 and min(shares) >= 0.95, row
