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
