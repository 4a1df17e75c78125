"""Every learning and answering rule costed on every window, in both modes, over map seeds (issue 37
items 2-5; docs/results.md §10.14).

    cortexloc eval rules --data ../shared/data/nordland_tiny_64x32 --jobs 16 --out rules.jsonl
    cortexloc eval rules --tables rules.jsonl          # the tables again from the lines

Windows: every 200-file window of both Nordland halves slid by 100 (`stress.windows`: 7 of `tune`, 7
of `test`), labels = file index, tolerance 1. Per window, map seed, memory (`tm`, the default map, and
`none`, the same pipeline without the Temporal Memory: the memory's ablation) and rule switched off:
- **localise mode**: the window's summer frames learned as one traverse, then driven again in winter by
  another stream that localises (`service_path.replay`): R@1, R@5 and the paper's all-pairs AUC from the
  stream's beam scores (`sequences.evaluate`), and at the map's revisit threshold the revisits'
  precision, recall, per-query AUC and recall at 100 % precision (`slam.score`, `slam.localise_truth`);
- **learning mode**: the same summer then winter frames as ONE learning stream
  (`service_path.slam_replay`, the stress suite's `seasons`): lap-2 recall and precision, false
  revisits while mapping, merged places and wrong consolidations (`stress.merges`).
With every rule on (`all`) the localise mode also drives the window as two harder lap-2 kinds, both
made from the winter frames (`flat`: blurred and its contrast cut, a featureless other
season, `benchmarks/experiments/span.py`'s; `noise`: the winter frames with σ 8 pixel noise, harder than
the suite's noisy summer lap),
and each answer's decided confidence, span and whether the true row lies inside the span are kept, so
the revisit threshold is chosen from the lines (`threshold_table`, issue 37 item 2).

A rule is switched off for one run only (`switched_off`), the rest of the path being the service's:
`condition` (a stream's condition, science §11.10: `condition_frames` 0), `span` (the span gate,
§11.11: `span_max` 4096), `lag` (a revisit's path keeping pace with its stream, §11.13: `lag_max`
1000000), `short-term` (a stream's short-term memory, §11.6: `short_term` 0),
`consolidation` (the consolidation gate, §11.8: `consolidate` 1, every frame a row), `echo` (the echo
rule, §11.6: `benchmarks/experiments/echo.py`'s `off`), `flat-visits` (a flat frame consolidated into
a flat appearance its path names, §11.7/§11.8: a flat frame makes a row), `joins` (warm-up joins,
§11.8), `kept-joins` (a warm-up join that keeps its row, §11.8: `join_kept` 1), `low-information`
(frames with no information, §11.7: no contrast measured) and `null-rows`
(rows born from the null, §11.5: `benchmarks/experiments/null_entry.py`'s `rows`).

Jobs run in a process pool (`--jobs`); each line is written as its job ends, so a run cut short keeps
what it finished. Deterministic: the map seeds, the fixed noise seeds of the lap-2 kinds.
"""

from __future__ import annotations

import json
import multiprocessing
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from models.evaluation import sequences, slam
from models.localisation import PlaceMap, informative, trail
from models.localisation import localiser as loc
from models.localisation.localiser import reaches
from models.localisation.options import LAG_OFF
from models.localisation.places import Explained
from models.pipeline import observe
from service.evaluation import service_path, stress
from service.maps.config import DEFAULT_REVISIT_THRESHOLD

#: Every rule switched off, `all` first (every rule on: the default map).
RULES = ("all", "condition", "span", "lag", "short-term", "consolidation", "echo", "flat-visits", "joins",
         "kept-joins", "low-information", "null-rows")
#: The maps' localiser options that switch a rule off (the others are patched, `switched_off`).
OPTIONS: dict[str, dict[str, Any]] = {"condition": {"condition_frames": 0}, "span": {"span_max": 4096},
                                      "lag": {"lag_max": LAG_OFF}, "short-term": {"short_term": 0},
                                      "consolidation": {"consolidate": 1.0}, "kept-joins": {"join_kept": 1.0}}
