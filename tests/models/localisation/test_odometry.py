"""Odometry's word on a revisit (docs/design/science.md §11.12): within one drive of one stream, rows its
poses say it cannot be back at are judged beyond; everything else is kept."""

from __future__ import annotations

import numpy as np

from models.localisation import PlaceMap
from models.localisation.motion import Motion
from models.localisation.odometry import NO_READING, Odometer, Reading, RowOdometry
from models.localisation.options import LocaliserOptions

CONF = LocaliserOptions()  # drift 0.2, slack 5 m, gap 60 s, max speed 50 m/s


def _drive(poses: list[tuple[float, float]],
           stamps: list[float] | None = None) -> tuple[RowOdometry, Odometer]:
    """Rows 1.. made at `poses` (1 s apart unless `stamps`) by one stream; its odometer after them."""
    rows, odo = RowOdometry(), Odometer()
    for i, (x, y) in enumerate(poses):
        stamp = float(i) if stamps is None else stamps[i]
        r = odo.peek(Motion((x, y), stamp), CONF, rows.drives)
        rows.drives += r.drive == rows.drives
        odo.take(r, stamp)
        rows.record(i + 1, r)
    return rows, odo


def test_on_a_straight_drive_rows_more_than_the_drift_and_slack_behind_are_beyond():
    rows, odo = _drive([(float(x), 0.0) for x in range(41)])  # rows 1..41 at x = 0..40
    here = odo.reading
    assert here.travelled == 40.0
    beyond = rows.beyond(np.arange(1, 42), here, 0.2, 5.0)
    # a row p metres behind: p > 0.2 p + 5, i.e. more than 6.25 m back
    assert beyond.tolist() == [40.0 - x > 6.25 for x in range(41)]


def test_a_loop_back_near_its_start_keeps_the_start_within_the_drift():
    side = [(float(x), 0.0) for x in range(25)] + [(25.0, float(y)) for y in range(25)] + \
        [(25.0 - x, 25.0) for x in range(25)] + [(0.0, 25.0 - y) for y in range(25)]
    rows, odo = _drive([*side, (3.0, 4.0)])  # back 5 m from the start after 104 m: drift 5 %
    here = odo.reading
    assert not rows.beyond(np.array([1]), here, 0.2, 5.0)[0]
    # the far side of the square is beyond: 25+ m away after some 50 m of path
    assert rows.beyond(np.array([51]), here, 0.2, 5.0)[0]


def test_a_gap_a_stamp_back_a_jump_or_a_frame_without_pose_or_stamp_starts_another_drive():
    base = [(float(x), 0.0) for x in range(30)]
    for case, motion in {"gap": Motion((30.0, 0.0), 29.0 + 61.0), "back": Motion((30.0, 0.0), 10.0),
                         "jump": Motion((30.0 + 5000.0, 0.0), 30.0), "no pose": Motion(None, 30.0),
                         # odometry restarted from zero within the gap, slower than max_speed allows
                         "restart": Motion((0.0, 0.0), 31.0),
                         "no stamp": Motion((30.0, 0.0), None)}.items():
        rows, odo = _drive(base)
        r = odo.peek(motion, CONF, rows.drives)
        assert r.drive in (rows.drives, -1), case  # a new drive (or none): nothing behind it is judged
        assert not rows.beyond(np.arange(1, 31), r, 0.2, 5.0).any(), case
    rows, odo = _drive(base)
    on = odo.peek(Motion((30.0, 0.0), 30.0), CONF, rows.drives)
    assert on.drive == 0 and on.travelled == 30.0  # the drive goes on
    assert odo.peek(Motion((29.0, 0.0), 29.0), CONF, 7).drive == 0  # the same frame posted again


def test_rows_of_no_drive_or_of_another_stream_s_drive_are_never_judged():
    rows, odo = _drive([(float(x), 0.0) for x in range(30)])
    other = Reading(drive=rows.drives, travelled=500.0, x=1000.0, y=0.0)  # another stream's drive
    assert not rows.beyond(np.arange(1, 31), other, 0.2, 5.0).any()
    assert not rows.beyond(np.arange(1, 31), NO_READING, 0.2, 5.0).any()
    assert not rows.beyond(np.array([500]), odo.reading, 0.2, 5.0).any()  # a row it never recorded


