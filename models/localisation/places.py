"""A map's places (`PlaceMap`): the learned links, each row's place, the localiser, and one stream's step
(docs/design/science.md §11, docs/design/service.md §1.2).

The map holds one `SequenceGraph` (each stored row's `context_prev_seq`, rebuilt from the store on
recovery, appended on every learned step) and one `SequenceLocaliser`; each stream holds its own
`LocaliserState` (`models.pipeline.state.Stream.localiser`, in snapshots). The step reads the candidates of
the inverted index's one pass for the frame's winner cells, so its cost does not grow with the map
beyond that pass (benchmarks/bench_index.py, docs/benchmarks.md).
"""

from __future__ import annotations

import copy
import itertools
import math
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, NamedTuple, TypeVar

import numpy as np

from models.localisation.graph import NONE, SequenceGraph
from models.localisation.index import Match
from models.localisation.localiser import LocaliserState, Place, SequenceLocaliser, flat_share
from models.localisation.localiser import informative as is_informative
from models.localisation.motion import NO_MOTION, Motion
from models.localisation.odometry import Odometer, RowOdometry
from models.localisation.options import LocaliserOptions
from models.localisation.short_term import KEPT, Anchor, ShortTerm, View, ring_moves
from models.localisation.trail import CodeStats, OwnTrail, code_dice

__all__ = ["Explained", "PlaceMap", "graph_from_rows"]

T = TypeVar("T")


def graph_from_rows(rows: Iterable[Any]) -> SequenceGraph:
    """The links of stored rows (each with `seq` and `context_prev_seq`, in seq order): row id = seq."""
    graph = SequenceGraph()
    for row in rows:
        graph.append(int(row.seq), -1 if row.context_prev_seq is None else int(row.context_prev_seq))
    return graph


#: How many links a warm-up join looks either side of the row the confident path stood on when a row was
#: made (`PlaceMap.explained`): the path may have stood still or skipped a row on the way (a move of 0 or
#: 2, §11.2); a neighbour beyond that is another place by the truth's tolerance (§11.4) twice over.
JOIN_SLACK = 1


class Explained(NamedTuple):
    """The warm-up joins one confident frame gives (`PlaceMap.explained`, docs/design/science.md §11.8):
    (row, old row) each. `joins`: the old row represents the row, which is then held no more; `kept`: no
    row there represents it, an appearance of the place of the old row (the row the path stood on) is
    like it, and it stays, a new appearance of that place."""

    joins: list[tuple[int, int]]
    kept: list[tuple[int, int]]