#: Map seeds: 42 is a new map's (`CreateMap.seed`'s default).
SEEDS = (42, 1, 7, 100, 2024)
MEMORIES = ("tm", "none")
#: The localise mode's lap-2 kinds with every rule on: the window in winter, in winter flat, in winter noisy.
KINDS = ("winter", "flat", "noise")
TOLERANCE = stress.TOLERANCE
#: The issue's bar on a rule: it may cost no window more than this of either number.
COST = 0.01
#: The localise-mode revisit precision the threshold is chosen for (issue 37 item 2).
PRECISION = 0.99


class Job(NamedTuple):
    half: str
    lo: int
    seed: int
    memory: str
    rule: str


def _no_echo(self: trail.OwnTrail, graph: Any, rows: np.ndarray, began: np.ndarray) -> np.ndarray:
    return np.zeros(len(rows), bool)


def _no_joins(self: PlaceMap, *args: Any, **kwargs: Any) -> Explained:
    return Explained([], [])


def _rows_level(self: loc.SequenceLocaliser, past: np.ndarray, null: float) -> float:
    """Rows never born from the null (before docs/results.md §10.8): the best row path less the cost."""
    return (float(past.max()) if past.size else 0.0) - float(self.options.jump_cost)


def _no_flat_visits(model: Any, st: Any, projected: np.ndarray, **kw: Any) -> Any:
    """`observe`, but a flat learned frame is never consolidated (it makes a row of its own)."""
    if kw.get("learn") and not informative(kw.get("contrast")):
        model.place_map.consolidation = lambda *a, **k: None
        try:
            return observe(model, st, projected, **kw)
        finally:
            del model.place_map.consolidation
    return observe(model, st, projected, **kw)


#: The rules switched off by patching (owner, attribute, value) for the run only.
PATCHES: dict[str, tuple[Any, str, Callable[..., Any]]] = {
    "echo": (trail.OwnTrail, "laid_behind", _no_echo),
    "joins": (PlaceMap, "explained", _no_joins),
    "null-rows": (loc.SequenceLocaliser, "_jump_level", _rows_level),
    "flat-visits": (service_path, "observe", _no_flat_visits),
}


@contextmanager
def switched_off(rule: str) -> Iterator[None]:
    """The rule patched out while the block runs (nothing for `all` or a rule the options switch)."""
    if rule not in PATCHES:
        yield
        return
    owner, name, value = PATCHES[rule]
    old = getattr(owner, name)
    setattr(owner, name, value)
    try:
        yield
    finally:
        setattr(owner, name, old)


#: What the workers read: {(half, kind): (features (894, D), contrast (894,))} and the maps' keywords.
_FEATS: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]] = {}
_MAP: dict[str, Any] = {}


def prepare(data: Path, backbone: str | None, halves: tuple[str, ...], jobs: int = 1) -> None:
    """Each half's frames as summer, winter, flat and noisy, encoded once (the feature cache): with
    `jobs` > 1 the sets are encoded in parallel by fresh processes (spawned: the backbone's threads are
    not forked), then read here from the cache."""
    from service.evaluation.slam import encoder_setup

    sets = [(data, backbone, half, kind) for half in halves for kind in ("summer", *KINDS)]
    if jobs > 1:
        with multiprocessing.get_context("spawn").Pool(min(jobs, len(sets))) as pool:
            pool.map(_encode, sets)
    enc, cache, _ = encoder_setup(backbone, None)
    frames = stress.Frames(data, enc, cache)
    for _, _, half, kind in sets:
        pngs = _pngs(frames, half, kind)
        _FEATS[(half, kind)] = (frames.features(pngs), service_path.contrasts(pngs))


def _encode(job: tuple[Path, str | None, str, str]) -> None:
    from service.evaluation.slam import encoder_setup

    data, backbone, half, kind = job
    enc, cache, _ = encoder_setup(backbone, None)
    frames = stress.Frames(data, enc, cache)
    frames.features(_pngs(frames, half, kind))


def _pngs(frames: stress.Frames, half: str, kind: str) -> list[bytes]:
    lo, hi = stress.HALVES[half]
    return [_frame(frames, kind, i) for i in range(lo, hi)]


