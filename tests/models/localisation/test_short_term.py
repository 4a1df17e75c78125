"""A stream's short-term memory (models/localisation/short_term.py, docs/design/science.md §11.6): the
rows made over its last moves, in fixed memory."""

from __future__ import annotations

import numpy as np

from models.localisation import Localisation, SequenceLocaliser
from models.localisation.graph import NONE
from models.localisation.short_term import KEPT, SPAN, ShortTerm

A, B = np.arange(10), np.arange(100, 110)  # two unlike codes (Dice 0)


def test_it_spans_moves_not_frames_and_a_consolidated_frame_is_a_move_without_a_row() -> None:
    m = ShortTerm(3)
    for row, code in [(1, A), (2, B), (3, B), (4, B), (NONE, A), (5, B)]:
        m.step(row, code, level=0.5)  # B after B is no move: rows 3 and 4 stay with row 2's move
    assert m.rows().tolist() == [2, 3, 4, 5]
    m.step(6, A, level=0.5)
    assert m.rows().tolist() == [5, 6]  # moves: row 6, row 5, the consolidated frame


def test_a_stop_keeps_the_rows_before_it_up_to_its_bound_and_the_ring_wraps() -> None:
    m = ShortTerm(2)
    m.step(1, A, 0.5)
    m.step(2, B, 0.5)
    for row in range(3, 3 + SPAN * 2 - 2):  # a stop: frames alike to the last move
        m.step(row, B, 0.5)
    assert m.rows()[0] == 1 and m.rows().size == SPAN * 2
    m.step(999, B, 0.5)  # one frame more than the ring holds: the oldest goes
    assert m.rows()[0] == 2 and m.rows()[-1] == 999


def test_the_map_keeps_the_memories_of_the_most_recently_learning_streams_and_counts_them() -> None:
    links = Localisation({}, 256)
    for k in range(KEPT + 5):
        links.add(k + 1, None, np.arange(k % 200, k % 200 + 8), stream=f"robot-{k}")
    assert links.short_term_rows("robot-0").size == 0  # the least recently learning ones went
    assert links.short_term_rows(f"robot-{KEPT + 4}").tolist() == [KEPT + 5]
    assert len(links._short) == KEPT
    with_memory, without = SequenceLocaliser({}), SequenceLocaliser({"short_term": 0})
    assert with_memory.stream_bytes(256) - without.stream_bytes(256) == 2 * ShortTerm.nbytes(20, 256)


def test_a_path_that_starts_just_behind_the_memory_is_followed_as_an_echo_and_one_farther_back_is_not():
    """`OwnTrail.born`: a path born within `margin` links behind the memory's oldest row, on the stream's
    trail, gets that row as its `born` (so `laid_behind` follows it as it walks on); a path born farther
    back (a loop a little longer than the memory, driven again in another season) keeps the map's row
    count, as every path did before the memory."""
    from models.localisation import SequenceGraph
    from models.localisation.trail import OwnTrail

    graph = SequenceGraph()
    for r in range(40):
        graph.append(r, r - 1 if r else -1)
    own = OwnTrail(first=30, here=40, last=39, trail=int(graph.trail[39])).with_short_term(np.arange(20, 40))
    born = own.born(graph, np.array([19, 16, 15, 14, 2, 25]), now=40, margin=5)
    assert born.tolist() == [20, 20, 20, 40, 40, 40]  # 19..15: 1-5 links behind; 14 and 2 farther
    assert OwnTrail.short_term_only(np.arange(20, 40)).born(graph, np.array([19]), 40, 5).tolist() == [40]
