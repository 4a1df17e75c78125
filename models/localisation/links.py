"""A map's sequence localisation: the learned links, the localiser, and one stream's step
(docs/design/science.md §11, docs/design/service.md §1.2).

The map holds one `SequenceGraph` (each stored row's `context_prev_seq`, rebuilt from the store on
recovery, appended on every learned step) and one `SequenceLocaliser`; each stream holds its own
`LocaliserState` (`models.pipeline.state.Stream.localiser`, in snapshots). The step reads the candidates of
the inverted index's one pass for the frame's winner cells, so its cost does not grow with the map
beyond that pass (benchmarks/bench_index.py, docs/benchmarks.md).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from models.localisation.graph import SequenceGraph
from models.localisation.index import Match
from models.localisation.localiser import LocaliserState, Place, SequenceLocaliser
from models.localisation.trail import CodeStats, OwnTrail

__all__ = ["Localisation", "graph_from_rows"]


def graph_from_rows(rows: Iterable[Any]) -> SequenceGraph:
    """The links of stored rows (each with `seq` and `context_prev_seq`, in seq order): row id = seq."""
    graph = SequenceGraph()
    for row in rows:
        graph.append(int(row.seq), -1 if row.context_prev_seq is None else int(row.context_prev_seq))
    return graph


class Localisation:
    """The map's localiser and links (docs/design/science.md §11.1, §11.2, §11.6).

    Args:
        conf: localiser options over `models.localisation.default_conf` (the map's `localiser` params).
    """

    def __init__(self, conf: dict[str, Any] | None = None, code_width: int = 0) -> None:
        self.localiser = SequenceLocaliser(conf)
        self.graph = SequenceGraph()
        self.codes = CodeStats(code_width)  # the stored frame codes' bit counts (§11.6)
        self.top_k = int(self.localiser.conf["top_k"])

    def rebuild(self, rows: Iterable[Any]) -> None:
        """The links and code statistics of the store's rows (recovery)."""
        self.graph = SequenceGraph()
        self.codes.rebuild([])
        for row in rows:
            self.add(int(row.seq), row.context_prev_seq, row.input_sdr)

    def add(self, seq: int, prev: int | None, code: np.ndarray) -> None:
        """A row just learned, after `prev` (None: the start of a sequence), and its frame code."""
        self.graph.append(seq, -1 if prev is None else prev)
        self.codes.add(code)

    def candidates_wanted(self, top_k: int) -> int:
        """How many ranked rows one index pass must return for `top_k` matches and the localiser (whose
        candidates leave out up to `exclusion` of them: the stream's own rows behind those not left)."""
        return max(top_k, self.top_k + int(self.localiser.conf["exclusion"]))

    def new_state(self) -> LocaliserState:
        return self.localiser.new_state()

    def own_trail(self, state: LocaliserState, last_learned: int | None, code: np.ndarray,
                  code_of: Callable[[int], np.ndarray], informative: bool = True) -> OwnTrail | None:
        """The stream's own rows it has not left, after this frame (`SequenceLocaliser.own_trail`,
        docs/design/science.md §11.6): not candidates of the index pass, not states of the filter."""
        return self.localiser.own_trail(state, self.graph, last_learned, code, code_of, self.codes,
                                        informative)

    def step(self, state: LocaliserState, ranked: Sequence[Match], own: OwnTrail | None,
             informative: bool = True) -> Place | None:
        """One frame of one stream (docs/design/science.md §11.2), before this frame is stored.

        Args:
            state: the stream's localiser state, updated in place.
            ranked: the index's pass for the frame's winner cells, best first (Dice scores), without
                the rows the stream has not left; the localiser leaves out the rest of `own` and keeps
                its `top_k` best.
            own: the stream's own rows (`own_trail`). informative: False for a frame too flat to say
                where it is (`localiser.informative`, §11.7): no evidence, no revisit.

        Returns:
            The place, or None during warm-up.
        """
        seqs = np.fromiter((m.seq for m in ranked), np.int64, len(ranked))
        scores = np.fromiter((m.score for m in ranked), np.float64, len(ranked))
        return self.localiser.step(state, self.graph, seqs, scores, own, informative)