def _frame(frames: stress.Frames, kind: str, i: int) -> bytes:
    """File i as `kind`: summer, winter, or winter `flat` / with σ 8 `noise` (`stress.variant`, seeded
    by the file, so a file looks the same in every window)."""
    if kind in ("summer", "winter"):
        return stress.png(frames.image(kind, i))
    return stress.variant(frames.image("winter", i), "flat" if kind == "flat" else "noise:8", 7 + i)


def _localise(job: Job, kind: str, map_conf: dict[str, Any]) -> dict[str, Any]:
    a = job.lo - stress.HALVES[job.half][0]
    b = a + stress.WINDOW
    db, dbc = _FEATS[(job.half, "summer")]
    q, qc = _FEATS[(job.half, kind)]
    contrast = None if job.rule == "low-information" else np.r_[dbc[a:b], qc[a:b]]
    trace: dict[str, Any] = {}
    found = service_path.replay(db[a:b], q[a:b], seed=job.seed, memory=job.memory, contrast=contrast,
                                trace=trace, **map_conf)
    return localise_scores(found, trace["span"], trace["span_rows"], answers=job.rule == "all")


def _map_setup(backbone: str | None) -> None:
    """The served map's options for `backbone` (its localiser's left to each job) into `_MAP`."""
    from service.evaluation.slam import encoder_setup

    _, _, map_conf = encoder_setup(backbone, None)
    map_conf.pop("localiser")
    _MAP.update(map_conf)


def check_starts(starts: tuple[int, ...], kinds: tuple[str, ...],
                 windows: tuple[tuple[str, int], ...] | None) -> None:
    """`start_shares`' options, each one it can evaluate: a window inside its half (`stress.HALVES`,
    `lo` the file it starts at), a start inside the window, a kind of `KINDS`. Raises ValueError saying
    which is not."""
    for half, lo in windows or ():
        if half not in stress.HALVES:
            raise ValueError(f"no half {half!r}: the halves are {', '.join(stress.HALVES)}")
        first, end = stress.HALVES[half]
        if not first <= lo <= end - stress.WINDOW:
            raise ValueError(f"window {half}:{lo}: a {half} window of {stress.WINDOW} files starts at a "
                             f"file from {first} to {end - stress.WINDOW}")
    if not starts or any(not 0 <= s < stress.WINDOW for s in starts):
        raise ValueError(f"starts {starts}: each is a file into the window, 0 to {stress.WINDOW - 1}")
    if not kinds or not set(kinds) <= set(KINDS):
        raise ValueError(f"kinds {kinds}: each is one of {', '.join(KINDS)}")


def start_shares(*, data: Path, seed: int = 42, starts: tuple[int, ...] = (0, 23, 57),
                 kinds: tuple[str, ...] = ("winter", "flat"),
                 windows: tuple[tuple[str, int], ...] | None = None,
                 backbone: str | None = None) -> list[dict[str, Any]]:
    """The localise mode's laps started part-way into their window (docs/results.md §11): each window's
    summer frames learned as one traverse, its `kind` frames from file lo + start on localised
    (`service_path.replay`, every rule on), and the share of those frames whose answer names a row within
    `TOLERANCE` of the truth (a frame in warm-up counts as not named). `rules_runs` starts every lap at
    the map's first row, where a stream's first frame once named row 1 whatever it showed.

    Returns:
        One dict per window, kind and start: half, lo, kind, start, share.

    Raises:
        ValueError: an option it cannot evaluate (`check_starts`).
    """
    check_starts(starts, kinds, windows)
    _map_setup(backbone)
    todo = windows or tuple(stress.windows(False))
    prepare(data, backbone, tuple(sorted({half for half, _ in todo})))
    out = []
    for half, lo in todo:
        a = lo - stress.HALVES[half][0]
        b = a + stress.WINDOW
        db, dbc = _FEATS[(half, "summer")]
        for kind in kinds:
            q, qc = _FEATS[(half, kind)]
            for start in starts:
                found = service_path.replay(db[a:b], q[a + start:b], seed=seed, memory="tm",
                                            contrast=np.r_[dbc[a:b], qc[a + start:b]], **_MAP, localiser=None)
                named = (found.best >= 0) & (np.abs(found.best - np.arange(start, b - a)) <= TOLERANCE)
                out.append({"half": half, "lo": lo, "kind": kind, "start": start,
                            "share": round(float(named.mean()), 3)})
    return out


