"""Merges made from a stream's own recent trail, found again in a log (models/localisation/repair.py,
docs/design/science.md §11.6)."""

from __future__ import annotations

import dataclasses

import numpy as np

from models.localisation.motion import Motion
from models.localisation.options import LocaliserOptions
from models.localisation.repair import GRACE, Learned, Named, Pruned, own_trail_merges, window


def code(k: int) -> np.ndarray:
    return np.arange(8 * k, 8 * k + 8)  # unlike every other k (Dice 0): each learned frame is a move


def rows(stream: str, seqs: range, first_code: int = 0) -> list[Learned]:
    return [Learned(stream, s, code(first_code + i), made=True, ref=s) for i, s in enumerate(seqs)]


def test_a_visit_into_the_streams_own_recent_rows_is_a_merge_one_older_or_another_streams_is_not():
    log = [*rows("a", range(1, 11)),  # a: rows 1..10
           Learned("a", 8, code(40), made=False, ref=101),  # 3 moves back: within a memory of 4 moves
           Learned("a", 2, code(41), made=False, ref=102),  # far behind
           Learned("b", 10, code(42), made=False, ref=103)]  # another stream's visit into a's row
    found = own_trail_merges(log, LocaliserOptions(short_term=4), 512)
    assert found.visits == [101] and found.joins == [] and found.closures == []


def test_a_row_that_joined_a_place_through_its_own_recent_row_and_a_closure_naming_one_are_merges():
    log = [*rows("a", range(1, 6)),
           Named(1, "a", 4),  # a names its own row 4: an echo
           Learned("a", 6, code(20), made=True, through=(4, 4), ref=6),  # and joins its place
           Named(2, "b", 5),  # b names a's row: a loop for b
           Named(3, "a", 1, into=5),  # logged with a visit into a's own row 5
           Learned("a", 7, code(21), made=True, through=(1,), ref=7)]  # joined a place far behind
    found = own_trail_merges(log, LocaliserOptions(short_term=3), 512)
    assert found.joins == [6] and found.closures == [1, 3] and found.visits == []


def test_frames_alike_are_no_moves_so_a_stop_stays_recent_however_many_frames_it_lasts():
    stop = [Learned("a", s, code(1), made=True, ref=s) for s in range(2, 60)]  # a parked robot: one code
    log = [Learned("a", 1, code(0), made=True, ref=1), *stop, Learned("a", 3, code(1), made=False, ref=9)]
    assert own_trail_merges(log, LocaliserOptions(short_term=2), 512).visits == [9]


def test_a_map_without_a_memory_is_judged_by_the_default_window():
    assert window(LocaliserOptions(short_term=0)) == window(LocaliserOptions()) == 20
    assert window(LocaliserOptions(short_term=5)) == 5
    log = [*rows("a", range(1, 16)), Learned("a", 3, code(50), made=False, ref=7)]  # 12 moves back
    assert own_trail_merges(log, LocaliserOptions(short_term=0), 512).visits == [7]
    assert own_trail_merges(log, LocaliserOptions(short_term=5), 512).visits == []


def test_a_log_that_lost_steps_judges_nothing_before_its_mark_and_a_stream_only_past_its_grace():
    # An outside probe: with the visit log pruned, a repair read a second lap's true closures as echoes.
    # Lap 1 makes rows 1-6; lap 2's frames were visits of them (moves, pruned); closure 1 names row 3 from
    # lap 2, after the stream moved on: no echo. Rebuilt without the visits, row 3 still looks recent.
    before = [*rows("a", range(1, 7)), Named(1, "a", 3, into=3)]
    opts = LocaliserOptions(short_term=4, short_term_metres=0.0)  # a grace of GRACE x 4 moves past the mark
    early = [Learned("a", 4, code(30), made=False, ref=201),  # the oldest visit kept: another lap's
             *rows("a", range(7, 9), first_code=40),
             Named(2, "a", 8, into=8), Learned("a", 8, code(50), made=False, ref=202)]  # an echo, too early
    late = [*rows("a", range(9, 9 + GRACE * 4), first_code=60),
            Named(3, "a", 15, into=15), Learned("a", 15, code(90), made=False, ref=203),  # an echo, judged
            Named(4, "a", 2)]  # row 2 was made before the mark: not told, so not a merge
    stale = own_trail_merges([*before, *early, *late], opts, 2048)
    assert 1 in stale.closures  # what the repair did: the true closure read as an echo
    found = own_trail_merges([*before, Pruned(), *early, *late], opts, 2048, pruned=True)
    assert found.closures == [3] and found.visits == [203]


def test_past_the_mark_a_first_frame_alike_to_the_lost_last_move_reads_no_true_closure_as_an_echo():
    # A review: the pruned steps held the stream's last move; rebuilt without it, the first frame after the
    # mark is a move where the stream's was none, and the rebuilt memory reached a frame further back.
    opts = LocaliserOptions(short_term=3)
    old = rows("a", range(1, 5))
    def alike(k: int) -> np.ndarray:  # codes of one place seen again, k bits on from the first
        return np.arange(2400 + k, 2400 + k + 8)

    lost = Learned("a", 2, alike(0), made=False, ref=900)  # the last (pruned) visit: the stream's last move

    for shift in range(1, 8):
        after = [Learned("a", 5, alike(shift), made=True, ref=5),
                 Learned("a", 6, alike(2 * shift), made=True, ref=6),
                 *rows("a", range(7, 9), first_code=70), Named(1, "a", 5)]
        live = own_trail_merges([*old, lost, *after], opts, 4096).closures
        rebuilt = own_trail_merges([*old, Pruned(), *after], opts, 4096, pruned=True).closures
        assert set(rebuilt) <= set(live), shift


def test_a_stream_that_names_a_trail_is_judged_on_that_trail_and_shares_it_with_its_other_cameras():
    """The memory is the trail's (`metadata.trail`), as the live map keeps it: a stream naming one is
    judged as one that names none, and a robot's two cameras naming one trail share it."""
    def naming(trail: str, log: list) -> list:
        return [dataclasses.replace(e, motion=Motion(trail=trail)) if isinstance(e, Learned) else e
                for e in log]

    log = [*rows("a", range(1, 6)),
           Named(1, "a", 4),  # an echo of a's own row 4
           Learned("a", 6, code(20), made=True, through=(4, 4), ref=6),
           Learned("a", 5, code(21), made=False, ref=101)]  # a visit into its own row 5
    bare = own_trail_merges(log, LocaliserOptions(short_term=3), 512)
    assert (bare.visits, bare.joins, bare.closures) == ([101], [6], [1])
    for trail in ("a", "robot"):
        found = own_trail_merges(naming(trail, log), LocaliserOptions(short_term=3), 512)
        assert (found.visits, found.joins, found.closures) == ([101], [6], [1]), trail
    # the rear camera names the front's trail: its visit into a front row of a moment ago is a merge;
    # naming none (another trail), it is a loop
    robot = Motion(trail="robot")
    front = [dataclasses.replace(e, motion=robot) for e in rows("front", range(1, 6))]
    for trail, merges in (("robot", [102]), (None, [])):
        rear = Learned("rear", 5, code(30), made=False, ref=102, motion=Motion(trail=trail))
        assert own_trail_merges([*front, rear], LocaliserOptions(short_term=3), 512).visits == merges
