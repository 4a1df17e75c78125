"""Odometry's word on a revisit (docs/design/science.md §11.12): within one drive of one stream, a row the
robot's own poses say it cannot be back at is no loop candidate.

Over one stretch of odometry the pose error grows with the path driven, not with time: after L metres a
pose is off by at most `odometry_drift` x L (wheel and visual odometry drift a few per cent of the distance)
plus `odometry_slack` metres (how far apart two views of one place may be taken). A row the stream made
L metres of path ago, whose pose lies farther from the frame's than that, is a place the robot has not
come back to, however alike it looks: the periodic doors of a straight corridor, a plateau driven
straight on. A true loop comes back near where its row's pose lies (a ring of 100 m, its start 0-20 m away
at 20 % drift), and passes. The rule only ever takes candidates away: where it cannot judge, it keeps them.

A **drive** (one odometry stretch, a `segment`) is what a stream's learned frames trace while each carries a
pose and a stamp, each stamp after the last by at most `odometry_gap` seconds and each step no faster than
`max_speed` (the short-term memory's reset, §11.6). A frame without a pose or stamp, a gap (the node
stopped, a robot powered off: its odometry may start again from zero), a stamp that goes back (a bag
replayed) or a jump ends the drive; the next posed frame starts another. Rows of another drive, of another
robot (two robots' odometry share no frame) or without a pose are never judged. `travelled` sums every
step of the drive, so a row's distance from the frame is at most the path between them.

The streams that name one trail are one robot's cameras (§11.6): their poses are the robot's, in its one
odometry frame, so a frame is judged against the rows of each of their live drives too (`Odometer.beside`:
the frame read as a step of that camera's drive). Without it two cameras of a robot driving faster than its
short-term memory covers in a few frames named each other's rows just behind it, an echo of where the
robot just was (an outside probe, through the ROS 2 node: every loop closure of a summer lap false).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from models.localisation.motion import Motion
from models.localisation.options import LocaliserOptions

__all__ = ["BESIDE_S", "JUMP", "NO_READING", "Odometer", "Reading", "RowOdometry"]

#: A step longer than `odometry_slack` and this many times the drive's last step ends the drive: an
#: odometry node restarted from zero within `odometry_gap` (a review's case: a 150 m jump after 1 m steps
#: vetoed a loop's true start), while a sparse but steady frame rate (a frame every 280 m) stays one drive.
JUMP = 3.0
#: Seconds apart, at most, that a frame and the last frame of another camera of its robot may be stamped
#: for the frame to be judged on that camera's drive (`Odometer.beside`): cameras that post together. A
#: camera that stopped while the robot drove on reads a path since its rows too short (its last step
#: spans the whole gap in a straight line), and would veto the robot's true loop (a review's case).
BESIDE_S = 2.0


class Reading(NamedTuple):
    """Where a stream's odometry stands at a learned frame: its `drive` (a number unique in the map; -1:
    none, the frame is not on a drive), the path `travelled` on it (m) and the pose (x, y)."""

    drive: int = -1
    travelled: float = 0.0
    x: float = 0.0
    y: float = 0.0


#: Not on a drive: nothing to judge by.
NO_READING = Reading()


class Odometer:
    """One stream's drive: its last posed learned frame's reading and stamp."""

    def __init__(self) -> None:
        self.reading = NO_READING
        self.stamp: float | None = None
        self.step: float | None = None  # the drive's last step (m); None at its start

    def peek(self, motion: Motion, conf: LocaliserOptions, new_drive: int) -> Reading:
        """The reading at a frame of this `motion`, this odometer unchanged; `new_drive` the number a drive
        that starts here gets. `conf`: the localiser options (`odometry_gap`, `max_speed`)."""
        if motion.pose is None or motion.stamp is None:
            return NO_READING
        x, y = motion.pose
        last = self.reading
        if last.drive >= 0 and self.stamp is not None:
            dt = motion.stamp - self.stamp
            step = math.hypot(x - last.x, y - last.y)
            # a step both longer than the slack and JUMP times the drive's last one is no drive's: an
            # odometry restarted from zero within the gap (a node restarted), not a sparse frame rate
            jump = self.step is not None and step > max(conf.odometry_slack, JUMP * self.step)
            if 0.0 < dt <= conf.odometry_gap and step <= conf.max_speed * dt and not jump:
                return Reading(last.drive, last.travelled + step, x, y)
            if dt == 0.0 and step == 0.0:  # the same stamp and pose again (a frame posted twice)
                return last
        return Reading(new_drive, 0.0, x, y)

    def beside(self, motion: Motion, conf: LocaliserOptions) -> Reading:
        """The reading at a frame of this `motion` taken by another camera of the same robot (a stream
        naming this odometer's stream's trail, §11.6), read on this odometer's drive, which it leaves
        unchanged: on it where the frame's stamp is within `BESIDE_S` of the drive's last, either way
        (the cameras post in either order), and its pose within `max_speed` x that of the drive's last
        pose plus `odometry_slack` (the cameras' mounts apart); `travelled` the drive's own plus the
        step where the frame is the later one, so the path since a row is never less than the drive's.
        NO_READING where the drive is over or the frame has no pose or stamp."""
        last = self.reading
        if motion.pose is None or motion.stamp is None or last.drive < 0 or self.stamp is None:
            return NO_READING
        x, y = motion.pose
        dt = motion.stamp - self.stamp
        step = math.hypot(x - last.x, y - last.y)
        if abs(dt) > min(BESIDE_S, conf.odometry_gap) or \
                step > conf.max_speed * abs(dt) + conf.odometry_slack:
            return NO_READING
        return Reading(last.drive, last.travelled + (step if dt > 0 else 0.0), x, y)

    def take(self, reading: Reading, stamp: float | None) -> None:
        """A learned frame's reading (`peek`'s) becomes the odometer's."""
        same = reading.drive >= 0 and reading.drive == self.reading.drive
        self.step = reading.travelled - self.reading.travelled if same else None
        self.reading, self.stamp = reading, stamp if reading.drive >= 0 else None


class RowOdometry:
    """Each row's reading when it was made (rows of no drive: -1), grown as rows are added: 32 bytes a
    row."""

    def __init__(self) -> None:
        self.drive = np.zeros(0, np.int64)
        self.at = np.zeros((0, 3), np.float64)  # travelled, x, y
        self.drives = 0  # drives started in this map, the next one's number

    def record(self, row: int, reading: Reading) -> None:
        if row >= self.drive.size:
            grow = max(row + 1, 2 * self.drive.size, 16) - self.drive.size
            self.drive = np.concatenate([self.drive, np.full(grow, -1, np.int64)])
            self.at = np.concatenate([self.at, np.zeros((grow, 3))])
        self.drive[row] = reading.drive
        self.at[row] = reading.travelled, reading.x, reading.y

    def beyond(self, rows: np.ndarray, here: Reading, drift: float, slack: float) -> np.ndarray:
        """(H,) bool: which of `rows` (H,) the stream at `here` cannot be back at (module docstring): made on
        its drive, farther from its pose than `drift` x the path since plus `slack` metres."""
        rows = np.asarray(rows, np.int64)
        out = np.zeros(rows.size, bool)
        if here.drive < 0 or not rows.size:
            return out
        known = rows < self.drive.size
        mine = np.zeros(rows.size, bool)
        mine[known] = self.drive[rows[known]] == here.drive
        if not mine.any():
            return out
        at = self.at[rows[mine]]
        path = np.maximum(here.travelled - at[:, 0], 0.0)
        gone = np.hypot(here.x - at[:, 1], here.y - at[:, 2])
        out[mine] = gone > drift * path + slack
        return out
