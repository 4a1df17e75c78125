"""The online sequence localiser run causally over a database/query similarity matrix.

docs/design/science.md §11.4: the database traverse is learned in order (row r's predecessor is r - 1),
then the query frames are fed one at a time, learning off; the answer for query frame j uses columns
<= j (in driven order) only. The `online-X` methods of `models.evaluation.sequences` are this on method
X's single-image similarity. `loop_closure` is the grid world's form (§2.4): one learning stream
localised against its own past steps.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from models.localisation import CodeStats, LocaliserOptions, SequenceGraph, SequenceLocaliser, top_candidates


class OnlineAnswers(NamedTuple):
    """The localiser's answers for n_q query frames in driven order against n_db database rows.

    Attributes:
        best: (n_q,) int64 answered row (-1: no answer yet, the warm-up).
        confidence: (n_q,) float64 in [0, 1] (0 where no answer).
        support: (n_q,) int64 frames behind each answer (0 where none).
        S: (n_db, n_q) the beam's path scores after each frame (best over both directions; -inf for rows
            outside the beam): the similarity matrix for R@5 and the all-pairs AUC.
    """

    best: np.ndarray
    confidence: np.ndarray
    support: np.ndarray
    S: np.ndarray


def localise(S: np.ndarray, conf: Mapping[str, Any] | None = None,
             graph: SequenceGraph | None = None) -> OnlineAnswers:
    """Run one stream of query frames through `SequenceLocaliser`, causally.

    Args:
        S: (n_db, n_q) single-image similarity, higher = more similar, columns in driven order.
        conf: localiser options over `models.localisation.default_conf`.
        graph: the database's links; default one traverse in row order (`SequenceGraph.chain`).
    """
    S = np.asarray(S, dtype=np.float64)
    n_db, n_q = S.shape
    loc = SequenceLocaliser(LocaliserOptions.of(conf))
    top_k = loc.options.top_k
    graph = SequenceGraph.chain(n_db) if graph is None else graph
    return _drive(loc, graph, n_db, n_q, lambda j: top_candidates(S[:, j], top_k))


def loop_closure(S: np.ndarray, codes: Sequence[np.ndarray], conf: Mapping[str, Any] | None = None,
                 width: int | None = None) -> OnlineAnswers:
    """One learning stream localised against its own past: the grid protocol (docs/design/science.md
    §2.4) and a robot mapping a route (§11.6), through the service's localiser and its own-trail rule.

    Step i is localised before it is stored: the map then holds steps 0 … i − 1, linked in order (row r's
    predecessor r − 1). As in the service (`service/maps/runtime/writer.py`), the stream's own rows it
    has not left (`SequenceLocaliser.own_trail`, measured on the steps' frame codes) are not candidates,
    nor rows of similarity <= 0 (the index returns only rows sharing a cell). Then step i joins the map. One
    stream, one state, no reset.

    Args:
        S: (T, T) single-image similarity of step j (rows) and step i (columns), higher = more similar;
            only entries j < i are read, so any symmetric matrix of causal descriptors (input SDRs, TM
            winner cells learned online) gives a causal answer.
        codes: T sorted index arrays, each step's frame code (its input SDR: what it looks like).
        conf: localiser options over `models.localisation.default_conf`.
        width: the codes' bit space (default: the largest index + 1).

    Returns:
        OnlineAnswers over T steps against T rows; S[j, i] is -inf unless j < i and j is in the beam.
    """
    S = np.asarray(S, dtype=np.float64)
    T = S.shape[0]
    if S.shape != (T, T) or len(codes) != T:
        raise ValueError(f"S must be square (T, T) with T codes, got {S.shape} and {len(codes)}")
    loc = SequenceLocaliser(LocaliserOptions.of(conf))
    top_k = loc.options.top_k
    codes = [np.unique(np.asarray(c, np.int64)) for c in codes]
    stats = CodeStats(width or 1 + max((int(c.max()) for c in codes if c.size), default=0))
    graph = SequenceGraph()
    state = loc.new_state()
    best, confidence = np.full(T, -1, np.int64), np.zeros(T)
    support, out = np.zeros(T, np.int64), np.full((T, T), -np.inf)
    for i in range(T):
        own = loc.own_trail(state, graph, i - 1 if i else None, codes[i], codes.__getitem__, stats)
        sims = S[:i, i].copy()
        if own is not None:
            sims[own.holds(graph, np.arange(i))] = -np.inf
        seqs, scores = top_candidates(sims, top_k)
        ok = scores > 0  # the index's min_overlap 1; -inf: the stream's own rows
        place = loc.step(state, graph, seqs[ok], scores[ok], own)
        live = state.rows >= 0
        np.maximum.at(out[:, i], state.rows[live], state.scores[live])
        if place is not None:
            best[i], confidence[i], support[i] = place.seq, place.confidence, place.support
        graph.append(i, i - 1 if i else -1)
        stats.add(codes[i])
    return OnlineAnswers(best, confidence, support, out)


def _drive(loc: SequenceLocaliser, graph: SequenceGraph, n_db: int, n_q: int,
           candidates: Callable[[int], tuple[np.ndarray, np.ndarray]]) -> OnlineAnswers:
    """One localising stream through `loc`: frame j's candidates (rows, scores) from `candidates(j)`."""
    state = loc.new_state()
    best = np.full(n_q, -1, np.int64)
    confidence = np.zeros(n_q)
    support = np.zeros(n_q, np.int64)
    out = np.full((n_db, n_q), -np.inf)
    for j in range(n_q):
        place = loc.step(state, graph, *candidates(j))
        live = state.rows >= 0
        np.maximum.at(out[:, j], state.rows[live], state.scores[live])
        if place is not None:
            best[j], confidence[j], support[j] = place.seq, place.confidence, place.support
    return OnlineAnswers(best, confidence, support, out)