def starts_table(lines: list[dict[str, Any]]) -> str:
    """`start_shares`' lines as a markdown table: a row per window and kind, a column per start."""
    starts = sorted({x["start"] for x in lines})
    rows: dict[tuple[str, int, str], dict[int, float]] = {}
    for x in lines:
        rows.setdefault((x["half"], x["lo"], x["kind"]), {})[x["start"]] = x["share"]
    head = "| window | kind | " + " | ".join(f"start {s}" for s in starts) + " |\n"
    head += "|---|---|" + "---|" * len(starts) + "\n"
    return head + "".join(f"| {h} {lo + 1}-{lo + stress.WINDOW} | {k} | "
                          + " | ".join(_f(v.get(s)) for s in starts) + " |\n"
                          for (h, lo, k), v in rows.items())


def localise_scores(found: Any, span: np.ndarray, span_rows: list[tuple[int, ...]], *,
                    answers: bool) -> dict[str, Any]:
    """A localise-mode lap over a window (`service_path.replay`'s answers `found`, over n database rows
    whose true rows are the query's frame indices; `span` (n,) and `span_rows` its trace's): R@1, R@5,
    the all-pairs AUC, and at the default threshold precision, recall, right places called, query AUC and
    recall at 100 % precision; with `answers`, each answer's confidence, whether it names the true row,
    its span and whether the true row lies inside the span (for `threshold_table`)."""
    n = len(found.best)
    labels = np.r_[np.arange(n), np.arange(n)]
    laps = np.r_[np.zeros(n, np.int64), np.ones(n, np.int64)]
    best, conf = np.r_[np.full(n, -1), found.best], np.r_[np.zeros(n), found.confidence]
    s = slam.score(best, conf, labels, DEFAULT_REVISIT_THRESHOLD, TOLERANCE, laps,
                   slam.localise_truth(labels, laps, TOLERANCE))["lap"][1]
    answered = found.best >= 0
    e = sequences.evaluate(found.S, TOLERANCE, columns=answered, answers=(found.best, found.confidence))
    out = {"r1": s["recall_at_1"], "r5": e["recall_at_5"], "auc": e["auc"], "precision": s["precision"],
           "recall": s["recall"], "right_called": s["right_called"], "query_auc": s["query_auc"],
           "r100p": s["recall_at_100p"]}
    if answers:  # each answer, for the threshold (issue 37 item 2)
        truth = np.arange(n)
        inside = [bool(np.any(np.abs(np.asarray(rows, np.int64) - t) <= TOLERANCE)) if rows else False
                  for rows, t in zip(span_rows, truth, strict=True)]
        out["answers"] = {"conf": np.round(found.confidence[answered], 5).tolist(),
                          "named": (np.abs(found.best - truth) <= TOLERANCE)[answered].astype(int).tolist(),
                          "span": np.asarray(span)[answered].tolist(),
                          "inside": np.asarray(inside)[answered].astype(int).tolist()}
    return out


def _learn(job: Job, map_conf: dict[str, Any]) -> dict[str, Any]:
    a = job.lo - stress.HALVES[job.half][0]
    b = a + stress.WINDOW
    (s_f, s_c), (w_f, w_c) = _FEATS[(job.half, "summer")], _FEATS[(job.half, "winter")]
    n = b - a
    contrast = None if job.rule == "low-information" else np.r_[s_c[a:b], w_c[a:b]]
    trace: dict[str, Any] = {}
    found, threshold = service_path.slam_replay(np.r_[s_f[a:b], w_f[a:b]], seed=job.seed, memory=job.memory,
                                                contrast=contrast, trace=trace, **map_conf)
    labels = np.r_[np.arange(n), np.arange(n)]
    laps = np.r_[np.zeros(n, np.int64), np.ones(n, np.int64)]
    s = slam.score(found.best, found.confidence, labels, threshold, TOLERANCE, laps)
    lap2 = s["lap"][1]
    out = {"recall": lap2["recall"], "precision": lap2["precision"], "r1": lap2["recall_at_1"],
           "false_revisits": s["false_revisits"], **stress.merges(labels, trace)}
    if job.rule == "all":  # to rescore the false revisits while mapping at another threshold
        out["answers"] = {"best": found.best.tolist(), "conf": np.round(found.confidence, 5).tolist()}
    return out


