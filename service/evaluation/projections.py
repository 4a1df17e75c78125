"""The map seed's spread and what might narrow it: the localise mode with the sLSBH projection varied,
over map seeds, on the windows of `cortexloc eval rules` (issue 37 item 4; docs/results.md §10.16).

    cortexloc eval projections --data ../shared/data/nordland_tiny_64x32 --jobs 2 --halves tune \
        --windows 1 --out hardest.jsonl                     # the hardest `tune` window (files 1-200)
    cortexloc eval projections --tables hardest.jsonl       # the tables again from the lines

The map seed draws the projection P (docs/design/science.md §7.1) and the memory's wiring; the rules
run (§10.14) found the hardest `tune` window's localise-mode R@1 spread 0.075 over 5 seeds (0.080
without the memory). Each variant replaces only the projection step of `service_path.replay` (the
served map's path otherwise: its memory, localiser and rules at the defaults), per window, seed and
memory (`tm` and `none`, the memory's ablation):

- `today`: the map's projection, as served;
- `concat:K`: K projections of k/K columns each, drawn from K seeds (the map seed's and K-1 derived
  ones) and stacked: the same code size (2k bits). Column by column this is the same law as one draw
  (every column an independent unit Gaussian), so it can only show that;
- `wide:K`: one hash of K stacked projections: k·K columns (the code 2k·K bits, the memory's columns
  2k·K, the same sparsity s), K times the size. The projection is the one such a map gets within the
  default map budget (`service.maps.encoding.projection.for_map`): from K = 2 the very sparse one
  (§7.1), since the memory alone is then over CORTEXLOC_MAX_MAP_BYTES' default (a served map needs it
  raised: 142 MB of memory and streams at K = 2, 282 MB at K = 4); `wide-dense:K` the same with the
  dense Gaussian projection (what a map gets with the budget above the memory plus D·k·K·4 bytes);
- `vote:K`: K maps (the map seed and K-1 derived ones: K projections and K memories) each learn the
  window and localise it; the vote is the sum of the K beam-score matrices (a map's rows outside its
  beam at its lowest score of that frame): per query frame the answer is the row where the sum is
  highest, its confidence the sum of the confidences of the maps whose answer lies within the
  tolerance of it / K, its span the union of their spans (a vote of the K decided answers picks the
  first map's on the hard frames, where every map's decided confidence is 0);
- `centred`: y = (x - mu)·P, mu the mean of the map's own (reference) frames, never the query's;
- `pca:R`: the reference frames' centred features onto their first R principal directions, then a
  (R, k) Gaussian projection from the map seed: y = ((x - mu)·V_R)·G;
- `whiten:R`: as `pca:R`, each direction divided by its standard deviation over the reference frames;
- `adapt:T`: the map option that exists (`slsbh.adapt_tau` T: each stream's running mean subtracted,
  models/frontend/adaptation.py).

Fitted variants see the whole window's reference frames before the first is learned (an upper bound
on what a map fitted on its own frames could do, since a served map makes its projection before its
first frame). Jobs run in a process pool; each line is written as its job ends. Deterministic.
"""

from __future__ import annotations

import functools
import json
import multiprocessing
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from models.evaluation.online import OnlineAnswers
from models.frontend import slsbh
from service.evaluation import rules, service_path, stress

#: The variants measured by default (module docstring).
VARIANTS = ("today", "concat:4", "wide:2", "vote:3", "centred", "pca:64", "whiten:64", "adapt:20")
NAMES = ("today", "concat", "wide", "wide-dense", "vote", "centred", "pca", "whiten", "adapt")
SEEDS = rules.SEEDS
MEMORIES = rules.MEMORIES
#: The issue's bars: the hardest `tune` window's spread over seeds, and what a variant may cost a window.
SPREAD = 0.05
COST = rules.COST
TOLERANCE = rules.TOLERANCE


class Job(NamedTuple):
    half: str
    lo: int
    seed: int
    memory: str
    variant: str


def parse(variant: str) -> tuple[str, int]:
    """(name, its number: K, R or T; 0 where it takes none). Raises ValueError for an unknown one."""
    name, _, arg = variant.partition(":")
    if name not in NAMES or (name in ("today", "centred")) != (arg == "") or (arg and int(arg) < 1):
        raise ValueError(f"unknown variant {variant!r}; known: today, centred, concat:K, wide:K, "
                         "wide-dense:K, vote:K, pca:R, whiten:R, adapt:T")
    return name, int(arg or 0)


