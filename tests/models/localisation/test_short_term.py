"""A stream's short-term memory (models/localisation/short_term.py, docs/design/science.md §11.6): the
rows made over its last moves, in fixed memory."""

from __future__ import annotations

import numpy as np

from models.localisation import LocaliserOptions, PlaceMap, SequenceLocaliser
from models.localisation.graph import NONE
from models.localisation.motion import NO_MOTION, Motion
from models.localisation.short_term import KEPT, SLOTS, SPAN, Anchor, ShortTerm

A, B = np.arange(10), np.arange(100, 110)  # two unlike codes (Dice 0)


def feed(m: ShortTerm, anchor: Anchor, frames: list, conf: dict | None = None) -> None:
    """(row, code[, motion]) learned frames of one stream into memory `m`, departure level 0.5."""
    options = LocaliserOptions.of({"short_term": 3, **(conf or {})})
    for row, code, *motion in frames:
        m.add(row, anchor.move(code, 0.5, motion[0] if motion else NO_MOTION, options))


def test_it_spans_moves_not_frames_and_a_consolidated_frame_is_a_move_without_a_row() -> None:
    m, anchor = ShortTerm(3), Anchor()
    feed(m, anchor, [(1, A), (2, B), (3, B), (4, B), (NONE, A), (5, B)])
    # B after B is no move: rows 3 and 4 stay with row 2's move
    assert m.rows().tolist() == [2, 3, 4, 5]
    feed(m, anchor, [(6, A)])
    assert m.rows().tolist() == [5, 6]  # moves: row 6, row 5, the consolidated frame


def test_a_stop_keeps_the_rows_before_it_up_to_its_bound_and_the_ring_wraps() -> None:
    m, anchor = ShortTerm(2), Anchor()
    conf = {"short_term": 2}
    feed(m, anchor, [(1, A), (2, B)], conf)
    feed(m, anchor, [(row, B) for row in range(3, 3 + SPAN * 2 - 2)], conf)  # a stop: alike to the last move
    assert m.rows()[0] == 1 and m.rows().size == SPAN * 2
    feed(m, anchor, [(999, B)], conf)  # one frame more than the ring holds: the oldest goes
    assert m.rows()[0] == 2 and m.rows()[-1] == 999


def test_the_map_keeps_the_memories_of_the_most_recently_learning_streams_and_counts_them() -> None:
    place_map = PlaceMap(LocaliserOptions(), 256)
    for k in range(KEPT + 5):
        place_map.add(k + 1, None, np.arange(k % 200, k % 200 + 8), stream=f"robot-{k}")
    assert place_map.short_term_rows("robot-0").size == 0  # the least recently learning ones went
    assert place_map.short_term_rows(f"robot-{KEPT + 4}").tolist() == [KEPT + 5]
    assert len(place_map._short) == KEPT
    with_memory, without = SequenceLocaliser(), SequenceLocaliser(LocaliserOptions(short_term=0))
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
    # a slower robot's memory (3 rows a move: 60 rows) reaches a quarter of its rows back, 15 links
    for r in range(40, 100):
        graph.append(r, r - 1)
    slow = OwnTrail(first=90, here=100, last=99, trail=int(graph.trail[99]))
    slow = slow.with_short_term(np.arange(40, 100))
    assert slow.born(graph, np.array([39, 28, 25, 24]), now=100, margin=5).tolist() == [40, 40, 40, 100]


# ------------------------------------------------------------------ poses (issue 35: D metres of path)

def code(q: int) -> np.ndarray:
    """A code unlike every other q's: 12 random bits of 256."""
    return np.sort(np.random.default_rng(q).choice(256, 12, replace=False))


def learn(place_map: PlaceMap, frames: list, stream: str = "a", trail: str | None = None) -> None:
    """(seq, code, x or None, stamp or None) learned rows of `stream`, each after its last."""
    for seq, c, x, stamp in frames:
        motion = Motion(None if x is None else (float(x), 0.0), stamp, trail)
        place_map.add(seq, seq - 1 if seq > 1 else None, c, stream=stream, motion=motion)


def test_with_poses_a_robot_that_stands_with_noisy_frames_has_not_moved() -> None:
    """Every frame unlike the last (a busy scene, a noisy camera) is a move by appearance, so a robot
    standing for 100 frames fills its memory with 20 of them and the rows from before the stop leave it;
    with its pose (within `move_metres`) none is a move and the rows before the stop stay."""
    drive = [(q, code(q), float(q), None) for q in range(1, 31)]  # 30 m at 1 m a frame
    stand = [(q, code(q), 30 + 0.2 * np.sin(q), None) for q in range(31, 131)]
    posed, blind = PlaceMap(LocaliserOptions(), 256), PlaceMap(LocaliserOptions(), 256)
    learn(posed, drive + stand)
    learn(blind, [(q, c, None, t) for q, c, _, t in drive + stand])
    assert posed.short_term_rows("a").tolist() == list(range(11, 131))  # 20 m of drive, then the stop
    assert blind.short_term_rows("a").tolist() == list(range(111, 131))  # 20 moves, all of the stop


