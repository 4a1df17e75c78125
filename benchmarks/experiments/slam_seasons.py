"""Experiments of docs/results.md §10.6: changes to the localiser's evidence tried against the season
bias of one learning stream, over the `cortexloc eval slam` routes. Not the service's code: each
wraps `SequenceLocaliser.step` for the run only, so the rest of the path is the service's.

    cortexloc eval slam-seasons own 0.5 --half test
    cortexloc eval slam-seasons contrast 5 --half test

`own X`: the evidence of candidate rows on the stream's own trail lowered by X candidate spreads.
`contrast W`: each candidate's score less the mean of its ±W route neighbours' (rows outside the
candidates at the weakest candidate's score): SeqSLAM's local contrast along the links.
(Stream adaptation, the third, is a map option: `cortexloc eval slam --adapt-tau 20`.)

The experiments of §10.7, before a stream's condition became the service's rule (with the service's
condition off, `condition_frames` 0, so each runs alone):
`hub T B`: each candidate's score less B × its expected Dice with the stream's recent frames (an
exponential average of the stream's code bits, time constant T), after the plain ranking.
`idf T B`: the index's overlap weighted per query cell by max(0, 1 − B × its column's rate in the
stream's recent frames (time constant T, the rates started at the first frame's bits)), summed shared
weight over the query's (the first form of docs/design/science.md §11.10).
`local M B`: the same weights from the frame's M best rows by plain Dice instead of the stream's past.

    cortexloc eval slam-seasons hub 50 2 --half test
    cortexloc eval slam-seasons idf 100 2 --half tune
    cortexloc eval slam-seasons local 100 2 --half tune
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.localisation import localiser as loc


def own(x: float):
    def change(graph, seqs, scores, own_trail):
        if own_trail is not None and x and seqs.size:
            scores = scores.copy()
            scores[graph.trail[seqs] == own_trail.trail] -= x * (scores.std() + 1e-9)
        return scores
    return change


def contrast(w: int):
    def change(graph, seqs, scores, own_trail):
        if not w or seqs.size < 2:
            return scores
        floor, look, h = scores.min(), dict(zip(seqs.tolist(), scores.tolist(), strict=True)), seqs.size
        nb = np.full((h, 2 * w), floor)
        fw, bw = seqs.copy(), seqs.copy()
        for k in range(w):
            fw, bw = graph.walk(fw, np.ones(h, np.int8), 1), graph.walk(bw, -np.ones(h, np.int8), 1)
            nb[:, 2 * k] = [look.get(int(r), floor) for r in fw]
            nb[:, 2 * k + 1] = [look.get(int(r), floor) for r in bw]
        return scores - nb.mean(1)
    return change


_RATES: dict[int, np.ndarray] = {}  # id(stream state) -> its bit rates (`hub`, `idf`)
_FRAME: dict[str, object] = {}  # what the frame being observed is: its stream's key, code, code_of, cpc


def _rates_after(key: int, code: np.ndarray, tau: float, width: int) -> None:
    rates = _RATES.get(key)
    if rates is None:
        rates = _RATES[key] = np.zeros(width)
        rates[code] = 1.0
    else:
        rates *= 1.0 - 1.0 / tau
        rates[code] += 1.0 / tau


def _watch_frames(tau: float) -> None:
    """Wrap `observe` (wherever the evaluation imported it): note each frame's stream, code and
    `code_of` for the ranking, then take its code into the stream's rates."""
    import models.pipeline as pipeline
    from models.pipeline import core
    from service.evaluation import service_path

    observe = core.observe

    def observed(model, st, projected, **kw):
        cpc = int(model.tm.cells_per_column) if model.memory == "tm" else 1
        width = int(model.place_map.codes.counts.size)
        _FRAME.update(key=id(st), cpc=cpc, code_of=kw["code_of"], width=width)
        step = observe(model, st, projected, **kw)
        _rates_after(id(st), step.code, tau, int(_FRAME["width"]))
        _FRAME.clear()
        return step

    core.observe = pipeline.observe = service_path.observe = observed