def derived(seed: int, i: int) -> int:
    """The i-th seed derived from a map seed (the 0th is the map seed itself)."""
    return seed if i == 0 else int(np.random.SeedSequence([seed, i]).generate_state(1)[0] % 2**31)


class Fitted:
    """x -> ((x - mu)·W)·P, hashed as the map's codes (`Hasher`'s `project` and `s`, all `replay` reads).

    Args:
        P: (R, k) float32 projection applied last. s: the map's sparsity.
        mu: (D,) mean subtracted first, or None. W: (D, R) applied after, or None (R = D).
    """

    def __init__(self, P: np.ndarray, s: float, mu: np.ndarray | None = None,
                 W: np.ndarray | None = None) -> None:
        self.P, self.s, self.mu, self.W = P, s, mu, W

    def project(self, X: np.ndarray) -> np.ndarray:
        """(N, D) features -> (N, k) float32."""
        X = np.asarray(X, np.float32)
        if self.mu is not None:
            X = X - self.mu
        if self.W is not None:
            X = X @ self.W
        return np.ascontiguousarray(X @ self.P, dtype=np.float32)


def fitted(name: str, r: int, reference: np.ndarray, hasher: slsbh.Hasher, seed: int
           ) -> Fitted | slsbh.Hasher:
    """The projection of variant `name` for a map of seed `seed` whose reference frames are `reference`
    (n, D); `hasher` is the map's own (`today`'s)."""
    k, s = hasher.k, hasher.s
    if name == "wide-dense":
        return slsbh.Hasher(slsbh.make_projection(hasher.d, k, seed), s)
    if name == "concat":
        parts = [slsbh.make_projection(hasher.d, k // r + (i < k % r), derived(seed, i)) for i in range(r)]
        return slsbh.Hasher(np.ascontiguousarray(np.hstack(parts)), s)
    if name not in ("centred", "pca", "whiten"):
        return hasher
    mu = reference.mean(axis=0, dtype=np.float64).astype(np.float32)
    if name == "centred":
        assert isinstance(hasher.P, np.ndarray)
        return Fitted(hasher.P, s, mu)
    _, sv, vt = np.linalg.svd(reference.astype(np.float64) - mu, full_matrices=False)
    r = min(r, int(np.sum(sv > sv[0] * 1e-6)))
    W = vt[:r].T
    if name == "whiten":
        W = W / (sv[:r] / np.sqrt(max(len(reference) - 1, 1)))
    return Fitted(slsbh.make_projection(r, k, seed), s, mu, W.astype(np.float32))


@contextmanager
def projected_by(make: Callable[[slsbh.Hasher], Any]) -> Iterator[None]:
    """`service_path.replay`'s projection step replaced by `make(the map's hasher)` while the block runs."""
    old = service_path._model

    def model(*args: Any, **kwargs: Any) -> Any:
        m, hasher, config = old(*args, **kwargs)
        return m, make(hasher), config

    service_path._model = model
    try:
        yield
    finally:
        service_path._model = old


def _replay(job: Job, kind: str, seed: int, create: dict[str, Any] | None,
            make: Callable[[slsbh.Hasher], Any]) -> tuple[OnlineAnswers, dict[str, Any]]:
    a = job.lo - stress.HALVES[job.half][0]
    b = a + stress.WINDOW
    db, dbc = rules._FEATS[(job.half, "summer")]
    q, qc = rules._FEATS[(job.half, kind)]
    trace: dict[str, Any] = {}
    with projected_by(make):
        found = service_path.replay(db[a:b], q[a:b], seed=seed, memory=job.memory, create=create,
                                    contrast=np.r_[dbc[a:b], qc[a:b]], trace=trace,
                                    **{**rules._MAP, "localiser": None})
    return found, trace


def vote(runs: list[tuple[OnlineAnswers, dict[str, Any]]]
         ) -> tuple[OnlineAnswers, np.ndarray, list[tuple[int, ...]]]:
    """K maps' answers voted (module docstring, `vote:K`): (answers, span (n,), span rows)."""
    S = np.zeros_like(runs[0][0].S)
    seen = np.zeros(S.shape[1], bool)
    for f, _ in runs:
        finite = np.isfinite(f.S)
        low = np.where(finite, f.S, np.inf).min(axis=0)
        S += np.where(finite, f.S, np.where(np.isfinite(low), low, 0.0))
        seen |= finite.any(axis=0)
    S[:, ~seen] = -np.inf
    n, k = S.shape[1], len(runs)
    best, conf = np.full(n, -1, np.int64), np.zeros(n)
    support, span, span_rows = np.zeros(n, np.int64), np.zeros(n, np.int64), [()] * n
    for j in range(n):
        if not seen[j] or all(f.best[j] < 0 for f, _ in runs):
            continue
        row = int(np.argmax(S[:, j]))
        agree = [(float(f.confidence[j]), t["span_rows"][j]) for f, t in runs
                 if f.best[j] >= 0 and abs(int(f.best[j]) - row) <= TOLERANCE]
        rows = tuple(sorted({r for c, rs in agree if c > 0 for r in rs}))
        best[j], conf[j], support[j] = row, sum(c for c, _ in agree) / k, len(agree)
        span[j], span_rows[j] = len(rows), rows
    return OnlineAnswers(best, conf, support, S), span, span_rows


def run_job(job: Job, kinds: tuple[str, ...] = ("winter",)) -> dict[str, Any]:
    """One window, seed, memory and variant: the localise mode's figures per lap-2 kind
    (`rules.localise_scores`, with each answer's confidence and span), one JSON-able line."""
    t0 = time.perf_counter()
    name, r = parse(job.variant)
    a = job.lo - stress.HALVES[job.half][0]
    reference = rules._FEATS[(job.half, "summer")][0][a:a + stress.WINDOW]
    create = None
    if name in ("wide", "wide-dense"):
        k = int(slsbh_k())
        create = {"slsbh": {"k": k * r}, "tm": {"columnDimensions": 2 * k * r}}
    elif name == "adapt":
        create = {"slsbh": {"adapt_tau": r}}
    out: dict[str, Any] = {}
    for kind in kinds:
        if name == "vote":
            runs = [_replay(job, kind, derived(job.seed, i), None, lambda h: h) for i in range(r)]
            found, span, span_rows = vote(runs)
        else:
            found, trace = _replay(job, kind, job.seed, create,
                                   lambda h: fitted(name, r, reference, h, job.seed))
            span, span_rows = trace["span"], trace["span_rows"]
        out[kind] = rules.localise_scores(found, span, span_rows, answers=True)
    return {**job._asdict(), "localise": out, "s": round(time.perf_counter() - t0, 2)}


def slsbh_k() -> int:
    """The default map's projected dimension (the one home: `presets.SlsbhOptions`)."""
    from models import presets

    return int(presets.SlsbhOptions.of(presets.slsbh_params(rules._MAP["preset"])).k)


def jobs_of(seeds: tuple[int, ...], variants: tuple[str, ...], memories: tuple[str, ...],
            halves: tuple[str, ...], windows: int = 0) -> list[Job]:
    """Every job, variant by variant (a run cut short has whole variants); `windows` > 0: the first
    `windows` of each half (the first of `tune` is the hardest, files 1-200)."""
    per_half: dict[str, int] = {}
    wins = []
    for half, lo in stress.windows(False):
        per_half[half] = per_half.get(half, 0) + 1
        if half in halves and (not windows or per_half[half] <= windows):
            wins.append((half, lo))
    return [Job(half, lo, seed, m, v) for v in variants for m in memories for seed in seeds
            for half, lo in wins]


def projection_runs(*, data: Path, out: Path, jobs: int = 1, seeds: tuple[int, ...] = SEEDS,
                    variants: tuple[str, ...] = VARIANTS, memories: tuple[str, ...] = MEMORIES,
                    halves: tuple[str, ...] = tuple(stress.HALVES), windows: int = 0,
                    kinds: tuple[str, ...] = ("winter",), backbone: str | None = None,
                    log: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """The experiment (module docstring): each job's line appended to `out` as it ends (JSON lines), the
    tables beside it (`out` with `.md`); returns the lines. Raises ValueError for an unknown variant,
    half or kind."""
    log = log or (lambda line: print(line, file=sys.stderr, flush=True))
    from service.evaluation.slam import encoder_setup

    for v in variants:
        parse(v)
    if set(halves) - set(stress.HALVES) or set(kinds) - set(rules.KINDS):
        raise ValueError(f"halves: {', '.join(stress.HALVES)}; kinds: {', '.join(rules.KINDS)}")
    _, _, map_conf = encoder_setup(backbone, None)
    map_conf.pop("localiser")
    rules._MAP.update(map_conf)
    todo = jobs_of(seeds, variants, memories, halves, windows)
    t0 = time.perf_counter()
    rules.prepare(data, backbone, halves, jobs)
    log(f"features ready in {time.perf_counter() - t0:.0f} s; {len(todo)} jobs on {jobs} processes")
    run_job(todo[0]._replace(variant="today"), ("winter",))  # compile the kernels before the workers fork
    lines: list[dict[str, Any]] = []
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("w") as f:
        pool = multiprocessing.get_context("fork").Pool(jobs) if jobs > 1 else None
        try:
            run = functools.partial(run_job, kinds=kinds)
            for line in (pool.imap(run, todo) if pool else map(run, todo)):
                lines.append(line)
                f.write(json.dumps(line) + "\n")
                f.flush()
                log(f"{len(lines)}/{len(todo)} {line['half']} {line['lo']} {line['seed']} {line['memory']} "
                    f"{line['variant']} R@1 {line['localise']['winter']['r1']:.3f} {line['s']} s "
                    f"({time.perf_counter() - t0:.0f} s)")
        finally:
            if pool:
                pool.close()
    out.with_suffix(".md").write_text(tables(lines))
    return lines


# --------------------------------------------------------------------------------------------- tables


def _windows(lines: list[dict[str, Any]], variant: str, memory: str, half: str, kind: str
             ) -> dict[int, dict[int, float]]:
    """{window lo: {seed: R@1}}."""
    out: dict[int, dict[int, float]] = {}
    for x in rules._by(lines, variant=variant, memory=memory, half=half):
        if kind in x["localise"]:
            out.setdefault(x["lo"], {})[x["seed"]] = x["localise"][kind]["r1"]
    return out


def hardest(lines: list[dict[str, Any]], memory: str = "tm") -> int | None:
    """The `tune` window where `today` has the lowest mean R@1 over seeds (its first file, 0-based)."""
    w = _windows(lines, "today", memory, "tune", "winter")
    return min(w, key=lambda lo: np.mean(list(w[lo].values()))) if w else None


def costs(lines: list[dict[str, Any]], variant: str, memory: str, kind: str = "winter"
          ) -> tuple[float, str, float, str] | None:
    """Against `today` on the windows both ran (same seeds): (the largest drop of mean R@1 over seeds, its
    window; the largest drop of the worst seed's R@1, its window); positive: the variant costs that."""
    worst_mean, worst_low = (-np.inf, ""), (-np.inf, "")
    for half in stress.HALVES:
        base = _windows(lines, "today", memory, half, kind)
        mine = _windows(lines, variant, memory, half, kind)
        for lo in set(base) & set(mine):
            seeds = set(base[lo]) & set(mine[lo])
            if not seeds:
                continue
            b, m = [base[lo][s] for s in seeds], [mine[lo][s] for s in seeds]
            where = f"{half} {lo + 1}"  # files 1-based from the route's first, as `eval rules`
            worst_mean = max(worst_mean, (float(np.mean(b) - np.mean(m)), where))
            worst_low = max(worst_low, (float(min(b) - min(m)), where))
    if worst_mean[1] == "":
        return None
    return worst_mean[0], worst_mean[1], worst_low[0], worst_low[1]


def _pooled(lines: list[dict[str, Any]], kind: str, **match: Any) -> dict[str, np.ndarray]:
    """Each answer of the matching lines' lap-2 `kind`, pooled (`rules.at_threshold`'s input)."""
    rows = [x["localise"][kind]["answers"] for x in rules._by(lines, **match) if kind in x["localise"]]
    return {f: np.concatenate([np.asarray(r[f]) for r in rows]) if rows else np.zeros(0)
            for f in ("conf", "named", "span", "inside")}


def variant_table(lines: list[dict[str, Any]], kind: str = "winter") -> str:
    """Per variant, memory and half: mean / worst over windows and seeds of R@1, R@5, R@100P, and at the
    default threshold the revisits' precision (named within the tolerance), their span precision and the
    right places called (issue 37's count, `rules.at_threshold`, pooled; with the revisits and the wrong
    ones counted); the hardest `tune` window's R@1
    per seed and spread; the cost against `today` on its worst window and the worst seed's; whether the
    variant meets item 4's bars."""
    out = ["| variant | memory | half | runs | R@1 | R@5 | R@100P | revisit precision (named) | span "
           "precision / right places called (revisits, wrong; pooled) | hardest `tune` window: R@1 per "
           "seed | spread | mean / worst seed | cost vs today: mean R@1 (window) / worst seed (window) | "
           "meets item 4 (on the windows run) |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    variants = list(dict.fromkeys(x["variant"] for x in lines))
    for variant in variants:
        for memory in MEMORIES:
            lo = hardest(lines, memory)
            for half in stress.HALVES:
                mine = [x for x in rules._by(lines, variant=variant, memory=memory, half=half)
                        if kind in x["localise"]]
                if not mine:
                    continue
                e = [x["localise"][kind] for x in mine]
                p, c, n = rules.at_threshold(_pooled(lines, variant=variant, memory=memory, half=half,
                                                     kind=kind), rules.DEFAULT_REVISIT_THRESHOLD)
                wrong = round(n * (1 - p)) if p is not None else 0
                hard = _windows(lines, variant, memory, "tune", kind).get(lo, {}) if half == "tune" else {}
                vals = list(hard.values())
                cost = costs(lines, variant, memory, kind) if variant != "today" else None
                spread_ = max(vals) - min(vals) if vals else None
                meets = "–"
                if cost is not None and spread_ is not None:
                    meets = "yes" if spread_ <= SPREAD and cost[0] <= COST and cost[2] <= COST else "no"
                out.append("| " + " | ".join([
                    variant, memory, half, str(len(mine)),
                    *(rules._mw([v[k] for v in e]) for k in ("r1", "r5", "r100p")),
                    rules._mw([v["precision"] for v in e]), f"{rules._f(p)} / {rules._f(c)} ({n}, {wrong})",
                    ", ".join(f"{s}: {v:.3f}" for s, v in hard.items()) or "–",
                    rules._f(spread_), f"{np.mean(vals):.3f} / {min(vals):.3f}" if vals else "–",
                    (f"{cost[0]:+.3f} ({cost[1]}) / {cost[2]:+.3f} ({cost[3]})" if cost and half == "tune"
                     else "–"), meets if half == "tune" else "–"]) + " |")
    return "\n".join(out)


def window_table(lines: list[dict[str, Any]], memory: str, kind: str = "winter") -> str:
    """Per window that `today` ran on: each variant's R@1, mean / worst over the seeds (what `costs`
    compares)."""
    variants = list(dict.fromkeys(x["variant"] for x in rules._by(lines, memory=memory)))
    if "today" not in variants:
        return ""
    out = ["| window (files) | " + " | ".join(variants) + " |", "|---" * (len(variants) + 1) + "|"]
    for half in stress.HALVES:
        per = {v: _windows(lines, v, memory, half, kind) for v in variants}
        for lo in sorted(per["today"]):
            cells = [f"{half} {lo + 1}-{lo + stress.WINDOW}"]
            for v in variants:
                r = list(per[v].get(lo, {}).values())
                cells.append(f"{np.mean(r):.3f} / {min(r):.3f}" if r else "–")
            out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def tables(lines: list[dict[str, Any]]) -> str:
    """docs/results.md §10.16's tables from the lines: one per lap-2 kind that ran."""
    kinds = [k for k in rules.KINDS if any(k in x["localise"] for x in lines)]
    parts = []
    for kind in kinds:
        parts += [f"### Localise mode, lap 2 `{kind}`, every variant (mean / worst over windows and seeds)",
                  variant_table(lines, kind), ""]
        for memory in MEMORIES:
            table = window_table(lines, memory, kind)
            if table:
                parts += [f"### Per window, lap 2 `{kind}`, memory `{memory}`: R@1 mean / worst over seeds",
                          table, ""]
    return "\n".join(parts)


read = rules.read