def run_job(job: Job) -> dict[str, Any]:
    """One window, seed, memory and rule: both modes (module docstring), one JSON-able line."""
    t0 = time.perf_counter()
    map_conf = {**_MAP, "localiser": OPTIONS.get(job.rule)}
    with switched_off(job.rule):
        kinds = KINDS if job.rule == "all" else ("winter",)
        localise = {kind: _localise(job, kind, map_conf) for kind in kinds}
        learn = _learn(job, map_conf)
    return {**job._asdict(), "localise": localise, "learn": learn, "s": round(time.perf_counter() - t0, 2)}


def jobs_of(seeds: tuple[int, ...], rules: tuple[str, ...], memories: tuple[str, ...],
            windows: int = 0) -> list[Job]:
    """Every job, seed by seed (a run cut short has whole seeds): first the default memory's and the
    ablation's with every rule on, then the ablation's with each rule off; `windows` > 0: the first
    `windows` of each half."""
    per_half: dict[str, int] = {}
    wins = []
    for half, lo in stress.windows(False):
        per_half[half] = per_half.get(half, 0) + 1
        if not windows or per_half[half] <= windows:
            wins.append((half, lo))
    first = [(m, r) for m in memories for r in rules if m == memories[0] or r == "all"]
    then = [(m, r) for m in memories for r in rules if (m, r) not in first]
    return [Job(half, lo, seed, m, r) for group in (first, then) for seed in seeds for half, lo in wins
            for m, r in group]