def test_the_map_judges_a_streams_frame_by_its_drive_and_a_rebuild_gives_the_same_readings():
    loc = PlaceMap(CONF, 64)
    code = np.arange(8, dtype=np.int64)
    assert loc.beyond("robot", Motion((0.0, 0.0), 0.0)) is None  # nothing learned yet
    prev = None
    for i in range(1, 31):
        loc.add(i, prev, code + i, stream="robot", motion=Motion((float(i), 0.0), float(i)))
        prev = i
    judge = loc.beyond("robot", Motion((31.0, 0.0), 31.0))
    assert judge is not None and judge(np.array([1, 29, 30])).tolist() == [True, False, False]
    assert loc.beyond("query", Motion((31.0, 0.0), 31.0)) is None  # another stream: no word
    assert loc.beyond("robot", Motion((31.0, 0.0), 31.0 + 600.0)) is None  # after a gap: no word

    class Row:
        def __init__(self, seq: int) -> None:
            self.seq, self.context_prev_seq, self.stream = seq, seq - 1 or None, "robot"
            self.input_sdr = code + seq
            self.metadata = {"pose": {"x": float(seq), "y": 0.0}, "stamp": float(seq)}

    again = PlaceMap(CONF, 64)
    again.rebuild([Row(s) for s in range(1, 31)])
    assert np.array_equal(again.odometry.drive[:31], loc.odometry.drive[:31])
    assert np.array_equal(again.odometry.at[:31], loc.odometry.at[:31])
    judge_again = again.beyond("robot", Motion((31.0, 0.0), 31.0))
    assert judge_again is not None and judge_again(np.array([1, 29, 30])).tolist() == [True, False, False]


def test_a_robots_other_camera_is_judged_by_each_live_drive_of_its_trail():
    # Two cameras of one robot name one trail (§11.6): their poses are the robot's, so a rear frame on its
    # own drive is judged against the front camera's drive too, where that camera posts beside it.
    loc = PlaceMap(CONF, 256)
    code = np.arange(8, dtype=np.int64)
    prev = None
    for i in range(1, 31):  # the front camera, 1 m a second
        loc.add(i, prev, code + i, stream="front", motion=Motion((float(i), 0.0), float(i), "robot"))
        prev = i
    for row, x in ((31, 29.5), (32, 30.5)):  # the rear camera's first frames: its own drive
        loc.add(row, None if row == 31 else 31, code + 100 + row, stream="rear",
                motion=Motion((x, 0.0), x, "robot"))
    rear = loc.beyond("rear", Motion((31.0, 0.0), 31.0, "robot"))
    assert rear is not None and rear(np.array([1, 29, 30, 31])).tolist() == [True, False, False, False]
    front_rows = np.arange(1, 31)
    for motion, case in ((Motion((31.0, 0.0), 31.0 + 61.0, "robot"), "its own drive is over (a gap)"),
                         (Motion((5000.0, 0.0), 31.0, "robot"), "a jump: its odometry restarted"),
                         (Motion((31.0, 0.0), None, "robot"), "no stamp")):
        assert loc.beyond("rear", motion) is None, case
    for motion, case in ((Motion((31.0, 0.0), 33.5, "robot"), "the front camera has not posted for 3 s"),
                         (Motion((31.0, 0.0), 31.0, "other"), "another robot's trail"),
                         (Motion((31.0, 0.0), 31.0), "its own trail")):
        judge = loc.beyond("rear", motion)
        assert judge is not None and not judge(front_rows).any(), case  # its own rows only
    assert loc.beyond("renamed", Motion((31.0, 0.0), 31.0, "robot")) is None  # no drive of its own yet
    # a frame stamped before the front's last (the cameras post in either order) is judged too, and a
    # loop back near the front's first row after a long path keeps it
    early = loc.beyond("rear", Motion((30.8, 0.0), 30.9, "robot"))
    assert early is not None and early(np.array([1, 28])).tolist() == [True, False]
    loop = PlaceMap(CONF, 256)
    side = [(float(x), 0.0) for x in range(25)] + [(25.0, float(y)) for y in range(25)] + \
        [(25.0 - x, 25.0) for x in range(25)] + [(0.0, 25.0 - y) for y in range(25)]
    prev = None
    for i, pose in enumerate(side, start=1):
        loop.add(i, prev, code + i, stream="front", motion=Motion(pose, float(i), "robot"))
        prev = i
    loop.add(101, None, code + 150, stream="rear", motion=Motion((1.0, 3.0), 100.0, "robot"))
    back = loop.beyond("rear", Motion((3.0, 4.0), 101.0, "robot"))
    assert back is not None and back(np.array([1, 51])).tolist() == [False, True]


def test_a_steady_sparse_frame_rate_is_one_drive_and_a_jump_after_short_steps_is_not():
    rows, odo = _drive([(280.0 * i, 0.0) for i in range(6)], stamps=[10.0 * i for i in range(6)])
    assert set(rows.drive[1:7].tolist()) == {0} and odo.reading.travelled == 1400.0  # a frame every 280 m
    rows, odo = _drive([(float(x), 0.0) for x in range(10)] + [(40.0, 0.0)])  # 1 m steps, then 31 m in 1 s
    assert rows.drive[10] == 0 and rows.drive[11] == 1  # the jump starts another drive