def hub(tau: float, beta: float):
    """`hub T B` (module docstring): a change of the localiser's candidate scores."""
    _watch_frames(tau)

    def change(graph, seqs, scores, own_trail):
        rates = _RATES.get(_FRAME.get("key"))
        if rates is None or not seqs.size:
            return scores
        code_of = _FRAME["code_of"]
        codes = [np.asarray(code_of(int(r)), np.int64) for r in seqs]  # a map's codes have one size
        return scores - beta * np.array([rates[c].sum() / max(c.size, 1) for c in codes])
    return change


def _weighted_rank(weights_of):
    """Replace `InvertedIndex.rank` by an every-row ranking on shared weight / query weight, the query
    cells' weights from `weights_of(index, q)` (None: the plain ranking)."""
    from models.localisation import index as ix

    rank = ix.InvertedIndex.rank

    def ranked(self, cells, top_k, *, exclude_seqs=(), exclude_own=None, min_overlap=1, weights=None):
        q = np.unique(np.asarray(cells, np.int64))
        w = weights_of(self, q, exclude_seqs, exclude_own) if q.size and self._seq.n else None
        if w is None or not w.any():
            return rank(self, cells, top_k, exclude_seqs=exclude_seqs, exclude_own=exclude_own,
                        min_overlap=min_overlap)
        n = self._seq.n
        acc, ov = np.zeros(n), np.zeros(n, np.int64)
        for c, wc in zip(q.tolist(), w.tolist(), strict=True):
            rows = self._post[c][: self._plen[c]] if self._plen[c] else np.zeros(0, np.int64)
            acc[rows] += wc
            ov[rows] += 1
        keep = ov >= max(min_overlap, 1)
        keep[self._excluded_rows(exclude_seqs, exclude_own)] = False
        cand = np.flatnonzero(keep)
        score = 2.0 * acc[cand] / (self._weight.data[cand] + q.size)
        order = np.lexsort((cand, -score))[:top_k]
        return [ix.Match(int(a), int(b), float(c)) for a, b, c in
                zip(self._seq.data[cand[order]], ov[cand[order]], score[order], strict=True)]

    ix.InvertedIndex.rank = ranked


def idf(tau: float, beta: float) -> None:
    """`idf T B` (module docstring)."""
    _watch_frames(tau)

    def weights_of(index, q, exclude_seqs, exclude_own):
        rates = _RATES.get(_FRAME.get("key"))
        return None if rates is None else np.clip(1.0 - beta * rates[q // int(_FRAME["cpc"])], 0.0, None)

    _weighted_rank(weights_of)


def local(m: int, beta: float) -> None:
    """`local M B` (module docstring)."""
    from models.localisation import index as ix

    rank = ix.InvertedIndex.rank

    def weights_of(index, q, exclude_seqs, exclude_own):
        best = rank(index, q, m, exclude_seqs=exclude_seqs, exclude_own=exclude_own)
        if not best:
            return None
        rows = np.searchsorted(index._seq.view(), [b.seq for b in best])
        top = np.zeros(index._seq.n, bool)
        top[rows] = True
        held = [top[index._post[c][: index._plen[c]]].sum() if index._plen[c] else 0 for c in q.tolist()]
        return np.clip(1.0 - beta * np.asarray(held, np.float64) / len(best), 0.0, None)

    _weighted_rank(weights_of)


def main(*, kind: str, value: float, beta: float, half: str, routes: str, methods: str, data: Path,
         json_out: Path | None) -> None:
    """Install variant `kind` (module docstring) and run `cortexloc eval slam` with these options."""
    if kind in ("idf", "local"):
        (idf(value, beta) if kind == "idf" else local(int(value), beta))

        def change(graph, seqs, scores, own_trail):
            return scores
    else:
        change = {"own": lambda: own(value), "contrast": lambda: contrast(int(value)),
                  "hub": lambda: hub(value, beta)}[kind]()
    step = loc.SequenceLocaliser.step

    def changed(self, state, graph, seqs, scores, own_trail=None, *rest, **kw):
        seqs, scores = np.asarray(seqs, np.int64), np.asarray(scores, np.float64)
        return step(self, state, graph, seqs, change(graph, seqs, scores, own_trail), own_trail, *rest, **kw)

    loc.SequenceLocaliser.step = changed
    from service.evaluation import slam

    slam.slam_runs(data=data, half=half, routes=routes, methods=methods, json_path=json_out,
                   localiser={"condition_frames": 0})