class PlaceMap:
    """The map's localiser, links and places (docs/design/science.md §11.1, §11.2, §11.6, §11.8, §11.9).

    Args:
        options: the map's localiser options (default: the defaults).
        code_width: the frame code's bit space (the code statistics, §11.6).

    Attributes:
        used: (seq,) int64 when each row was last used (made, visited, or the place a learning stream's
            new row joined): the seq-space clock, -1 for rows not held; the drop and forgetting rules
            read it (§11.9).
        flat: (seq,) bool whether each row's frame was flat (under `MIN_CONTRAST`, §11.7): a later flat
            frame whose path names its place, or a neighbouring one, is a visit of it (`consolidation`).
    """

    def __init__(self, options: LocaliserOptions | None = None, code_width: int = 0) -> None:
        self.localiser = SequenceLocaliser(options)
        self.options = self.localiser.options
        self.graph = SequenceGraph()
        self.codes = CodeStats(code_width)  # the stored frame codes' bit counts (§11.6, §11.8)
        self.looks = CodeStats(code_width)  # one code a move of its maker: the departure level's (§11.6)
        self.top_k = int(self.options.top_k)
        self.short_term = ring_moves(self.options)  # the memories' size in moves (0: none)
        self.used = np.zeros(0, np.int64)
        self.flat = np.zeros(0, bool)
        self._last_row: dict[str, int] = {}  # each stream's last made row (its trail goes on from there)
        # the trail each stream names (`Motion.trail`, else its own name), the KEPT most recently learning
        self._named: OrderedDict[str, str] = OrderedDict()
        # each trail's short-term memory and each stream's last move (§11.6), the KEPT most recently
        # learning ones, oldest first
        self._short: OrderedDict[str, ShortTerm] = OrderedDict()
        self._anchors: OrderedDict[str, Anchor] = OrderedDict()
        # each stream's drive and each row's reading on it (odometry's word, §11.12)
        self._odometers: OrderedDict[str, Odometer] = OrderedDict()
        self.odometry = RowOdometry()
        self.held = 0  # rows held (not dropped)
        self.visits = 0  # consolidated frames seen since the map was loaded
        self._tried: dict[int, int] = {}  # row -> confident frames it was not joined on (`explained`)

    def rebuild(self, rows: Iterable[Any], dropped: Iterable[int] = (), joined: dict[int, int] | None = None,
                visited: Iterable[tuple[Any, ...]] = (), used: Mapping[int, int] | None = None,
                remade: Iterable[int] = (), unjoined: Iterable[int] = (),
                folded: Iterable[tuple[int, int]] = (), flat: Iterable[int] = ()) -> None:
        """The links, places and code statistics of the store's rows (recovery).

        Args:
            rows: the stored rows in seq order (`seq`, `context_prev_seq`, `input_sdr`, `stream`, and
                `place`: the place the row joined, None for its own or a row stored before places).
            dropped: seqs no longer held (§11.9). joined: seq -> the row its learning stream revisited,
                from the loop-closure log (the place of a row stored before places, §11.8).
            visited: (previous row or None, row, clock[, stream, code[, motion]]) of the visits kept, in
                log order: their links and the rows' recency (the clock a visit's `after_seq` + 1, a lower
                bound of the live one), and with the stream, the frame's code and its `Motion` (from its
                stored metadata) the short-term memory (§11.6): rows and visits are taken in the order
                they were learned. A row's motion is its stored `metadata`'s. A visit a repair re-made as a
                row has row NONE: only its step of the memory, no link, no recency.
            used: row -> the clock of its last use by a later step, as the live map recorded it (the
                store's `recency`): with it the rows' recency is the live map's exactly (§11.9).
            remade: rows a repair re-made from visits (§11.6): each a trail and a place of its own after
                the row its stream continued, neither its stream's last row nor a step of its memory.
            unjoined: rows a repair gave back their own place (their stored `place` is not read).
            folded: (row, old row) of the warm-up joins (`fold`, §11.8), in log order; their rows are
                among `dropped`.
            flat: the rows whose frame was flat (the store's `flat`, §11.7); every other row is not.
        """
        self.graph = SequenceGraph()
        self.codes.rebuild([])
        self.looks.rebuild([])
        self.used = np.zeros(0, np.int64)
        self.flat = np.zeros(0, bool)
        self._last_row, self._short, self._anchors, self.held = {}, OrderedDict(), OrderedDict(), 0
        self._named = OrderedDict()
        self._odometers, self.odometry = OrderedDict(), RowOdometry()
        self._tried = {}  # as a map loaded fresh: a repair's rebuild and a restart alike
        joined = joined or {}
        gone, remade, unjoined, flat = set(dropped), set(remade), set(unjoined), set(flat)
        # Rows and visits in the order they were learned (a visit's clock is its `after_seq` + 1), so each
        # stream's short-term memory is the live map's.
        pending = deque(visited)
        for row in rows:
            seq = int(row.seq)
            while pending and pending[0][2] <= seq:
                self.visit(*pending.popleft())
            place = None if seq in unjoined or seq in remade else getattr(row, "place", None)
            if place is None and seq in joined and seq not in unjoined:
                place = int(self.graph.place[joined[seq]])
            prev = row.context_prev_seq
            if prev is not None and (prev >= len(self.graph) or self.graph.place[prev] < 0):
                prev = None  # a joined row whose visit the log pruned (§11.8): a trail starts here
            self.add(seq, prev, row.input_sdr, stream=row.stream,
                     place=-1 if place is None else int(place), remade=seq in remade,
                     motion=Motion.of(getattr(row, "metadata", None)), flat=seq in flat)
        for row, old in folded:  # after every row: a join names rows stored before it
            if int(row) < len(self.graph) and self.graph.place[int(row)] >= 0:  # (its visit not pruned)
                self.fold(int(row), int(old))
        for seq in sorted(gone):
            if seq < len(self.graph):
                self.drop(seq)
        for v in pending:
            self.visit(*v)
        for row, clock in (used or {}).items():
            self.touch(row, clock)

    def add(self, seq: int, prev: int | None, code: np.ndarray, *, stream: str = "", place: int = -1,
            remade: bool = False, motion: Motion = NO_MOTION, flat: bool = False) -> None:
        """A row just learned, after `prev` (None: the start of a sequence), its frame code, and the place
        it shows (-1: a new place). It continues `prev`'s trail only when `prev` is its stream's last made
        row; after a consolidated frame `prev` is a row it visited, and a new trail starts (§11.8), and
        the stream's last made row, if it still has no successor (its visits named no stream, §11.1),
        gets this one. `remade`: a row a repair
        re-made from a visit (§11.6), learned long before its seq: a trail of its own after `prev`, not
        its stream's last row, no step of its short-term memory (its visit was that step). `motion`: the
        frame's pose, stamp and trail (its short-term memory, §11.6). `flat`: its frame was flat (§11.7)."""
        own = None if remade else self._last_row.get(stream)
        joins = prev is not None and own == prev
        self.graph.append(seq, -1 if prev is None else prev, place=place, joins=joins)
        if prev is not None and not joins and own is not None:
            # its own rows stay one route: the last it made leads on to this one if it led nowhere
            self.graph.link(own, seq, successor=True)
        moved = True
        if not remade:
            self._last_row[stream] = seq
            moved = self._learned(stream, seq, code, motion)
        if moved:
            # One code a move for the departure level: a robot that stands, or crawls, makes a row a
            # frame (its short-term memory holds them), and counting each filled the statistics with its
            # one place, raised that place's background likeness and so its departure level, until its
            # own copies read as moves (§11.6: a parked robot's memory aged while it stood, and its
            # paths kept pace with "moves"). Consolidation reads every row's (§11.8).
            self.looks.add(code)
        self.codes.add(code)
        if seq >= self.used.size:
            grow = max(seq + 1, 2 * self.used.size, 16) - self.used.size
            self.used = np.concatenate([self.used, np.full(grow, -1, np.int64)])
            self.flat = np.concatenate([self.flat, np.zeros(grow, bool)])
        self.used[seq] = seq
        self.flat[seq] = flat
        self.held += 1

    def touch(self, row: int, clock: int) -> None:
        """Row `row` was used at `clock` (a seq-space time)."""
        if 0 <= row < self.used.size and self.used[row] >= 0:
            self.used[row] = max(int(self.used[row]), int(clock))

    def visit(self, prev: int | None, row: int, clock: int, stream: str | None = None,
              code: np.ndarray | None = None, motion: Motion = NO_MOTION) -> None:
        """A learning stream's frame consolidated into `row` after `prev` (its last row, None: none), at
        `clock`: the link, and the row's recency (§11.8); with `stream` and the frame's `code`, a learned
        frame of that stream that made no row (its short-term memory, §11.6; `motion` as in `add`)."""
        if prev is not None:
            # the stream's last made row, if it led nowhere, leads where the stream went next: to this
            # row, not to the next row it makes after the visits (a shortcut over every place visited
            # in between, which paths walking its route then took onto rows files ahead, §11.1)
            self.graph.link(prev, row, successor=stream is not None and self._last_row.get(stream) == prev)
        self.touch(row, clock)
        if stream is not None and code is not None:
            self._learned(stream, NONE, code, motion)

    def _learned(self, stream: str, row: int, code: np.ndarray, motion: Motion) -> bool:
        """A learned frame of `stream` into its trail's short-term memory (`motion.trail`, else the
        stream's own), before its code joins the statistics (so a rebuild, which adds the rows in the
        same order, gives the same moves), and its odometry reading (the row's, where it made one).
        Returns whether it was a move of its stream (every frame where the map has no memory)."""
        self._named[stream] = motion.trail or stream
        self._named.move_to_end(stream)
        while len(self._named) > KEPT:
            self._named.popitem(last=False)
        odometer = _recent(self._odometers, stream, Odometer)
        reading = odometer.peek(motion, self.options, self.odometry.drives)
        if reading.drive == self.odometry.drives:
            self.odometry.drives += 1
        odometer.take(reading, motion.stamp)
        if row != NONE:
            self.odometry.record(row, reading)
        if not self.short_term:
            return True
        anchor = _recent(self._anchors, stream, Anchor)
        trail = motion.trail or stream
        memory = _recent(self._short, trail, lambda: ShortTerm(self.short_term))
        code = np.asarray(code, np.int64)
        span = anchor.move(code, self.departure(code), motion, self.options)
        memory.add(row, span, stream, still=anchor.stood)
        return span is not None

    def departure(self, code: np.ndarray) -> float:
        """The Dice under which a frame of code `code` (n,) sorted has left a code (§11.6): the `departure`
        share above its background likeness, read on the statistics of one code a move (`looks`)."""
        return self.looks.level(np.asarray(code, np.int64), float(self.options.departure))

    def moves(self, anchor: Anchor, code: np.ndarray, motion: Motion = NO_MOTION) -> bool:
        """Whether a frame (`code` (n,) sorted, its `motion`) moved the stream whose last move `anchor`
        holds, learning or not (§11.6); the anchor takes the frame where it is a move. It has not moved
        only where it and the anchor carry poses (`short_term_metres` > 0) and `Anchor.move` finds no
        move (its pose within `move_metres` of that move's). A step faster than `max_speed` (a reset) is
        a move whatever its look: the memory judges it by appearance, but its poses cannot say it stood
        (before, a lap posed faster than that bound rehearsed its alike frames into the row it had
        left, docs/results.md §10.29). Without poses, moved: appearance cannot tell a robot that stands from a
        stretch whose places look alike (measured, docs/results.md §11: at the `departure` level a
        Nordland frame and its copy with pixel noise of σ 8 read as a move, frames 5 apart as none on
        9 % of the route; rehearsing those merged places, and a localiser that expected such frames to
        stay called 8 false revisits while mapping on the held-out route, docs/results.md §10.15).
        Without a memory (`short_term` 0) every frame moves."""
        conf = self.options
        if not self.short_term:
            return True
        code = np.asarray(code, np.int64)
        anchor.move(code, self.departure(code), motion, conf)
        # only poses say a robot stood: a frame alike by its look alone (no pose, or a reset, which the
        # memory judges by its look) is a move, as without poses (§11.6)
        return not anchor.stood

    def departs(self, look: np.ndarray, code: np.ndarray) -> bool:
        """Whether a frame of code `code` (n,) sorted is a move of its stream by its look (§11.13): unlike
        `look`, the code of the stream's last move, by the `departure` level (§11.6). The caller asks it
        only of a frame that moved by its poses too (`moves`), with a look to judge it against."""
        code = np.asarray(code, np.int64)
        return code_dice(code, look) < self.departure(code)

    def repeats(self, seen: View | None, code: np.ndarray, motion: Motion, moved: bool) -> bool:
        """Whether a frame (`code` (n,) sorted, its `motion`; `moved`: a move of its stream, `moves`) only
        repeats `seen`, the view of the frame its stream's localiser last stepped (§11.2 step 2): no move,
        posed within `stand_metres` of that frame's pose, and not unlike its view by the `departure`
        level (`departs`). Such a frame is no new evidence. Without poses never (appearance cannot tell
        a robot that stands from a stretch alike, `moves`)."""
        if moved or seen is None or motion.pose is None:
            return False
        gone = math.hypot(motion.pose[0] - seen.pose[0], motion.pose[1] - seen.pose[1])
        return gone < float(self.options.stand_metres) and not self.departs(seen.code, code)

    def stays(self, stream: str, code: np.ndarray, motion: Motion = NO_MOTION) -> bool:
        """Whether a learned frame of `stream` has not moved since its short-term memory's last move
        (`moves`): a rehearsal of the row its stream is at, not a row of its own (RTAB-Map's
        rehearsal), §11.6. False before the stream's first move. Changes nothing (judged on a copy of
        the anchor; the frame's own step judges it again)."""
        anchor = self._anchors.get(stream) if self.short_term else None
        return (anchor is not None and anchor.code is not None
                and not self.moves(copy.copy(anchor), code, motion))

    def laid_by_others(self, stream: str, trail: str) -> set[int]:
        """The trails (`SequenceGraph.trail` ids) that the other streams naming `trail` (a robot's other
        cameras, §11.6) are laying: the chains their last made rows end, where that row is still in the
        trail's short-term memory (a camera that stopped, or yesterday's session under the same names,
        lays no chain now; a map without the memory, `short_term` 0, keeps every such chain). A row on
        one of them is on the robot's own trail as much as one on `stream`'s (whose own chain its state
        holds). O(streams kept), and the memory's rows only where another stream names the trail."""
        last = [row for name, named in self._named.items() if named == trail and name != stream
                and (row := self._last_row.get(name)) is not None and row < len(self.graph)]
        if last and self.short_term:  # (a stream alone on its trail, the usual case, reads no memory)
            recent = set(self.short_term_rows(trail).tolist())
            last = [row for row in last if row in recent]
        return {int(self.graph.trail[row]) for row in last}

    def forget_short_term(self) -> None:
        """Every trail's short-term memory and every stream's last move forgotten (§11.6): where a log
        lost steps, what they held is unknown (`models.localisation.repair.Pruned`). The next learned
        frame of each stream is a move, and its memory holds what it learns from then on."""
        self._short.clear()
        self._anchors.clear()

    def short_term_rows(self, trail: str) -> np.ndarray:
        """(m,) int64 ascending: the rows `trail`'s streams made over its last moves and still held,
        its short-term memory (`ShortTerm`, docs/design/science.md §11.6); a stream's trail is its own
        name unless its frames name another (`Motion.trail`)."""
        memory = self._short.get(trail)
        if memory is None:
            return np.zeros(0, np.int64)
        rows = memory.rows()
        return rows[self.used[rows] >= 0] if rows.size else rows

    def beyond(self, stream: str, motion: Motion) -> Callable[[np.ndarray], np.ndarray] | None:
        """What its robot's odometry says of `stream`'s frame of this `motion` (docs/design/science.md
        §11.12): rows (H,) -> (H,) bool, the rows of its drive it cannot be back at, and, where the frame
        is on its own drive, those of another stream's live drive that names its trail (the robot's
        other cameras, `Odometer.beside`); None where the frame is on no drive of its own (no pose or
        stamp, a gap, a jump: an odometry restarted, whose poses the other cameras' rows are not in, or
        nothing learned yet). O(streams kept) to build; O(H) per drive judged to apply."""
        conf = self.options
        odometer = self._odometers.get(stream)
        here = [] if odometer is None else [odometer.peek(motion, conf, -1)]
        if not here or here[0].drive < 0:  # a frame that would start a drive judges nothing
            return None
        trail = motion.trail or stream
        others = [self._odometers[name].beside(motion, conf) for name, named in self._named.items()
                  if named == trail and name != stream and name in self._odometers]
        here += [r for r in others if r.drive >= 0]
        drift, slack = conf.odometry_drift, conf.odometry_slack

        def judged(rows: np.ndarray) -> np.ndarray:
            out = self.odometry.beyond(rows, here[0], drift, slack)
            for reading in here[1:]:
                out |= self.odometry.beyond(rows, reading, drift, slack)
            return out
        return judged

    def drop(self, seq: int) -> None:
        """Row `seq` is no longer held: not an appearance of its place, never touched again (§11.9)."""
        if self.used[seq] >= 0:
            self.graph.drop(seq)
            self.used[seq] = -1
            self.held -= 1

    def place_of(self, seq: int) -> int:
        return int(self.graph.place[seq])

    def appearances(self, place: int) -> list[int]:
        """The rows place `place` holds."""
        return [r for r in self.graph.members(place) if self.used[r] >= 0]

    def places(self) -> int:
        """Places with at least one row held."""
        held = np.flatnonzero(self.used[:len(self.graph)] >= 0)
        return int(np.unique(self.graph.place[held]).size)

    def consolidation(self, place: Place, code: np.ndarray, code_of: Callable[[int], np.ndarray],
                      own: OwnTrail | None = None, neighbours: bool = True, flat: bool = False,
                      known: bool = False) -> int | None:
        """The stored row that already represents a frame of code `code` whose best path names `place`,
        or None (docs/design/science.md §11.8): the place's appearance most like it, when its Dice
        reaches b + consolidate · (1 − b), b the frame's background likeness (`CodeStats.background`,
        the scale of `departure`); failing that, the same of the places just before and after the row
        the path ends on (`place.seq`) along the route it was learned on (its predecessor's, and its
        successor's where that row continues it: the path is sure of its row give or take one, the
        pace of the robot against the map's, so a frame one place ahead of or behind its path is a
        visit of that place, not a new appearance of this one; not a link a consolidation added, which
        may join rows far apart on the route). The path's own place first: where it represents the
        frame, a neighbour that looks as much alike (a low-texture corridor, rows a metre apart) is no
        better answer. `neighbours` False: the place's alone (a frame whose stream has not moved is a
        rehearsal of the row it is at, not a visit a place off, §11.6). `flat`: the frame is flat
        (§11.7): its code says nothing of where it is, so a flat appearance of those places (`flat`)
        represents it whatever its code (the place's first, then the neighbours', the most alike of
        them), and only failing both the code decides as for any frame. `known`: the frame's stream is
        in the place's conditions (its last frame was at the level, `Stream.represented`): the place's
        own appearance most like it represents it if more alike than the background (level 0). Rows
        held only, less the stream's own (`own.holds`: its short-term memory, rows it has not left,
        rows its odometry says it cannot be at); `consolidate` 1 never consolidates. O(appearances)
        code reads."""
        if float(self.options.consolidate) >= 1.0:
            return None
        near: list[int] = []
        r = int(place.seq)
        if neighbours and 0 <= r < len(self.graph):
            prev, nxt = int(self.graph.prev[r]), int(self.graph.next[r])
            # the successor only where it continues r: a stream's last made row leads on to the row it
            # visited next, and (visits that named no stream) `add` makes its next made row the
            # successor across consolidated frames (rows far apart on the route, §11.1)
            near = [prev, nxt if nxt >= 0 and int(self.graph.prev[nxt]) == r else -1]
        around = {int(self.graph.place[n]) for n in near if n >= 0} - {place.place, -1}
        tiers = []
        for tier in ({place.place}, around):
            rows = np.array(sorted({a for q in tier for a in self.appearances(q)}), np.int64)
            if own is not None and rows.size:
                rows = rows[~own.holds(self.graph, rows)]
            tiers.append(rows)
        # a flat frame: a flat appearance, whatever its code; then, as any frame, its code's level
        level = self.codes.level(code, float(self.options.consolidate))
        if known:  # the place's own appearances down to the background (the stream's conditions are theirs)
            tiers, level = tiers[:1], self.codes.level(code, 0.0)
        chances = [rows[self.flat[rows]] for rows in tiers] if flat else []
        return _most_alike(code, code_of, [*((rows, -np.inf) for rows in chances),
                                           *((rows, level) for rows in tiers)])

    def reach(self) -> int:
        """How many of a stream's newest rows a warm-up join looks back over: `warmup` + `exclusion`
        (the frames before a first answer and the rival window after it, §11.8)."""
        return int(self.options.warmup) + int(self.options.exclusion)

    def explained(self, stream: str, place: Place, direction: int, code_of: Callable[[int], np.ndarray],
                  trail: str | None = None, moved: bool = True) -> Explained:
        """The warm-up joins a learning stream's confident revisit `place` gives (docs/design/science.md
        §11.8): (row, old row) for each of the stream's newest `reach` rows held (its own learned frames,
        as its short-term memory's ring remembers them, `ShortTerm.ages`) that is a place of its own
        (made while it warmed up or was unsure; nothing named it since), that the path covers (made
        a frames ago, a < the path's `support`), and that is represented, at the `consolidate` level, by
        the row the path stood on then: a row m links back from `place.seq` along its route (m: the
        moves of the stream since that frame, this one's where `moved`; a frame its poses said stood still
        is none, and a path that kept pace with its stream stayed on it, `ShortTerm.moves_after`), against
        the path's `direction` (+1: the path runs along the stored direction, -1 against it; the state's
        best hypothesis's), give or take JOIN_SLACK, stored before every row of the stretch. Never ahead
        of the path: on an aliased route the rows ahead may look like the stretch behind it, and a join
        there merges places that far apart. A flat row (§11.7) is joined by the path alone: to the flat
        row the path stood on then, failing that to a flat row a step off, whatever its code (a flat
        frame's code is noise); failing both, as any row. By its code, the old rows' places' other
        appearances count too. A row that is not flat and that no such row represents, but that an
        appearance of the place of the row the path stood on then (not a step off) is at least
        `join_kept` like (another season's first frames, a noisier camera's), is joined and kept
        (`Explained.kept`): a new appearance of that place, not a place of its own. The old row is
        never of a place a row of the stream's short-term memory shows, nor one a row the path covers
        shows (held, or folded into it by an earlier join: two moves of one pass are two places), nor
        of the trail the joined row lies on. Each
        row is tried on at most `exclusion` confident frames: O(reach · JOIN_SLACK · appearances) code
        reads on such a frame, O(reach) on the rest. `trail`: the short-term memory
        the stream learns into (`Motion.trail`; None: its own). `moved`: this frame was a move of its
        stream (`moves`).
        """
        c = float(self.options.consolidate)
        memory = self._short.get(trail or stream)
        if c >= 1.0 or memory is None:
            return Explained([], [])
        g = self.graph
        tries = int(self.options.exclusion)
        # its newest rows held, from the memory's ring, whether or not still in the short-term memory
        # proper: with poses that memory is the last `short_term_metres` of path, which at a frame every
        # 10 m is 2 rows, and a posed drive's first warm-up rows were never joined (an outside tester)
        ages = memory.ages(stream)  # newest first
        moves = memory.moves_after(stream)
        held = (r for r in ages if self.used[r] >= 0)
        newest = np.fromiter(itertools.islice(held, self.reach()), np.int64)
        if not newest.size:
            return Explained([], [])
        rows = [r for r, alone in zip(newest.tolist(), g.alone(newest), strict=True)
                if alone and self._tried.get(r, 0) < tries]
        rows = [r for r in rows if ages[r] + 1 < place.support]  # the path covers it
        if not rows:
            return Explained([], [])
        if len(self._tried) > KEPT * self.reach():  # bounded: the rows of the streams kept
            self._tried.clear()
        # The places the stream's own rows show: its short-term memory's, and every row it made since its
        # path began (this pass), held or joined away. A row an earlier join folded into a place shows
        # that place as much as a held one does, and two moves of one pass are two places (with the held
        # rows alone, rows two moves apart were joined on two frames into one place that then spanned
        # both: the stress suite's two cameras, docs/results.md §10.31). A pass before the path's (a
        # drive before a restart) may show the place: that is a revisit.
        this_pass = np.array([r for r, a in ages.items() if a + 1 < place.support], np.int64)
        mine = set(g.place[np.r_[self.short_term_rows(trail or stream), this_pass]].tolist())
        first = min(rows)
        keeps = float(self.options.join_kept) < c
        out, kept = [], []
        for r in rows:
            # the rows a path keeping pace advanced from the row's frame to this one: its stream's moves
            # (a robot that stood still on its poses during its warm-up: that many rows fewer; counted in
            # frames, a kept join named a place as many rows back, a review)
            lag = moves[r] + int(moved)
            walk = g.route(place.seq, -int(direction), lag + JOIN_SLACK)
            off = np.abs(np.arange(walk.size) - lag)  # steps from the path's row then
            keep = (off <= JOIN_SLACK) & (walk < first) & (self.used[walk] >= 0)
            keep &= (g.trail[walk] != g.trail[r]) & np.isin(g.place[walk], list(mine), invert=True)
            old, off = walk[keep], off[keep]
            code = np.asarray(code_of(r), np.int64)
            # A flat row's code is noise (§11.7): among rows as blank the most alike is chance, and a
            # noisy tunnel frame is more like another noisy one a place off than like the clean row the
            # path stood on. So a flat row is joined by the path alone: the flat row it stood on then,
            # failing that a flat row a step off (the most alike); as consolidation takes a flat frame.
            flat = self.flat[old] if self.flat[r] else np.zeros(old.size, bool)
            # By its code, the places' other appearances too, as a frame's consolidation reads them: the
            # place seen otherwise (a kept join's row, another pass's) represents a later drive's row as
            # well as the row its route was learned with (before, each winter drive kept its warm-up again)
            seen = self._appearances_before(old, first, int(g.trail[r]))
            joined = _most_alike(code, code_of, [(old[(off == 0) & flat], -np.inf),
                                                 (old[(off > 0) & flat], -np.inf),
                                                 (seen, self.codes.level(code, c))])
            if joined is not None:
                out.append((r, joined))
                mine.add(int(g.place[joined]))  # r shows that place now, in this call as after it
                continue
            # Not represented, but like the row the path says it was: that place seen otherwise (another
            # season, a noisier camera), a new appearance of it. Never a flat row: its code is noise.
            # The path's geometry is the guard here as for any join: on a route that aliases, a row a few
            # places off is as alike as the true one often enough (docs/results.md §11). So the path
            # names the place: the row it stood on then, not a step off (taken by its code among the
            # rows a step either side, noisy rows were kept a step before and after one place, which then
            # spanned three: merged places on the quick stress suite's noisy lap and two cameras).
            at = old[off == 0]
            if keeps and not self.flat[r] and at.size:
                level = self.codes.level(code, float(self.options.join_kept))
                like = _most_alike(code, code_of, [(seen[g.place[seen] == g.place[at[0]]], level)])
                if like is not None:  # (recorded as the row the path stood on: the place it names)
                    kept.append((r, int(at[0])))
                    mine.add(int(g.place[at[0]]))
                    continue
            self._tried[r] = self._tried.get(r, 0) + 1
        return Explained(out, kept)

    def _appearances_before(self, rows: np.ndarray, first: int, trail: int) -> np.ndarray:
        """(n,) int64 `rows` and the other appearances of their places, those stored before row `first`
        and not on trail `trail` (a warm-up join's candidates, `explained`), ascending."""
        g = self.graph
        seen = {int(a) for q in np.unique(g.place[rows]).tolist() for a in self.appearances(q)}
        seen = np.array(sorted(seen | set(rows.tolist())), np.int64)
        return seen[(seen < first) & (g.trail[seen] != trail)] if seen.size else seen

    def fold(self, row: int, old: int, clock: int | None = None) -> None:
        """A warm-up join (`explained`): row `row` shows the place of `old`; `old` used at `clock` (None: a
        recovery, whose recency is the store's). For a join `old` represents, the caller drops `row`: like
        a consolidated frame it adds no appearance; a kept join's row stays, an appearance of the place."""
        self.graph.rejoin(row, old)
        if clock is not None:
            self.touch(old, clock)

    def over_cap(self, place: int, *keep: int) -> list[int]:
        """The appearances to drop so that `place` holds at most `appearances` rows: the least recently
        used first (ties: the older row), never one of `keep` (the rows the step just made or kept, the
        row its frame is consolidated into) (§11.9)."""
        rows = self.appearances(place)
        extra = len(rows) - int(self.options.appearances)
        if extra <= 0:
            return []
        rows = [r for r in rows if r not in keep]
        return sorted(rows, key=lambda r: (int(self.used[r]), r))[:extra]

    def least_recent(self, n: int) -> list[int]:
        """Rows of the least recently used places, whole places, at least `n` rows (forgetting, §11.9):
        a place's recency is its most recently used row's."""
        held = np.flatnonzero(self.used[:len(self.graph)] >= 0)
        if not held.size or n <= 0:
            return []
        places = self.graph.place[held]
        order = np.lexsort((held, places))
        places, rows = places[order], held[order]
        starts = np.r_[0, np.flatnonzero(places[1:] != places[:-1]) + 1]
        recency = np.maximum.reduceat(self.used[rows], starts)
        out: list[int] = []
        for i in np.lexsort((places[starts], recency)):
            lo = starts[i]
            hi = starts[i + 1] if i + 1 < starts.size else rows.size
            out.extend(int(r) for r in rows[lo:hi])
            if len(out) >= n:
                break
        return out

    def candidates_wanted(self, top_k: int, short_term: int = 0) -> int:
        """How many ranked rows one index pass must return for `top_k` matches and the localiser (whose
        candidates leave out up to `exclusion` of them, the stream's own rows behind those not left, and
        the `short_term` rows of its memory: a slow robot's holds hundreds)."""
        return max(top_k, self.top_k + int(self.options.exclusion) + int(short_term))

    def new_state(self) -> LocaliserState:
        return self.localiser.new_state()

    def own_trail(self, state: LocaliserState, last_learned: int | None, code: np.ndarray,
                  code_of: Callable[[int], np.ndarray], informative: bool = True) -> OwnTrail | None:
        """The stream's own rows it has not left, after this frame (`SequenceLocaliser.own_trail`,
        docs/design/science.md §11.6): not candidates of the index pass, not states of the filter."""
        return self.localiser.own_trail(state, self.graph, last_learned, code, code_of, self.looks,
                                        informative)

    def step(self, state: LocaliserState, ranked: Sequence[Match], own: OwnTrail | None,
             contrast: float | None = None, moved: bool = True, departed: bool = False,
             repeat: bool = False) -> Place | None:
        """One frame of one stream (docs/design/science.md §11.2), before this frame is stored.

        Args:
            state: the stream's localiser state, updated in place.
            ranked: the index's pass for the frame's winner cells, best first (Dice scores), without
                the rows the stream has not left; the localiser leaves out the rest of `own` and keeps
                its `top_k` best.
            own: the stream's own rows (`own_trail`).
            contrast: the frame's (None: not measured). Under `MIN_CONTRAST` it is too flat to say where
                it is (`localiser.informative`, §11.7): no evidence, no revisit; over it, a flat row
                keeps `flat_share` of its evidence (§11.7).
            moved: False where the frame is no move of its stream by its poses (`moves`, §11.6).
            departed: the frame is a move of its stream by its look (`departs`, §11.13).
            repeat: the frame stands by its poses and repeats the view of the frame the localiser last
                stepped (`repeats`, §11.2 step 2): no new evidence, the answer read again off the
                unchanged state.

        Returns:
            The place, or None during warm-up.
        """
        seqs = np.fromiter((m.seq for m in ranked), np.int64, len(ranked))
        scores = np.fromiter((m.score for m in ranked), np.float64, len(ranked))
        # (a row outside the map is the localiser's to refuse, not an index to wrap)
        ok = seqs.size and seqs.min() >= 0 and seqs.max() < self.flat.size
        flat = self.flat[seqs] if ok else np.zeros(seqs.size, bool)
        shares = np.where(flat, flat_share(contrast), 1.0) if flat.any() else None
        return self.localiser.step(state, self.graph, seqs, scores, own, is_informative(contrast), moved,
                                   departed, shares, repeat)


def _most_alike(code: np.ndarray, code_of: Callable[[int], np.ndarray],
                tiers: Sequence[tuple[np.ndarray, float]]) -> int | None:
    """The row most like `code` of the first tier (rows (n,) int64, floor) whose most alike row reaches
    its floor, tiers in order, empty ones skipped; None: none does. O(rows read) code reads."""
    for rows, floor in tiers:
        if not rows.size:
            continue
        sims = [code_dice(code, np.asarray(code_of(int(row)), np.int64)) for row in rows.tolist()]
        best = int(np.argmax(sims))
        if sims[best] >= floor:
            return int(rows[best])
    return None


def _recent(kept: OrderedDict[str, T], key: str, new: Callable[[], T]) -> T:
    """`kept[key]` (made by `new` where missing), now the most recent; the least recent beyond KEPT go."""
    value = kept.get(key)
    if value is None:
        value = kept[key] = new()
        if len(kept) > KEPT:
            kept.popitem(last=False)
    kept.move_to_end(key)
    return value
