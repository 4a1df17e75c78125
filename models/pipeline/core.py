"""The per-frame pipeline of a map, pure: a projected frame through the stream's adaptation, the sLSBH
hash, the memory, one index pass and the localiser, and for a learned frame into the index and the links
(docs/design/service.md §1.2, §6; docs/design/science.md §7, §11.2).

No SQLite, no threads: the service's map writer (`service.maps.runtime.MapRuntime.apply`), the
recovery's replay (`service.maps.recovery.memory.rebuild`) and the evaluation
(`service.evaluation.service_path`) call these functions on the same `MapModel`, so what is measured and
replayed is what is served.
Ordering, persistence (the row, its seq) and snapshots are the caller's.

`observe` is one frame online; `replay` is one stored row again (its code is stored, so no hash, no
index pass: the index and the links are rebuilt in bulk from the rows afterwards), `revisit` one stored
visit again (a consolidated frame: the memory learned it, no row was made, docs/design/science.md §11.8).
All keep a stream's sequence bookkeeping through `_remember`, the one place its rules live.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from models.frontend import slsbh
from models.frontend.adaptation import RunningMean
from models.localisation import InvertedIndex, LocaliserOptions, Match, Place, PlaceMap, informative
from models.localisation.condition import Condition
from models.localisation.motion import NO_MOTION, Motion
from models.localisation.short_term import View
from models.localisation.trail import OwnTrail
from models.memory import registry as memories
from models.memory.temporal_memory import TemporalMemory
from models.pipeline.state import Stream
from models.presets import TmOptions

__all__ = ["MapModel", "Step", "observe", "replay", "revisit"]


@dataclass
class MapModel:
    """What a frame's step reads and changes: the map's memory, index and places, and the frozen options
    the step needs (docs/design/service.md §1.1).

    Attributes:
        tm: the Temporal Memory (unused with `memory: none`).
        index: winner cells -> stored seqs, ranked by Dice (docs/design/service.md §5).
        place_map: the places: the learned links, the localiser and each row's place
            (`models.localisation.places.PlaceMap`, docs/design/science.md §11).
        memory: a registered memory (`models.memory.registry`: `tm`, or `none`, the ablation).
        s: the sLSBH sparsity (the fraction of the k projections kept on each side, §7).
        adapt_tau: the streams' adaptation time constant (0: none).
    """

    tm: TemporalMemory
    index: InvertedIndex
    place_map: PlaceMap
    memory: str = "tm"
    s: float = 0.0
    adapt_tau: int = 0

    @classmethod
    def new(cls, tm: TmOptions, localiser: LocaliserOptions, *, max_observations: int,
            memory: str = "tm", s: float = 0.0, adapt_tau: int = 0) -> MapModel:
        """A fresh model: an empty memory with options `tm`, an empty index of `max_observations` rows,
        no links, the localiser with the `localiser` options (its code statistics over the TM's columns,
        the sLSBH code's width)."""
        connections = TemporalMemory(tm)
        return cls(connections, InvertedIndex(connections.n_cells, max_observations),
                   PlaceMap(localiser, connections.n_columns), memory, s, adapt_tau)

    def fresh(self, tm: TemporalMemory | None = None) -> MapModel:
        """The same options over `tm` (default: this model's), with an empty index and no links."""
        tm = self.tm if tm is None else tm
        return MapModel(tm, InvertedIndex(tm.n_cells, self.index.max_observations),
                        PlaceMap(self.place_map.options, tm.n_columns), self.memory, self.s,
                        self.adapt_tau)

    @property
    def condition_frames(self) -> int:
        """The streams' condition time constant (docs/design/science.md §11.10; 0: none)."""
        return self.place_map.options.condition_frames

    def cells_per_column(self) -> int:
        """Winner cells per code bit: the TM's cells per column, 1 where the code is the winners."""
        return int(self.tm.cells_per_column) if memories.get(self.memory).sequential else 1


@dataclass(frozen=True)
class Step:
    """One frame's outcome, before anything is stored.

    Attributes:
        code: (2n,) int64 sorted sLSBH columns (what a learned row stores as `input_sdr`).
        winners: (w,) int64 sorted winner cells (stored as `winner_cells`).
        prev_seq: the learned row this frame continues (None: a new sequence), the row's `context_prev_seq`
            (or the visit's).
        step: steps of the stream since its context was last empty, before this one.
        stats: the TM step's column counts (`StreamContext.stats.as_dict()`).
        ranked: the best `top_k` stored rows by Dice (weighted by the stream's condition, docs/design/
            science.md §11.10), best first.
        place: the stream's place on the map, or None (warm-up).
        timings_ms: hash, tm, search (ranking and localiser), localiser.
        visit: a learned frame consolidated into this stored row (no row made, docs/design/science.md
            §11.8); None: a row was made (learning) or nothing is learned.
        joined: for a made row, the place it joined (-1: a new place of its own).
        dropped: rows places dropped over their cap (§11.9), least recently used first: those of the places
            the step's kept joins joined (`kept`), then those of the made row's place.
        touched: rows this learned step used at the clock `seq` (the answer's row, the visited row):
            stored with the row or visit, so a recovery gives them the same recency (§11.9).
        joins: the warm-up joins this step's confident revisit made (docs/design/science.md §11.8):
            (row, old row), the stream's earlier row now of the old row's place and held no more
            (dropped from the index and the places with the step, logged with its row or visit).
        kept: the warm-up joins that keep their row (§11.8): (row, old row), the stream's earlier row now
            an appearance of the old row's place, still held (logged with its row or visit).
        flat: the frame was flat (under `MIN_CONTRAST`, §11.7): a made row is a flat row (stored with it).
    """

    code: np.ndarray
    winners: np.ndarray
    prev_seq: int | None
    step: int
    stats: dict[str, int]
    ranked: list[Match]
    place: Place | None
    timings_ms: dict[str, float]
    visit: int | None = None
    joined: int = -1
    dropped: tuple[int, ...] = ()
    touched: tuple[int, ...] = ()
    joins: tuple[tuple[int, int], ...] = ()
    kept: tuple[tuple[int, int], ...] = ()
    flat: bool = False


def _remember(model: MapModel, st: Stream, code: np.ndarray, *, learn: bool, starts: bool) -> np.ndarray:
    """The memory's step on the stream's context; `starts`: the frame begins a new sequence."""
    if starts:
        st.new_sequence()
    return memories.get(model.memory).winners(model.tm, code, learn, st.context)


def _condition(model: MapModel, st: Stream, code: np.ndarray) -> None:
    """The frame's code into the stream's condition (docs/design/science.md §11.10), after its ranking:
    every frame; a replay of the rows and visits gives a stream that only learned its live condition
    again (learn=false frames are not stored: after a crash they are lost to it)."""
    if model.condition_frames:
        if st.condition is None:
            st.condition = Condition(model.place_map.codes.counts.size, model.condition_frames)
        st.condition.add(code, float(model.place_map.options.condition_discount))


def _advance(st: Stream, learn: bool, seq: int | None, made: bool = True) -> None:
    """The stream after its step: a learned frame is the row `seq` the next one continues (`made`: the
    stream's own new row; else a row it visited, §11.8)."""
    if learn:
        st.last_learned_seq = seq
        if made:
            st.own_seq = seq
    st.learning = learn
    st.step += 1


def observe(model: MapModel, st: Stream, projected: np.ndarray, *, learn: bool, stream: str, top_k: int,
            code_of: Callable[[int], np.ndarray], seq: int | None = None,
            threshold: float | None = None, contrast: float | None = None,
            motion: Motion = NO_MOTION) -> Step:
    """One frame of one stream (docs/design/service.md §1.2, §6).

    Args:
        model: the map's memory, index and links; changed in place when learning.
        st: the stream's state, changed in place.
        projected: (k,) the frame's features · the map's projection (docs/design/science.md §7).
        learn: learn the frame: the memory learns, and the frame joins the index and the links as `seq`.
        stream: the stream's name (its own rows it has not left are left out of the ranking, §11.6).
        top_k: ranked rows wanted in `Step.ranked`.
        code_of: a stored row's code (its `input_sdr`), read by the own-trail rule (§11.6): about one
            row per frame, and `exclusion` + 1 more plus one per such row on a frame where paths reach
            rows of the stream's own trail laid since they began.
        seq: the seq the learned row gets (required with `learn`; the caller stores it under that seq).
            It is also the clock of the places' recency (§11.9).
        threshold: the map's revisit threshold. A learning frame whose place is a revisit (confidence
            >= it) joins that place, and is consolidated into it when one of its appearances already
            represents the frame (`PlaceMap.consolidation`, docs/design/science.md §11.8): the
            memory learns it, no row is made (`Step.visit`); the rows the stream made before it
            knew where it was that its path now explains are joined to the old places (`Step.joins`,
            held no more; `Step.kept`, new appearances of them).
            None: no frame is a revisit, none is consolidated.
        contrast: the decoded frame's contrast (`models.frontend.images.contrast`; None: not measured).
            Under `localisation.MIN_CONTRAST` the frame says nothing of where it is (§11.7): it is no
            evidence to the localiser, leaves no row of the stream's trail, and its place is no revisit.
            It is still learned and ranked like any frame, and consolidated like an unconfident one:
            a visit of a flat row its path names (its place's, else a neighbouring place's), whatever
            its code, else of an appearance like it; a row it makes is a flat row (`Step.flat`).
        motion: the frame's pose, stamp and trail (`Motion.of` its metadata): a learned frame's move in
            its trail's short-term memory, and the trail whose memory is no candidate (§11.6).

    Returns:
        The step. The stream's bookkeeping is done; the caller stores a learned row (or the visit) after
        it, and drops `Step.dropped`.

    Raises:
        IndexFull: learning into a full index (the caller checks first; see `InvertedIndex.add`).
    """
    if learn and seq is None:
        raise ValueError("a learned frame needs its seq")
    t0 = time.perf_counter()
    if model.adapt_tau:
        # The adapted stream's code; a crash loses the means since the last snapshot (they are not in
        # the store), which costs about tau frames of weaker codes, never a stored row.
        st.adapt = st.adapt or RunningMean(model.adapt_tau)
        projected = st.adapt.subtract(projected)
    code = slsbh.hash_projected(projected[None, :], model.s)[0].astype(np.int64)
    t1 = time.perf_counter()
    # A switch to mapping starts a new sequence (replay relies on it); with a sequential memory, so
    # does an empty context (without one, only `step` counts).
    sequential = memories.get(model.memory).sequential
    if learn and st.learning is False:
        starts = True
    else:
        starts = False
        if st.context.active_cells.size == 0 and sequential:
            st.new_sequence(context=False)
    # Without context every column bursts and the winners are least-used cells: ranked by its columns
    # (docs/design/science.md §11.2 step 1).
    unprimed = sequential and (starts or st.context.active_cells.size == 0)
    winners = _remember(model, st, code, learn=learn, starts=starts)
    stats = st.context.stats.as_dict()
    t2 = time.perf_counter()
    st.localiser = st.localiser or model.place_map.new_state()
    prev, step = st.last_learned_seq, st.step
    # The stream's own rows it has not left are no answer (docs/design/science.md §11.6); one index pass
    # without them serves the matches and the localiser's candidates (§11.2), which also leaves out the
    # rival window behind them.
    # The trail is the stream's own made rows: after a consolidated frame it is not where `prev` is (§11.8).
    flat = not informative(contrast)
    own = model.place_map.own_trail(st.localiser, st.own_seq, code, code_of, not flat)
    if own is not None and own.here > own.last and st.last_learned_seq != st.own_seq:
        own = None  # it left every row it made and travels on rows it visited: none is where it is
    # the chains its robot's other cameras are laying are its trail as much as its own (the mirror
    # rule, §11.13; the consolidation guard below, §11.6)
    others = frozenset(model.place_map.laid_by_others(stream, motion.trail or stream))
    if own is not None and others:
        own = own._replace(others=others)
    # Its short-term memory, the rows it made over its last moves whatever its trail, is no loop
    # candidate; the map keeps it, so a restart, an eviction or a switch of mode keeps it too (§11.6).
    stm = model.place_map.short_term_rows(motion.trail or stream)
    if stm.size:
        own = OwnTrail.short_term_only(stm) if own is None else own.with_short_term(stm)
    # Nor is a row of its drive that its odometry says it cannot be back at (§11.12).
    beyond = model.place_map.beyond(stream, motion)
    if beyond is not None:
        own = (OwnTrail.short_term_only(stm) if own is None else own)._replace(beyond=beyond)
    wanted = model.place_map.candidates_wanted(top_k, stm.size)
    exclude = None if own is None or not own.has_trail else (stream, own.here)
    if unprimed:  # one frame a sequence: unweighted
        ranked = model.index.rank_columns(code, model.cells_per_column(), wanted, exclude_own=exclude)
    else:
        # Bits the stream's recent frames share say what its conditions are, not where it is (§11.10).
        weights = None if st.condition is None else st.condition.weights(
            winners, model.cells_per_column(), float(model.place_map.options.condition_discount))
        ranked = model.index.rank(winners, wanted, exclude_own=exclude, weights=weights)
    t_ranked = time.perf_counter()
    moved = model.place_map.moves(st.mover, code, motion)
    # a move its paths must keep pace with: by its look, and by its poses where it has them; a flat
    # frame's code is noise, no look (§11.13). With no look to judge it against (a stream's first
    # frame, or its first after a restart: paths restored, the look not stored) a frame is the look,
    # no move: a robot parked at its route's end would fall behind a dead end it cannot leave.
    departed = moved and not flat and st.look is not None and model.place_map.departs(st.look, code)
    if departed or (st.look is None and not flat):
        st.look = code
    # A frame that stands by its poses and shows the view of the frame the localiser last stepped is
    # that view again, no new evidence: the answer is read again off the state that step left (§11.2
    # step 2). Counted as new, a parked robot's frames let a path resting on a stored row elsewhere that
    # looks like its view gather confidence frame after frame, to a false revisit (docs/results.md
    # §10.24). `seen` is the view of the frame the localiser last stepped, or None where that frame
    # cannot be repeated (flat, or without a pose), so a flat frame at a stop is no view the stop's next
    # frames repeat (a review: its uninformative answer stood for the rest of the stop, and the parked
    # robot lost its revisit). A state with no step to answer from (new, restored, in warm-up) steps.
    repeat = (not flat and st.localiser.background is not None
              and model.place_map.repeats(st.seen, code, motion, moved))
    if not repeat:
        st.seen = None if flat or motion.pose is None else View(code, motion.pose)
    place = model.place_map.step(st.localiser, ranked, own, contrast, moved, departed, repeat)
    if place is not None and threshold is not None and place.is_revisit(threshold):
        # Learning or not, a revisit is entered on its path at the threshold, and its unconfident frames
        # are held on that path at `unsure_fraction` of it until another path calls a revisit or the
        # search starts again (§11.8). A dip under the fraction does not end it: ending it there was
        # measured and cost merged places on the stress suite (docs/results.md §10.26).
        st.localiser.revisit = st.localiser.best_path()
    visit, joined, touched, joins, kept = None, -1, [], [], []
    dropped: tuple[int, ...] = ()
    if learn:
        assert seq is not None
        place_map = model.place_map
        # whether it has not moved since its stream's last move (§11.6: no pose change of `move_metres`)
        still = place_map.stays(stream, code, motion)
        represented = False  # whether this frame's code earns its stream the place's conditions
        if place is not None and threshold is not None:
            # Well represented: like an appearance of the place its best path names, confident or not
            # (a pass's unconfident frames would otherwise become parallel places, each a rival, §11.8).
            # A flat frame too (never confident, §11.7): where its path names a place (or a neighbouring
            # one) that has a flat row, it is a visit of it whatever its code (a flat frame's code is
            # noise), not a new place each time it is seen.
            # never into the stream's own recent rows (its short-term memory, a row it has not left);
            # a frame that has not moved is the row it is at or a rehearsal, never a place off
            visit = place_map.consolidation(place, code, code_of, own, neighbours=not still, flat=flat)
            confident = place.is_revisit(threshold)
            at_level = visit is not None and not flat  # its code earned it: the place's conditions
            if visit is None and confident and st.represented and not still:
                # Its last frame was at the level of an appearance and this one, a revisit, falls under
                # it: the noise of one frame, not another condition, which shows on frames in a row (a
                # noisy pass stored 1-5 such rows per 400 frames, issue 36): a visit of the place's most
                # alike appearance, if more alike than the background (§11.8). A frame that has not
                # moved stays a rehearsal of the row it is at.
                visit = place_map.consolidation(place, code, code_of, own, neighbours=False, known=True)
            # the trail it lays: its own chain's, or one its robot's other cameras lay (§11.6)
            on = -1 if visit is None else int(place_map.graph.trail[visit])
            trail = visit is not None and (
                (st.own_seq is not None and on == int(place_map.graph.trail[st.own_seq]))
                or on in others)
            # (`unsure_fraction` of the threshold: some sequence evidence, LocaliserOptions)
            unsure = not confident and (place.confidence < threshold * place_map.options.unsure_fraction
                                        or trail or not place.advancing
                                        or not st.localiser.on_revisit_path())
            if visit is not None and unsure:
                # unconfident, it needs some sequence evidence, and never a row of the trail it is
                # laying (just behind its short-term memory a path in step with it is an echo, §11.6).
                # Nor a place its path has not called a revisit of: a revisit is entered at the
                # threshold and held on its path at a fraction of it. A path that never reached the
                # threshold is no evidence that it is on stored ground: a robot on ground the map has
                # not seen finds paths over look-alike rows at half of it (docs/results.md §10.25).
                visit = None
            represented = at_level and visit is not None
            if visit is not None or confident:
                place_map.touch(place.seq, seq)  # a learning stream used the place (§11.9)
                touched.append(place.seq)
                joined = place.place
        if (place is not None and threshold is not None and place.is_revisit(threshold)
                and st.localiser.pace == 1.0):
            # Rows it made while it warmed up or was unsure, that the path now explains (§11.8): those the
            # old rows represent are held no more, the rest like them are kept, appearances of their places.
            # Not at another pace than its map's (§11.2 step 2): where its path stood k moves ago is then
            # known only as well as its pace, an average that lags the robot's: joined as if at that pace,
            # the stress suite's `faster` case merged places (docs/results.md §10.28).
            found = place_map.explained(stream, place, int(st.localiser.dirs[0]), code_of, motion.trail,
                                        moved)
            joins, kept = found.joins, found.kept
            for row, old in (*joins, *kept):
                place_map.fold(row, old, seq)
                touched.append(old)
            drop(model, [row for row, _ in joins])
            if joined >= 0:  # the place as the folds left it, which a recovery reads before it folds
                joined = place_map.place_of(place.seq)
            # a place over its cap drops its least recently used appearances (§11.9), once for all the
            # rows the step kept in it (one at a time, a kept row one cap dropped still counted at the next
            # and the place lost one too many, a review), never those nor the row the frame visits
            filled = {place_map.place_of(old) for _, old in kept}
            spared = [row for row, _ in kept] + ([] if visit is None else [visit])
            for full in sorted(filled):
                capped = place_map.over_cap(full, *spared)
                drop(model, capped)
                dropped += tuple(capped)
        st.represented = represented  # a frame with no answer, or that made a row, earns none
        if visit is None and prev is not None and place_map.used[prev] >= 0 and still:
            # It has not moved since its last learned frame: a visit of the row that frame made or
            # visited (a rehearsal), the memory learns it, no row
            visit = prev
        if visit is not None:
            place_map.visit(prev, visit, seq, stream, code, motion)
            touched.append(visit)
            place_map.visits += 1
        else:
            model.index.add(seq, winners, stream)
            place_map.add(seq, prev, code, stream=stream, place=joined, motion=motion, flat=flat)
            capped = tuple(place_map.over_cap(joined, seq)) if joined >= 0 else ()
            drop(model, capped)
            dropped += capped
    _condition(model, st, code)
    _advance(st, learn, seq if visit is None else visit, made=visit is None)
    t3 = time.perf_counter()
    # search = the index's ranking (with the own-trail rule) + `localiser` (its step and the row's adds).
    timings = {"hash": (t1 - t0) * 1e3, "tm": (t2 - t1) * 1e3, "search": (t3 - t2) * 1e3,
               "localiser": (t3 - t_ranked) * 1e3}
    return Step(code=code, winners=winners, prev_seq=prev, step=step, stats=stats,
                ranked=list(ranked[:top_k]), place=place, timings_ms=timings, visit=visit, joined=joined,
                dropped=dropped, touched=tuple(touched), joins=tuple(joins), kept=tuple(kept), flat=flat)


def drop(model: MapModel, seqs: tuple[int, ...] | list[int]) -> None:
    """Rows that are no longer held (an appearance over its place's cap, a forgotten place,
    docs/design/science.md §11.9): out of the index and their places; their links stay."""
    model.index.remove(seqs)
    for s in seqs:
        model.place_map.drop(int(s))


def replay(model: MapModel, st: Stream, code: np.ndarray, *, seq: int, prev_seq: int | None) -> np.ndarray:
    """A stored row's step again (docs/design/service.md §4.4): its code through the memory on the
    stream's context, learning, with the bookkeeping `observe` gave it. The index and the links are not
    touched (rebuilt from the rows in one pass).

    Args:
        code: (2n,) the row's `input_sdr`; seq, prev_seq: the row's `seq` and `context_prev_seq`.

    Returns:
        (w,) the replayed winner cells (the caller compares them with the stored ones).
    """
    winners = _remember(model, st, code, learn=True, starts=prev_seq is None)
    _condition(model, st, code)
    _advance(st, True, seq)
    return winners


def revisit(model: MapModel, st: Stream, code: np.ndarray, *, row: int, prev_seq: int | None) -> np.ndarray:
    """A stored visit's step again (a consolidated frame, docs/design/science.md §11.8; service.md §4.4):
    its code through the memory on the stream's context, learning, and the stream moved onto the visited
    `row` as `observe` did. Nothing else is touched.

    Returns:
        (w,) the replayed winner cells (the caller compares them with the stored ones).
    """
    winners = _remember(model, st, code, learn=True, starts=prev_seq is None)
    _condition(model, st, code)
    _advance(st, True, row, made=False)
    return winners