def rules_runs(*, data: Path, out: Path, jobs: int = 1, seeds: tuple[int, ...] = SEEDS,
               rules: tuple[str, ...] = RULES, memories: tuple[str, ...] = MEMORIES, windows: int = 0,
               backbone: str | None = None, log: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """The experiment (module docstring): each job's line appended to `out` as it ends (JSON lines),
    progress to `log` (default stderr), then the tables written beside it (`out` with `.md`); returns
    the lines."""
    log = log or (lambda line: print(line, file=sys.stderr, flush=True))
    unknown = sorted(set(rules) - set(RULES))
    if unknown:
        raise ValueError(f"unknown rules {unknown}; known: {', '.join(RULES)}")
    _map_setup(backbone)
    todo = jobs_of(seeds, rules, memories, windows)
    t0 = time.perf_counter()
    prepare(data, backbone, tuple(sorted({j.half for j in todo})), jobs)
    log(f"features ready in {time.perf_counter() - t0:.0f} s; {len(todo)} jobs on {jobs} processes")
    run_job(todo[0])  # compile the kernels once, before the workers fork
    lines: list[dict[str, Any]] = []
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("w") as f:
        if jobs > 1:
            with multiprocessing.get_context("fork").Pool(jobs) as pool:
                for line in pool.imap_unordered(run_job, todo):
                    lines.append(line)
                    f.write(json.dumps(line) + "\n")
                    f.flush()
                    log(f"{len(lines)}/{len(todo)} {line['half']} {line['lo']} {line['seed']} "
                        f"{line['memory']} {line['rule']} {line['s']} s ({time.perf_counter() - t0:.0f} s)")
        else:
            for job in todo:
                line = run_job(job)
                lines.append(line)
                f.write(json.dumps(line) + "\n")
                f.flush()
    out.with_suffix(".md").write_text(tables(lines))
    return lines


# --------------------------------------------------------------------------------------------- tables


def _f(v: float | None) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{v:.3f}"


def _mw(values: list[float]) -> str:
    """'mean / worst' of the values (None left out)."""
    v = [x for x in values if x is not None]
    return f"{np.mean(v):.3f} / {np.min(v):.3f}" if v else "–"


def _by(lines: list[dict[str, Any]], **match: Any) -> list[dict[str, Any]]:
    return [x for x in lines if all(x[k] == v for k, v in match.items())]


def _window_means(lines: list[dict[str, Any]], get: Callable[[dict[str, Any]], float | None]
                  ) -> dict[tuple[str, int], float]:
    """{(half, lo): the mean over seeds of `get`} (None left out)."""
    acc: dict[tuple[str, int], list[float]] = {}
    for x in lines:
        v = get(x)
        if v is not None:
            acc.setdefault((x["half"], x["lo"]), []).append(v)
    return {k: float(np.mean(v)) for k, v in acc.items()}


def _key(x: dict[str, Any]) -> tuple[str, int, int]:
    return x["half"], x["lo"], x["seed"]


def rule_table(lines: list[dict[str, Any]]) -> str:
    """Item 3: per memory and rule switched off, over the windows and seeds it ran on with every rule on
    too ("runs"; mean / worst), and the rule's cost on its worst window (the mean over seeds with the rule
    off less with it on; positive: the rule costs that much there) and its gain on its best, of localise
    R@1 and learning lap-2 recall."""
    out = ["| memory | rule off | runs | localise R@1 | localise precision | learning lap-2 recall | "
           "learning precision | false revisits while mapping (total / worst) | merged places (total) | "
           "rule's worst cost R@1 / recall (window) | rule's best gain R@1 / recall | kept |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]

    def r1(x: dict[str, Any]) -> float | None:
        return x["localise"]["winter"]["r1"]

    def rec(x: dict[str, Any]) -> float | None:
        return x["learn"]["recall"]

    for memory in MEMORIES:
        ran = [r for r in RULES if _by(lines, memory=memory, rule=r)]
        if "all" not in ran:
            continue
        every = _by(lines, memory=memory, rule="all")
        for rule in ran:
            mine = _by(lines, memory=memory, rule=rule)
            paired = {_key(x) for x in mine} & {_key(x) for x in every}
            mine = [x for x in mine if _key(x) in paired]
            base = [x for x in every if _key(x) in paired]
            b_r1, b_rec = _window_means(base, r1), _window_means(base, rec)
            cells = [memory, rule if rule != "all" else "none (every rule on)", str(len(mine)),
                     _mw([r1(x) for x in mine]), _mw([x["localise"]["winter"]["precision"] for x in mine]),
                     _mw([rec(x) for x in mine]), _mw([x["learn"]["precision"] for x in mine]),
                     f"{sum(x['learn']['false_revisits'] for x in mine)} / "
                     f"{max(x['learn']['false_revisits'] for x in mine)}",
                     str(sum(x["learn"]["merged_places"] for x in mine))]
            if rule == "all":
                cells += ["–", "–", "–"]
            else:
                m_r1, m_rec = _window_means(mine, r1), _window_means(mine, rec)
                c_r1 = {k: m_r1[k] - b_r1[k] for k in m_r1 if k in b_r1}
                c_rec = {k: m_rec[k] - b_rec[k] for k in m_rec if k in b_rec}
                w1, w2 = max(c_r1, key=c_r1.get), max(c_rec, key=c_rec.get)
                cost = max(c_r1[w1], c_rec[w2])
                gain = f"{-min(c_r1.values()):+.3f} / {-min(c_rec.values()):+.3f}"
                cells += [f"{c_r1[w1]:+.3f} ({w1[0]} {w1[1] + 1}) / {c_rec[w2]:+.3f} ({w2[0]} {w2[1] + 1})",
                          gain, "yes" if cost <= COST else "trades"]
            out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def seed_table(lines: list[dict[str, Any]]) -> str:
    """Item 4 (and 5 beside it): every rule on, per half, memory and lap-2 kind: the localise mode's
    figures and the learning mode's, mean / worst over windows and seeds, and per seed the mean R@1."""
    out = ["| half | memory | lap 2 | R@1 | R@5 | AUC (paper, all pairs) | query AUC | R@100P | "
           "revisit precision | recall | right answers called | learning lap-2 recall | learning "
           "precision | false revisits / merged (total) | R@1 per seed (mean over windows) |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for half in stress.HALVES:
        for memory in MEMORIES:
            base = _by(lines, half=half, memory=memory, rule="all")
            if not base:
                continue
            seeds = sorted({x["seed"] for x in base}, key=lambda s: SEEDS.index(s) if s in SEEDS else s)
            for kind in KINDS:
                loc_ = [x["localise"][kind] for x in base]
                per_seed = ", ".join(
                    f"{s}: {np.mean([x['localise'][kind]['r1'] for x in base if x['seed'] == s]):.3f}"
                    for s in seeds)
                learn = kind == "winter"
                out.append("| " + " | ".join([
                    half, memory, kind, *(_mw([e[k] for e in loc_]) for k in
                                          ("r1", "r5", "auc", "query_auc", "r100p", "precision", "recall",
                                           "right_called")),
                    _mw([x["learn"]["recall"] for x in base]) if learn else "–",
                    _mw([x["learn"]["precision"] for x in base]) if learn else "–",
                    (f"{sum(x['learn']['false_revisits'] for x in base)} / "
                     f"{sum(x['learn']['merged_places'] for x in base)}") if learn else "–",
                    per_seed]) + " |")
    return "\n".join(out)


def spread(lines: list[dict[str, Any]], half: str = "tune", memory: str = "tm") -> str:
    """Item 4: the hardest window of `half` (lowest localise R@1, mean over seeds, every rule on) and
    its R@1 per seed and spread (max - min)."""
    base = _by(lines, half=half, memory=memory, rule="all")
    if not base:
        return ""
    means = _window_means(base, lambda x: x["localise"]["winter"]["r1"])
    worst = min(means, key=means.get)
    per = {x["seed"]: x["localise"]["winter"]["r1"] for x in base if (x["half"], x["lo"]) == worst}
    vals = list(per.values())
    files = f"files {worst[1] + 1}-{worst[1] + stress.WINDOW}"
    return (f"hardest {half} window ({files}, memory {memory}): R@1 per "
            f"seed {', '.join(f'{s}: {v:.3f}' for s, v in per.items())}; spread {max(vals) - min(vals):.3f}")


def answers_of(lines: list[dict[str, Any]], half: str, memory: str, kind: str, seed: int | None = None
             ) -> dict[str, np.ndarray]:
    rows = [x["localise"][kind]["answers"] for x in _by(lines, half=half, memory=memory, rule="all")
            if seed is None or x["seed"] == seed]
    return {k: np.concatenate([np.asarray(r[k]) for r in rows]) if rows else np.zeros(0)
            for k in ("conf", "named", "span", "inside")}


def at_threshold(a: dict[str, np.ndarray], t: float) -> tuple[float | None, float | None, int]:
    """(precision, right places called, revisits) at `t`: a revisit is an answer whose decided
    confidence reaches t (the span gate and the low-information rule already set it to 0); it is right
    when the true row lies inside its span (the span being at most `span_max` = 3, as every revisit's is);
    "right places called" = right revisits / answers that name the true row (within the tolerance)."""
    called = reaches(a["conf"], t) if a["conf"].size else np.zeros(0, bool)
    n = int(called.sum())
    right = int((called & (a["inside"] > 0)).sum())
    named = int((a["named"] > 0).sum())
    return (right / n if n else None), (int((called & (a["named"] > 0)).sum()) / named if named else None), n


def learning_false(lines: list[dict[str, Any]], t: float, half: str = "tune", memory: str = "tm") -> int:
    """False revisits while mapping of the learning runs (every rule on) rescored at `t` (the runs were
    made at the default: a frame consolidated there would be a row at a higher threshold)."""
    n = stress.WINDOW
    labels, laps = np.r_[np.arange(n), np.arange(n)], np.r_[np.zeros(n, np.int64), np.ones(n, np.int64)]
    runs = [x["learn"]["answers"] for x in _by(lines, half=half, memory=memory, rule="all")]
    return sum(slam.score(np.asarray(a["best"]), np.asarray(a["conf"]), labels, t, TOLERANCE,
                          laps)["false_revisits"] for a in runs)


def choose_threshold(lines: list[dict[str, Any]], memory: str = "tm") -> tuple[float | None, list[str]]:
    """Item 2 on `tune` only, what the lines say: the lowest threshold (0.005 steps, 0.80-0.99) at which
    every lap-2 kind at every seed reaches localise-mode revisit precision >= PRECISION, pooled over the
    windows, and the learning runs rescored there make no more false revisits while mapping than at the
    current default; and the sweep's table. (The stress suite at the candidates, `cortexloc eval slam
    --suite --threshold`, and the margin kept above are docs/results.md §10.14's.)"""
    seeds = sorted({x["seed"] for x in _by(lines, half="tune", memory=memory, rule="all")})
    at_default = learning_false(lines, DEFAULT_REVISIT_THRESHOLD, memory=memory)
    chosen = None
    rows = []
    for t in np.round(np.arange(0.80, 0.9901, 0.005), 3):
        precs, calls = [], []
        for kind in KINDS:
            for s in seeds:
                p, c, _ = at_threshold(answers_of(lines, "tune", memory, kind, s), float(t))
                precs += [p] if p is not None else []
                calls += [c] if c is not None else []
        worst = min(precs) if precs else None
        false = learning_false(lines, float(t), memory=memory)
        if chosen is None and worst is not None and worst >= PRECISION and false <= at_default:
            chosen = float(t)
        rows.append((float(t), worst, min(calls) if calls else None, false))
    table = ["| threshold | worst localise precision, kinds x seeds (`tune`) | worst right places called | "
             "learning: false revisits while mapping (rescored, `tune`) |", "|---|---|---|---|"]
    table += [f"| {t:.3f} | {_f(p)} | {_f(c)} | {f} |" for t, p, c, f in rows
              if round(t * 1000) % 20 == 0 or t in (chosen, DEFAULT_REVISIT_THRESHOLD)]
    return chosen, table


def threshold_table(lines: list[dict[str, Any]]) -> str:
    """Item 2: the threshold chosen on `tune`, and at it and at the current default, per half, memory,
    kind and seed pooled over windows: precision and right places called."""
    out = []
    chosen, sweep = choose_threshold(lines)
    out.append(f"lowest on tune (memory tm, every kind and seed >= {PRECISION}, no more false revisits "
               f"while mapping than at the default): {chosen}; current default {DEFAULT_REVISIT_THRESHOLD}")
    out += sweep
    out += ["", "| half | memory | lap 2 | threshold | precision per seed (pooled over windows) | "
            "right places called per seed | precision, all seeds | right places called, all seeds |",
            "|---|---|---|---|---|---|---|---|"]
    for half in stress.HALVES:
        for memory in MEMORIES:
            seeds = sorted({x["seed"] for x in _by(lines, half=half, memory=memory, rule="all")},
                           key=lambda s: SEEDS.index(s) if s in SEEDS else s)
            if not seeds:
                continue
            for kind in KINDS:
                for t in sorted({DEFAULT_REVISIT_THRESHOLD, chosen or DEFAULT_REVISIT_THRESHOLD}):
                    per = [at_threshold(answers_of(lines, half, memory, kind, s), t) for s in seeds]
                    p, c, _ = at_threshold(answers_of(lines, half, memory, kind), t)
                    out.append(f"| {half} | {memory} | {kind} | {t:.3f} | "
                               f"{', '.join(_f(x[0]) for x in per)} | {', '.join(_f(x[1]) for x in per)} | "
                               f"{_f(p)} | {_f(c)} |")
    return "\n".join(out)


def tables(lines: list[dict[str, Any]]) -> str:
    """Every table of docs/results.md §10.14 from the lines."""
    parts = ["### Rules (item 3), every window and seed, mean / worst", rule_table(lines), "",
             "### Seeds (item 4) and the memory (item 5), every rule on", seed_table(lines), "",
             spread(lines), spread(lines, memory="none"), "",
             "### Threshold (item 2)", threshold_table(lines)]
    return "\n".join(parts) + "\n"


def read(path: Path) -> list[dict[str, Any]]:
    return [json.loads(s) for s in path.read_text().splitlines() if s.strip()]