def test_with_poses_a_robot_that_moves_through_a_flat_stretch_has_moved_and_the_memory_is_d_metres() -> None:
    """The same code on every frame (a plateau, a bare corridor) is no move by appearance: the memory
    would hold the whole stretch. With poses each frame 2 m on is a move of 2 m, and the memory is the
    rows of the last `short_term_metres` of path."""
    flat = [(q, A, 2.0 * q, None) for q in range(1, 61)]
    for metres, held in ((20.0, 10), (40.0, 20), (0.0, 60)):  # 0: poses play no part
        place_map = PlaceMap(LocaliserOptions.of({"short_term_metres": metres}), 256)
        learn(place_map, flat)
        assert place_map.short_term_rows("a").tolist() == list(range(61 - held, 61)), metres


def test_a_step_faster_than_max_speed_is_a_reset_judged_by_appearance_that_keeps_the_memory() -> None:
    """A relocalisation (a pose 970 m away 1 s later) is no path: the memory keeps the rows of the 20 m
    driven before it and goes on from the new pose; taken as distance it would have emptied it. The
    pose cannot say how far the robot went, so the step is judged by appearance: the same view is no
    move, another view one move (1 / `short_term` of the memory, 1 m at the defaults)."""
    drive = [(q, code(q), float(q), float(q)) for q in range(1, 31)]  # 1 m/s
    place_map, still = PlaceMap(LocaliserOptions(), 256), PlaceMap(LocaliserOptions(), 256)
    fast = PlaceMap(LocaliserOptions(max_speed=1e4), 256)
    learn(place_map, [*drive, (31, code(31), 1000.0, 31.0)])
    learn(fast, [*drive, (31, code(31), 1000.0, 31.0)])
    learn(still, [*drive, (31, code(30), 1000.0, 31.0)])  # the estimate jumped, the view did not
    assert place_map.short_term_rows("a").tolist() == list(range(12, 32))  # one move by appearance
    assert still.short_term_rows("a").tolist() == list(range(11, 32))  # no move
    assert fast.short_term_rows("a").tolist() == [31]  # 970 m of "path" in one move
    learn(place_map, [(32, code(32), 1001.0, 32.0)])  # 1 m on from the new pose: a move of 1 m
    assert place_map.short_term_rows("a").tolist() == list(range(13, 33))


def test_a_bag_played_faster_than_max_speed_still_ages_its_memory_by_appearance() -> None:
    """Every step reads as a reset (10 m a frame at 10 frames a second: 100 m/s): the memory must not
    stop ageing, or no loop would ever close; each step is judged by appearance (20 moves at the
    defaults)."""
    place_map = PlaceMap(LocaliserOptions(), 256)
    learn(place_map, [(q, code(q), 10.0 * q, 0.1 * q) for q in range(1, 61)])
    assert place_map.short_term_rows("a").tolist() == list(range(41, 61))


def test_stamps_that_jump_back_reset_and_a_clock_step_forward_takes_the_step_as_it_is() -> None:
    """A bag replayed in a loop: the stamp goes back with the pose, no speed can be read (Δt <= 0) and a
    step of `move_metres` or more is a reset. Repeated stamps with a short step (stamps coarser than the
    frame rate) are no reset. A clock stepped forward (an hour) only loosens the speed check of its step."""
    place_map = PlaceMap(LocaliserOptions(), 256)
    learn(place_map, [(q, code(q), float(q), 100.0 + q) for q in range(1, 31)])
    learn(place_map, [(31, code(31), 0.0, 101.0)])  # the bag again from its start
    # no 30 m of path: a reset, another view (a move by appearance)
    assert place_map.short_term_rows("a").tolist() == list(range(12, 32))
    learn(place_map, [(32, code(32), 0.5, 101.0)])  # the same stamp, half a metre: no move, no reset
    assert place_map.short_term_rows("a").tolist() == list(range(12, 33))
    learn(place_map, [(33, code(33), 1.5, 3701.0)])  # an hour later by the clock, 1.5 m from the anchor
    assert place_map.short_term_rows("a").tolist() == list(range(13, 34))  # 1.5 m of path: row 12 leaves
    # without stamps a jump cannot be told from a drive: it is distance
    blind = PlaceMap(LocaliserOptions(), 256)
    learn(blind, [(q, code(q), float(q), None) for q in range(1, 31)] + [(31, code(31), 500.0, None)])
    assert blind.short_term_rows("a").tolist() == [31]


