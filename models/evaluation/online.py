"""The online sequence localiser run causally over a database/query similarity matrix.

docs/design/science.md §11.4: the database traverse is learned in order (row r's predecessor is r - 1),
then the query frames are fed one at a time, learning off; the answer for query frame j uses columns
<= j (in driven order) only. The `online-X` methods of `models.evaluation.sequences` are this on method
X's single-image similarity.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from models.localisation import SequenceGraph, SequenceLocaliser, top_candidates


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
    graph = SequenceGraph.chain(n_db) if graph is None else graph
    loc = SequenceLocaliser(conf)
    state = loc.new_state()
    k = int(loc.conf["top_k"])
    best = np.full(n_q, -1, np.int64)
    confidence = np.zeros(n_q)
    support = np.zeros(n_q, np.int64)
    out = np.full((n_db, n_q), -np.inf)
    for j in range(n_q):
        place = loc.step(state, graph, *top_candidates(S[:, j], k))
        live = state.rows >= 0
        np.maximum.at(out[:, j], state.rows[live], state.scores[live])
        if place is not None:
            best[j], confidence[j], support[j] = place
    return OnlineAnswers(best, confidence, support, out)
