"""A map's sequence localisation: the learned links, the localiser, and one stream's step
(docs/design/science.md §11, docs/design/service.md §1.2).

The map holds one `SequenceGraph` (each stored row's `context_prev_seq`, rebuilt from the store on
recovery, appended on every learned step) and one `SequenceLocaliser`; each stream holds its own
`LocaliserState` (`models.pipeline.state.Stream.localiser`, in snapshots). The step reads the candidates of
the inverted index's one pass for the frame's winner cells, so its cost does not grow with the map
beyond that pass (benchmarks/bench_index.py, docs/benchmarks.md).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from models.localisation.graph import SequenceGraph
from models.localisation.index import Match
from models.localisation.localiser import LocaliserState, Place, SequenceLocaliser

__all__ = ["Localisation", "graph_from_rows"]


def graph_from_rows(rows: Iterable[Any]) -> SequenceGraph:
    """The links of stored rows (each with `seq` and `context_prev_seq`, in seq order): row id = seq."""
    graph = SequenceGraph()
    for row in rows:
        graph.append(int(row.seq), -1 if row.context_prev_seq is None else int(row.context_prev_seq))
    return graph


class Localisation:
    """The map's localiser and links (docs/design/science.md §11.1, §11.2).

    Args:
        conf: localiser options over `models.localisation.default_conf` (the map's `localiser` params).
    """

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        self.localiser = SequenceLocaliser(conf)
        self.graph = SequenceGraph()
        self.top_k = int(self.localiser.conf["top_k"])
        # A learning stream's own last rows would always be its best candidates (the frame before this
        # one, just stored); they are left out, as far back as the rival window reaches.
        self.own_recent = int(self.localiser.conf["exclusion"])

    def rebuild(self, rows: Iterable[Any]) -> None:
        """The links of the store's rows (recovery)."""
        self.graph = graph_from_rows(rows)

    def add(self, seq: int, prev: int | None) -> None:
        """A row just learned, after `prev` (None: the start of a sequence)."""
        self.graph.append(seq, -1 if prev is None else prev)

    def candidates_wanted(self, top_k: int, learn: bool) -> int:
        """How many ranked rows one index pass must return for `top_k` matches and the localiser."""
        return max(top_k, self.top_k + (self.own_recent if learn else 0))

    def new_state(self) -> LocaliserState:
        return self.localiser.new_state()

    def step(self, state: LocaliserState, ranked: Sequence[Match], last_learned: int | None,
             learn: bool) -> Place | None:
        """One frame of one stream (docs/design/science.md §11.2), before this frame is stored.

        Args:
            state: the stream's localiser state, updated in place.
            ranked: the index's pass for the frame's winner cells, best first (Dice scores).
            last_learned: the stream's last stored row; with `learn`, it and the `own_recent` rows
                before it are not candidates.
            learn: the frame is being learned.

        Returns:
            The place, or None during warm-up.
        """
        own: set[int] = set()
        if learn and last_learned is not None:
            back = np.full(self.own_recent + 1, -1, np.int64)
            back[0] = last_learned
            for i in range(1, back.size):
                back[i] = self.graph.prev[back[i - 1]] if back[i - 1] >= 0 else -1
            own = {int(r) for r in back if r >= 0}
        kept = [m for m in ranked if m.seq not in own][:self.top_k]
        seqs = np.fromiter((m.seq for m in kept), np.int64, len(kept))
        scores = np.fromiter((m.score for m in kept), np.float64, len(kept))
        return self.localiser.step(state, self.graph, seqs, scores)