def test_frames_without_a_pose_in_a_stream_that_had_poses_move_by_appearance() -> None:
    place_map = PlaceMap(LocaliserOptions(), 256)
    learn(place_map, [(q, code(q), float(q), None) for q in range(1, 31)])
    learn(place_map, [(q, code(q), None, None) for q in range(31, 36)])  # unlike each other: 5 moves of 1/20
    learn(place_map, [(q, B, None, None) for q in range(36, 41)])  # a move, then alike to it: no moves
    # 6 appearance moves (1/20 each, 1 m at the defaults) + 14 m of path: rows 17-30 of the drive stay
    assert place_map.short_term_rows("a").tolist() == list(range(17, 41))
    learn(place_map, [(41, A, 300.0, None)])  # a pose again, its anchor had none: by appearance (A unlike B)
    learn(place_map, [(42, A, 302.0, None)])  # then by pose: 2 m
    assert place_map.short_term_rows("a").tolist() == list(range(20, 43))  # 3 m more


def test_two_streams_that_name_one_trail_share_its_memory_over_d_metres_of_path() -> None:
    """Two cameras of one robot (`metadata.trail`): the trail's memory holds both streams' rows of the
    last 20 m (each covers the path on its own: not 10 m), and neither stream has one of its own. A
    renamed node (`rear` goes on alone) ages the trail's memory with its own moves."""
    place_map = PlaceMap(LocaliserOptions(), 256)
    for q in range(1, 61):  # front: odd seqs, rear: even seqs, at x = 1 m per pair
        learn(place_map, [(q, code(q), float((q + 1) // 2), None)], stream="front" if q % 2 else "rear",
              trail="robot")
    assert place_map.short_term_rows("robot").tolist() == list(range(22, 61))  # rear's 20th metre back: 22
    assert place_map.short_term_rows("front").size == place_map.short_term_rows("rear").size == 0
    renamed = [(q, code(q), float(q - 30), None) for q in range(61, 81)]
    learn(place_map, renamed[:10], stream="node2", trail="robot")  # 10 m: the old names' 20 m stay
    assert place_map.short_term_rows("robot").tolist() == list(range(22, 71))
    learn(place_map, renamed[10:], stream="node2", trail="robot")
    assert place_map.short_term_rows("robot").tolist() == list(range(61, 81))  # its own 20 m


def test_a_ninth_stream_on_a_trail_never_takes_the_evicted_stream_s_frames_as_its_own() -> None:
    """`SLOTS` streams a trail tells apart: a ninth takes the least recently learning one's slot; the
    evicted stream's rows are no one's (they stay in the memory), never the ninth's look-back."""
    place_map = PlaceMap(LocaliserOptions(), 256)
    for i in range(SLOTS):
        learn(place_map, [(i + 1, code(i + 1), float(i), None)], stream=f"cam{i}", trail="robot")
    learn(place_map, [(SLOTS + 1, code(SLOTS + 1), 100.0, None)], stream="late", trail="robot")
    memory = place_map._short["robot"]
    assert memory.ages("late") == {SLOTS + 1: 0}  # cam0's row 1 is not its own
    assert memory.ages("cam0") == {}
    assert 1 in place_map.short_term_rows("robot").tolist()  # and it stays in the memory


def test_a_rebuild_from_the_stored_metadata_gives_the_same_memories() -> None:
    """Recovery: rows and visits replayed with the motion of their stored metadata give each trail the
    memory the live map had (poses, stamps with a reset, a shared trail, consolidated frames)."""
    live = PlaceMap(LocaliserOptions(), 256)
    rows, visits = [], []
    for q in range(1, 61):
        stream, x = ("front" if q % 3 else "rear"), (float(q) if q != 40 else 900.0)
        meta = {"pose": {"x": x, "y": 0.0, "yaw": 0.1}, "stamp": float(q), "trail": "robot"}
        if q == 50:
            meta.pop("pose")
        live.add(q, q - 1 if q > 1 else None, code(q), stream=stream, motion=Motion.of(meta))
        rows.append(type("Row", (), {"seq": q, "context_prev_seq": q - 1 if q > 1 else None, "place": None,
                                     "input_sdr": code(q), "stream": stream, "metadata": meta})())
    for k in range(5):  # consolidated frames of another stream, 3 m apart, into rows 1..5
        meta = {"pose": {"x": 3.0 * k, "y": 5.0}, "stamp": 70.0 + k}
        visit = (60 if k == 0 else k, k + 1, 61, "b", code(100 + k), Motion.of(meta))
        live.visit(*visit)
        visits.append(visit)
    again = PlaceMap(LocaliserOptions(), 256)
    again.rebuild(rows, visited=visits)
    for trail in ("robot", "b", "front"):
        assert again.short_term_rows(trail).tolist() == live.short_term_rows(trail).tolist()
    assert live.short_term_rows("robot").size >= 19
