"""The pure per-frame pipeline (models/pipeline/core.py): one frame online (`observe`) and one stored
row again (`replay`) share the memory step and the stream bookkeeping, with no store and no thread."""

from __future__ import annotations

import numpy as np
import pytest

from models.localisation import LocaliserOptions, Place
from models.pipeline import (
    MapModel,
    Stream,
    load_memory_state,
    memory_state,
    observe,
    replay,
    resume,
    resume_state,
)
from models.presets import TmOptions

TM = {"columnDimensions": 128, "cellsPerColumn": 4, "maxSegmentsPerCell": 4, "maxSynapsesPerSegment": 16,
      "activationThreshold": 3, "minThreshold": 2, "seed": 3}
K, S = 64, 0.1  # 2k = columnDimensions; n = 6 ones per half


def model(memory: str = "tm", adapt_tau: int = 0, localiser: dict | None = None) -> MapModel:
    return MapModel.new(TmOptions.of(TM), LocaliserOptions.of(localiser), max_observations=1000,
                        memory=memory, s=S, adapt_tau=adapt_tau)


def route(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, K)).astype(np.float32)


CODES: dict[int, np.ndarray] = {}  # the stored rows' codes, as a store would give them (code_of)


def learn_route(m: MapModel, frames: np.ndarray, st: Stream, first_seq: int = 1) -> list:
    steps = []
    for i, y in enumerate(frames):
        steps.append(observe(m, st, y, learn=True, stream="a", top_k=3, seq=first_seq + i,
                             code_of=CODES.__getitem__))
        CODES[first_seq + i] = steps[-1].code
    return steps


@pytest.mark.parametrize("memory", ["tm", "none"])
def test_replay_of_the_stored_codes_reproduces_every_step(memory):
    """What recovery relies on: the rows `observe` learned, replayed on a fresh memory, give the same
    winner cells, and the stream ends with the same bookkeeping."""
    m, st = model(memory), Stream()
    frames = route(12)
    steps = learn_route(m, frames[:6], st)
    st.break_sequence()  # a new sequence part-way: its first row has no predecessor
    steps += learn_route(m, frames[6:], st, first_seq=7)
    assert [s.prev_seq for s in steps] == [None, 1, 2, 3, 4, 5, None, 7, 8, 9, 10, 11]
    again, st2 = m.fresh(model(memory).tm), Stream()
    for seq, s in enumerate(steps, start=1):
        assert np.array_equal(replay(again, st2, s.code, seq=seq, prev_seq=s.prev_seq), s.winners)
    assert (st2.step, st2.last_learned_seq, st2.learning) == (st.step, st.last_learned_seq, st.learning)
    # the stream's condition (docs/design/science.md §11.10) is rebuilt too: the next ranking is the same
    assert st2.condition is not None and st2.condition.seen == 12
    assert np.array_equal(st2.condition.rates, st.condition.rates)


def test_a_learned_frame_joins_the_index_and_the_links_and_a_localisation_changes_neither():
    m, st = model(), Stream()
    frames = route(8)
    learn_route(m, frames, st)
    assert len(m.index) == 8 and m.place_map.graph.prev[5] == 4  # row 5 continues row 4
    before = (len(m.index), m.tm.size()["segments"])
    q = Stream()
    found = [observe(m, q, y + 0.01, learn=False, stream="q", top_k=1, code_of=CODES.__getitem__)
             for y in frames]
    assert (len(m.index), m.tm.size()["segments"]) == before
    assert found[0].ranked[0].seq == 1 and found[-1].ranked[0].seq == 8  # each frame finds itself
    assert found[-1].place is not None and found[-1].place.seq == 8
    assert q.last_learned_seq is None and q.learning is False


def test_a_switch_to_mapping_starts_a_new_sequence():
    m, st = model(), Stream()
    learn_route(m, route(3), st)
    observe(m, st, route(1, 5)[0], learn=False, stream="a", top_k=0, code_of=CODES.__getitem__)
    step = observe(m, st, route(1, 6)[0], learn=True, stream="a", top_k=0, seq=4, code_of=CODES.__getitem__)
    assert step.prev_seq is None and step.step == 0


def test_a_learned_frame_needs_its_seq_and_nothing_changes_without_it():
    m, st = model(), Stream()
    with pytest.raises(ValueError, match="seq"):
        observe(m, st, route(1)[0], learn=True, stream="a", top_k=0, code_of=CODES.__getitem__)
    assert len(m.index) == 0 and st.step == 0


def test_adaptation_subtracts_the_streams_running_mean_before_hashing():
    """With adapt_tau the first frame (no history) is hashed as it is, the later ones less the mean."""
    frames = route(6)
    adapted = [s.code for s in learn_route(model(adapt_tau=2), frames, Stream())]
    plain = [s.code for s in learn_route(model(), frames, Stream())]
    assert np.array_equal(adapted[0], plain[0])
    assert any(not np.array_equal(a, b) for a, b in zip(adapted[1:], plain[1:], strict=True))


def two_conditions(n: int, alpha: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(n, K) projections of n places seen in condition A, and the same places in condition B: each
    frame is its place's vector plus `alpha` times its condition's (what every frame of a season or a
    light shares) plus a little noise."""
    rng = np.random.default_rng(seed)
    places = rng.normal(size=(n, K))
    a, b = rng.normal(size=K), rng.normal(size=K)
    seen = [places + alpha * c + 0.3 * rng.normal(size=(n, K)) for c in (a, b)]
    return seen[0].astype(np.float32), seen[1].astype(np.float32)


def second_lap(localiser: dict) -> tuple[int, int]:
    """One learning stream drives 200 places in condition A, then the same places in condition B:
    (lap-2 answers naming the lap-1 row of their place, lap-2 answers naming the stream's own lap-2
    rows, i.e. other places seen in B)."""
    m, st = model("none", localiser=localiser), Stream()
    lap1, lap2 = two_conditions(200, 1.0)
    learn_route(m, lap1, st, first_seq=1)
    places = [s.place for s in learn_route(m, lap2, st, first_seq=201)]
    right = sum(p is not None and p.seq == i + 1 for i, p in enumerate(places))
    return right, sum(p is not None and p.seq > 200 for p in places)


def test_a_streams_condition_keeps_its_own_rows_of_the_new_condition_from_outranking_the_place():
    """docs/design/science.md §11.10: once the stream drives in condition B, its own B rows of other
    places share B's bits with every B frame; ranked by plain Dice they are its answers (the season bias
    of docs/results.md §10.6); with the bits its recent frames share discounted, it names the lap-1 row
    of the place it is at."""
    right, own = second_lap({"condition_frames": 0})
    assert right < 40 and own > 150  # (a path chasing the trail just laid ends, §11.6: a few right)
    right, own = second_lap({"condition_frames": 20})
    assert right > 150 and own < 40


@pytest.mark.parametrize("represented", [True, False])
def test_whether_the_last_frame_earned_the_places_conditions_survives_a_snapshot_and_a_crash(
        represented: bool) -> None:
    """`Stream.represented` (docs/design/science.md §11.8) is in the memory's snapshot and in the state a
    crash recovery resumes a stream with (`resume_state`, docs/design/service.md §4.4 step 7): the
    stream's next noisy frame is a visit or a row as it would have been without the restart. A
    snapshot or a packed state from before the rule loads without it."""
    m, st = model(), Stream()
    learn_route(m, route(3), st)
    st.represented = represented
    assert load_memory_state(memory_state(m.tm, {"a": st}), 0, 0)[1]["a"].represented is represented
    back = Stream(represented=not represented)
    resume(back, resume_state(st), 0)
    assert back.represented is represented
    old = memory_state(m.tm, {"a": st})
    key = next(k for k in old if k.startswith("streammeta."))
    old[key] = old[key][:4]  # a snapshot written before the flag
    assert load_memory_state(old, 0, 0)[1]["a"].represented is False


def test_the_condition_survives_a_snapshot_of_the_streams_and_weighs_columns_of_cells():
    m, st = model(), Stream()
    learn_route(m, route(6), st)
    _, streams = load_memory_state(memory_state(m.tm, {"a": st}), 0, m.condition_frames)
    back = streams["a"].condition
    assert back is not None and back.seen == 6 and np.array_equal(back.rates, st.condition.rates)
    # off (condition_frames 0): not loaded, and a stream keeps none
    assert load_memory_state(memory_state(m.tm, {"a": st}), 0, 0)[1]["a"].condition is None
    off, st_off = model(localiser={"condition_frames": 0}), Stream()
    learn_route(off, route(3), st_off)
    assert st_off.condition is None
    # the TM's winner cells are weighed by their column (4 cells each), the code itself bit by bit
    assert (model().cells_per_column(), model("none").cells_per_column()) == (4, 1)


# ---------------------------------------------------------------- a stream's short-term memory (§11.6)

REVISIT = 0.91  # the service's default revisit threshold (service.maps.config), at which a revisit is called


def slow_route(places: int, copies: int, rho: float, seed: int) -> np.ndarray:
    """(places · copies, K) a route whose places drift (each place's vector is `rho` times the last plus
    fresh noise: neighbours stay alike, as along a plateau or a corridor), each seen `copies` times with
    a little noise: a robot that posts `copies` frames per place (a slower robot, a faster camera)."""
    rng = np.random.default_rng(seed)
    p, out = rng.normal(size=K), []
    for _ in range(places):
        p = rho * p + np.sqrt(1.0 - rho**2) * rng.normal(size=K)
        out += [p + 0.3 * rng.normal(size=K) for _ in range(copies)]
    return np.asarray(out, np.float32)


def drive(m: MapModel, frames: np.ndarray, st: Stream, stream: str = "a", codes: dict | None = None,
          learn: bool = True) -> list:
    """One stream over `frames` at the service's revisit threshold; `codes`: the stored rows' codes."""
    codes = {} if codes is None else codes
    steps = []
    for y in frames:
        seq = max(codes, default=0) + 1
        steps.append(observe(m, st, y, learn=learn, stream=stream, top_k=3, seq=seq if learn else None,
                             code_of=codes.__getitem__, threshold=REVISIT))
        if learn and steps[-1].visit is None:
            codes[seq] = steps[-1].code
    return steps


def revisits(steps: list) -> int:
    return sum(s.place is not None and s.place.is_revisit(REVISIT) for s in steps)


def on_a_revisit(m: MapModel, row: int = 3, called: bool = True) -> Stream:
    """A stream whose best path (5 frames old, on `row`) called a revisit (`called`), or whose last
    revisit was called on another path (False): what an answer `step` is patched to give is read
    against it (docs/design/science.md §11.8)."""
    st = Stream(localiser=m.place_map.new_state())
    loc = st.localiser
    loc.rows[0], loc.ages[0], loc.scores[0], loc.frames = row, 5, 0.0, 9
    loc.revisit = loc.best_path() if called else (loc.frames - 7, 1)
    return st


def test_a_slower_robot_on_a_route_of_alike_places_never_revisits_its_own_trail() -> None:
    """Three frames per place, neighbouring places alike: the rows a few places back stay above the
    median candidate on every frame, and a path in step with the stream behind its rival window was an
    echo called as a revisit (issue 35: 24-56 per seed at rho 0.9), and frames were consolidated into
    rows of other places. The short-term memory (the rows made in the stream's last learned frames) is
    no candidate and no consolidation target, and a path that starts behind it is followed as an echo."""
    without = 0
    for seed in range(4):
        frames = slow_route(120, 3, 0.9, seed)
        without += revisits(drive(model("none", localiser={"short_term": 0}), frames, Stream()))
        after = drive(model("none"), frames, Stream())
        assert revisits(after) == 0
        assert sum(s.visit is not None for s in after) <= 3  # (before: 43-116 frames merged into other rows)
    assert without > 0  # the memory is what keeps them out


def test_a_real_loop_longer_than_the_short_term_memory_still_closes() -> None:
    """A 40-place loop driven twice: the second lap names the first lap's rows, confidently."""
    for seed in range(3):
        lap = slow_route(40, 1, 0.8, seed)
        again = lap + 0.3 * np.random.default_rng(seed + 100).normal(size=lap.shape).astype(np.float32)
        steps = drive(model("none"), np.concatenate([lap, again]), Stream())
        right = sum(s.place is not None and s.place.is_revisit(REVISIT) and s.place.seq == i + 1
                    for i, s in enumerate(steps[40:]))
        assert right >= 25
        assert revisits(steps[:40]) == 0


def test_the_short_term_memory_is_the_maps_so_an_eviction_a_switch_and_a_restart_keep_it() -> None:
    """The rows a stream made in its last learned frames are kept by the map (`PlaceMap`), not by
    the stream's state: a stream evicted (a new `Stream`), switched to localising, or rebuilt from the
    store's rows and visits after a restart still has them, and never names one of them."""
    frames = slow_route(30, 1, 0.8, 5)
    # evicted, then localising: a fresh stream state, the same name, over the places it just made rows of
    named = {}
    for n in (0, 20):
        m, codes = model("none", localiser={"short_term": n}), {}
        drive(m, frames, Stream(), codes=codes)
        steps = drive(m, frames[-15:], Stream(), codes=codes, learn=False)
        named[n] = {s.place.seq for s in steps if s.place is not None}
    stm = m.place_map.short_term_rows("a")
    # the default: the rows made over its last 20 moves (frames alike to the one before are no move)
    assert stm.size >= 20 and stm.tolist() == list(range(int(stm[0]), 31))
    assert named[0] & set(stm.tolist()) and not named[20] & set(stm.tolist())
    # rebuilt from the stored rows (as recovery does): the same rows
    rows = [type("Row", (), {"seq": q, "context_prev_seq": q - 1 if q > 1 else None, "input_sdr": c,
                             "stream": "a", "place": None})() for q, c in sorted(codes.items())]
    again = model("none")
    again.place_map.rebuild(rows)
    assert again.place_map.short_term_rows("a").tolist() == stm.tolist()
    # another stream's memory is its own: a second robot on the same route names the first's rows
    other = drive(m, frames[-10:], Stream(), stream="b", codes=codes)
    assert any(s.place is not None and s.place.seq in stm for s in other)


def test_consolidated_frames_move_the_short_term_memory_on_and_a_rebuild_replays_them_in_order() -> None:
    """A stream travelling over rows it visited has moved: those learned frames push its made rows out of
    its short-term memory (else a lap over known ground would keep its last made rows out of reach, and
    a short loop's third lap could not consolidate into them); frames alike to its last move (a stop) do
    not. A rebuild interleaves rows and visits by their clock, so the memory is the live one's."""
    place_map = model("none").place_map
    # every frame unlike the last (12 random bits of the 128): each a move
    codes = [np.sort(np.random.default_rng(q).choice(128, 12, replace=False)) for q in range(41)]
    for q in range(1, 26):
        place_map.add(q, q - 1 if q > 1 else None, codes[q], stream="a")
    assert place_map.short_term_rows("a").tolist() == list(range(6, 26))
    visits = [(25 if k == 0 else k, k + 1, 26, "a", codes[26 + k]) for k in range(15)]  # into rows 1..15
    for v in visits:
        place_map.visit(*v)
    assert place_map.short_term_rows("a").tolist() == list(range(21, 26))
    rows = [type("Row", (), {"seq": q, "context_prev_seq": q - 1 if q > 1 else None, "input_sdr": codes[q],
                             "stream": "a", "place": None})() for q in range(1, 26)]
    again = model("none").place_map
    again.rebuild(rows, visited=visits)
    assert again.short_term_rows("a").tolist() == list(range(21, 26))
    # frames alike to the last move are no move: a stop keeps the rows from before it
    place_map.add(26, 25, codes[25], stream="a")  # a move (unlike the last visit's frame), then a stop
    first = int(place_map.short_term_rows("a")[0])
    for q in range(27, 60):
        place_map.add(q, q - 1, codes[25], stream="a")
    assert int(place_map.short_term_rows("a")[0]) == first == 22
    # off: no short-term memory
    assert model("none", localiser={"short_term": 0}).place_map.short_term_rows("a").size == 0


def test_a_slow_robots_short_term_memory_does_not_crowd_the_right_old_row_out_of_the_candidates() -> None:
    """The index pass must return the localiser's `top_k` plus every row it leaves out: a robot parked at
    a place it stored long ago holds dozens of rows of the stop in its memory, each more like its frames
    than the old row, and a pass sized for `short_term` rows (not the memory's size) returned only them,
    so the right place was never a candidate (review of issue 35; here the old row ranks 55th)."""
    m, codes, st = model("none", localiser={"top_k": 5, "exclusion": 0}), {}, Stream()
    rng = np.random.default_rng(11)
    here = rng.normal(size=K)
    old = (here + 0.6 * rng.normal(size=K))[None, :].astype(np.float32)
    elsewhere = route(30, seed=12)
    parked = (here + 0.2 * rng.normal(size=(60, K))).astype(np.float32)
    learn = dict(threshold=None, top_k=0)  # nothing consolidated: every frame a row
    for frames in (old, elsewhere, parked):
        for y in frames:
            seq = len(codes) + 1
            codes[seq] = observe(m, st, y, learn=True, stream="a", seq=seq,
                                 code_of=codes.__getitem__, **learn).code
    assert m.place_map.short_term_rows("a").size > 5 + 20  # more than the old margin
    seen = {}
    step = m.place_map.step

    def spy(state, ranked, own, *args):
        seen["candidates"] = {r.seq for r in ranked} - set(own.short_term.tolist())
        return step(state, ranked, own, *args)

    m.place_map.step = spy
    # evicted (or restarted without its state), then localising: no trail of its own leaves the stop's
    # rows out of the pass, only its memory does
    observe(m, Stream(), parked[-1], learn=False, stream="a", top_k=0, code_of=codes.__getitem__)
    assert 1 in seen["candidates"]


def test_two_cameras_that_name_one_trail_never_revisit_each_others_recent_rows() -> None:
    """A robot that posts as two streams (two cameras over one route, `metadata.trail`): each stream's
    rows are the other's best candidates, and as two trails the second camera "revisits" the first's
    rows of a moment ago. Named as one trail, the memory of both (over its 20 m of path) is no candidate
    of either."""
    from models.localisation.motion import Motion

    frames = slow_route(60, 1, 0.8, 3)
    rng = np.random.default_rng(4)
    named = {}
    for trail in (None, "robot"):
        m, codes, cams = model("none"), {}, {"front": Stream(), "rear": Stream()}
        steps = {"front": [], "rear": []}
        for i, y in enumerate(frames):
            for name in cams:
                seq = len(codes) + 1
                view = y + 0.2 * rng.normal(size=K).astype(np.float32) if name == "rear" else y
                step = observe(m, cams[name], view, learn=True, stream=name, top_k=3, seq=seq,
                               code_of=codes.__getitem__, threshold=REVISIT,
                               motion=Motion((float(i), 0.0), float(i), trail))
                if step.visit is None:
                    codes[seq] = step.code
                steps[name].append(step)
        named[trail] = revisits(steps["front"]) + revisits(steps["rear"])
    assert named[None] > 0 and named["robot"] == 0


def test_a_stream_reads_the_chains_its_robots_other_cameras_lay_as_its_trail() -> None:
    """The mirror rule (§11.13) reads `OwnTrail.others`: the chains the streams that name
    the same trail are laying, and none where a stream names its own."""
    from models.localisation.motion import Motion

    frames = route(12, seed=5)
    for trail in (None, "robot"):
        m, codes, cams = model("none"), {}, {"front": Stream(), "rear": Stream()}
        seen: list[frozenset[int]] = []
        step = m.place_map.step

        def spy(state, ranked, own, *args, _seen=seen, _step=step):
            _seen.append(frozenset() if own is None else own.others)
            return _step(state, ranked, own, *args)

        m.place_map.step = spy
        for i, y in enumerate(frames):
            for name in cams:
                seq = len(codes) + 1
                got = observe(m, cams[name], y, learn=True, stream=name, top_k=3, seq=seq,
                              code_of=codes.__getitem__, threshold=None,
                              motion=Motion((float(i), 0.0), float(i), trail))
                if got.visit is None:
                    codes[seq] = got.code
        chains = {int(m.place_map.graph.trail[q]) for q in codes}
        if trail is None:
            assert not any(seen)
        else:  # from each camera's second frame on, the other camera's chain
            assert len(chains) == 2 and all(len(o) == 1 and o <= chains for o in seen[2:])


@pytest.mark.parametrize(("fraction", "consolidated"), [(0.5, True), (0.9, False)])
def test_an_unconfident_frame_is_consolidated_only_above_the_maps_unsure_fraction_of_the_threshold(
        fraction: float, consolidated: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """The consolidation gate (docs/design/science.md §11.8) reads the map's `unsure_fraction`: a frame
    answered at confidence 0.6 (no revisit at 0.91) that looks like a stored appearance is a visit of it
    where 0.6 reaches the fraction of the threshold (0.455 at the default 0.5, the `threshold / 2` it
    was), and a row of its own where it does not (0.819 at 0.9)."""
    m = model("none", localiser={"unsure_fraction": fraction})
    learn_route(m, route(6), Stream())
    place = Place(seq=3, confidence=0.6, support=5, place=m.place_map.place_of(3))
    monkeypatch.setattr(m.place_map, "step", lambda *args, **kwargs: place)
    monkeypatch.setattr(m.place_map, "consolidation", lambda *args, **kwargs: 3)
    step = observe(m, on_a_revisit(m), route(1, seed=9)[0], learn=True, stream="b", top_k=3, seq=7,
                   code_of=CODES.__getitem__, threshold=REVISIT)
    assert (step.visit == 3) is consolidated


def test_a_restored_stream_at_its_routes_end_is_still_there_on_its_first_frame() -> None:
    """A stream's last look is not stored (`Stream.look`), so after a restart its first frame is judged
    against nothing. It is its look, not a move (docs/design/science.md §11.13): a robot parked at its
    route's end (a dock), on the route's last row, a dead end its path cannot advance from, would
    otherwise fall a move behind it for good and call no revisit there again."""
    m, frames = model(), route(12, seed=4)
    learn_route(m, frames, Stream())
    st = Stream()
    kw = {"learn": False, "stream": "b", "top_k": 3, "code_of": CODES.__getitem__, "threshold": REVISIT}
    steps = [observe(m, st, y, **kw) for y in frames]
    assert steps[-1].place.seq == 12 and steps[-1].place.advancing
    _, streams = load_memory_state(memory_state(m.tm, {"b": st}), 0, 0)
    back = streams["b"]
    assert back.look is None and back.localiser.frames == st.localiser.frames
    lag = float(back.localiser.lags[0])  # the best path's, on row 12
    again = [observe(m, back, frames[-1], **kw) for _ in range(2)]
    assert all(s.place.seq == 12 and s.place.advancing and s.place.is_revisit(REVISIT) for s in again)
    assert back.look is not None and float(back.localiser.lags[0]) <= lag


@pytest.mark.parametrize(("confidence", "advancing", "visit", "joined"),
                         [(0.6, True, 3, True), (0.6, False, None, False), (0.95, False, None, False),
                          (0.95, True, None, True)])
def test_a_path_that_lags_its_stream_consolidates_and_joins_nothing(
        confidence: float, advancing: bool, visit: int | None, joined: bool,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """An answer whose path fell behind its stream (`Place.advancing` False, docs/design/science.md
    §11.13) is unsure whatever its confidence: its frame is not consolidated into the place it names and
    joins no place; the same answer in step with its stream is a visit (above the unsure fraction) or a
    revisit that joins the place (at or above the threshold, here a frame unlike every appearance)."""
    m = model("none")
    learn_route(m, route(6), Stream())
    place = Place(seq=3, confidence=confidence, support=5, place=m.place_map.place_of(3), advancing=advancing)
    monkeypatch.setattr(m.place_map, "step", lambda *args, **kwargs: place)
    monkeypatch.setattr(m.place_map, "consolidation", lambda *args, **kwargs: 3 if confidence < 0.9 else None)
    step = observe(m, on_a_revisit(m), route(1, seed=9)[0], learn=True, stream="b", top_k=3, seq=7,
                   code_of=CODES.__getitem__, threshold=REVISIT)
    assert step.visit == visit
    assert (step.joined >= 0) is joined


@pytest.mark.parametrize("pace", [1.0, 2.0])
def test_a_stream_at_another_pace_than_its_maps_joins_no_warm_up_rows(
        pace: float, monkeypatch: pytest.MonkeyPatch) -> None:
    """A confident revisit folds the warm-up rows its path explains (docs/design/science.md §11.8), read
    one row a move back along the path; a stream at another pace (§11.2 step 2, learned as an average that
    lags the robot's) knows where its path stood only that well, and joins none: those rows stay places
    of their own (the stress suite's `faster` case merged places so, docs/results.md §10.28)."""
    m = model("none")
    learn_route(m, route(6), Stream())
    place = Place(seq=3, confidence=0.99, support=5, place=m.place_map.place_of(3))
    monkeypatch.setattr(m.place_map, "step", lambda *args, **kwargs: place)
    asked = []
    explained = m.place_map.explained
    monkeypatch.setattr(m.place_map, "explained", lambda *a, **kw: asked.append(a) or explained(*a, **kw))
    st = on_a_revisit(m)
    st.localiser.pace = pace
    step = observe(m, st, route(1, seed=9)[0], learn=True, stream="b", top_k=3, seq=7,
                   code_of=CODES.__getitem__, threshold=REVISIT)
    assert step.place.is_revisit(REVISIT) and (len(asked) == 1) is (pace == 1.0) and step.joins == ()


@pytest.mark.parametrize(("frame", "visit"), [(3, 4), (2, 3), (4, None)])
def test_a_confident_frame_like_the_row_one_link_from_its_path_is_a_visit_of_it_not_a_new_appearance(
        frame: int, visit: int | None, monkeypatch: pytest.MonkeyPatch) -> None:
    """Consolidation (docs/design/science.md §11.8) reads the place's appearances and the rows one link
    from the row its path ends on: the path is sure of its row give or take one (the robot's pace
    against the map's), so a frame like the row just ahead of it is that row's visit, not a new row of
    the place (issue 36: on noisy passes such frames were a new appearance each pass). Two links away
    is no visit. The path names row 3; the frame is route frame `frame` again (row frame + 1)."""
    m = model("none")
    frames = route(6)
    learn_route(m, frames, Stream())
    place = Place(seq=3, confidence=0.99, support=5, place=m.place_map.place_of(3))
    monkeypatch.setattr(m.place_map, "step", lambda *args, **kwargs: place)
    step = observe(m, Stream(), frames[frame], learn=True, stream="b", top_k=3, seq=7,
                   code_of=CODES.__getitem__, threshold=REVISIT)
    assert step.visit == visit
    assert (step.joined == place.place) is True  # a visit of its neighbour or a new appearance: the place


@pytest.mark.parametrize(("shown", "visits"), [
    ("lead near near", [3, 4, None]),  # one under the level after one at it; then a second in a row
    ("near", [None]),  # no frame at the level before it: a stream new to the conditions
    ("lead gap near", [3, None, None]),  # a frame with no answer between (it made a row)
    ("lead unlike", [3, None]),  # under the level and the background: not the place's look at all
])
def test_one_confident_frame_under_the_level_after_one_at_it_is_a_visit_frames_in_a_row_are_an_appearance(
        shown: str, visits: list[int | None], monkeypatch: pytest.MonkeyPatch) -> None:
    """Consolidation (docs/design/science.md §11.8) in the stream's conditions: a confident revisit whose
    code falls under the level right after a frame at it is the noise of one frame (a pass with pixel
    noise stored 1-5 such rows per 400 frames, issue 36), a visit of its place's most alike appearance
    if more alike than the background; a second one in a row is another condition showing, and so is
    the first after a frame that made a row: each a new appearance, a row. The level is set near
    identical (`consolidate` 0.99): `lead` is row 3's frame again (at it), `near` the next route frame
    with pixel noise (under it), `gap` a frame with no answer, `unlike` a frame of no stored place."""
    m = model("none", localiser={"consolidate": 0.99})
    frames = route(6)
    learn_route(m, frames, Stream())
    noise = np.random.default_rng(5).normal(scale=0.3, size=(6, K)).astype(np.float32)
    kinds = shown.split()
    rows = iter(range(3, 3 + len(kinds)))  # the path names rows 3, 4, 5 in turn
    named = [None if k == "gap" else next(rows) for k in kinds]
    answers = iter(named)
    monkeypatch.setattr(m.place_map, "step", lambda *args, **kwargs: None if (r := next(answers)) is None
                        else Place(seq=r, confidence=0.99, support=9, place=m.place_map.place_of(r)))
    st, got = Stream(), []
    for i, (kind, r) in enumerate(zip(kinds, named, strict=True)):
        y = {"lead": frames[2], "gap": route(1, seed=7)[0], "unlike": -frames[3],
             "near": frames[(r or 1) - 1] + noise[i]}[kind]  # row r is route frame r - 1
        step = observe(m, st, y, learn=True, stream="b", top_k=3, seq=7 + i,
                       code_of=CODES.__getitem__, threshold=REVISIT)
        CODES[7 + i] = step.code
        got.append(step.visit)
    assert got == visits


def test_the_paths_own_place_comes_before_a_neighbour_that_looks_more_alike(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Consolidation (docs/design/science.md §11.8) asks the neighbouring places only when the path's own
    place does not represent the frame: where both do (a low-texture corridor, rows a metre apart) the
    path's row is the answer, not the neighbour that happens to look a little more alike (the most alike
    of all three places gave the corridor's lap 2 more consolidations two metres off, issue 36). Row 3
    keeps 80 % of row 4's code; the frame is row 4's frame again."""
    m = model("none")
    frames = route(6)
    learn_route(m, frames, Stream())
    codes = dict(CODES)
    four = codes[4]
    codes[3] = four[: int(0.8 * four.size)]  # like the frame above the level, less than row 4
    place = Place(seq=3, confidence=0.99, support=5, place=m.place_map.place_of(3))
    monkeypatch.setattr(m.place_map, "step", lambda *args, **kwargs: place)
    step = observe(m, Stream(), frames[3], learn=True, stream="b", top_k=3, seq=7,
                   code_of=codes.__getitem__, threshold=REVISIT)
    assert step.visit == 3


@pytest.mark.parametrize(("trail", "consolidated"), [("robot", False), (None, True)])
def test_an_unconfident_frame_is_never_consolidated_into_the_trail_its_robots_other_camera_lays(
        trail: str | None, consolidated: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """Unconfident, a frame is never consolidated into a row of the trail it is laying (docs/design/
    science.md §11.6, §11.8): with two cameras naming one trail (`metadata.trail`), the other camera's
    trail is that trail too (the stress suite's `cameras` case at seed 42: 3 rear frames consolidated
    into front rows 28 places back, beyond the shared short-term memory). As two trails, the rear
    camera's frame may be consolidated into the front's row."""
    from models.localisation.motion import Motion

    m = model("none", localiser={"short_term": 0})  # the rule itself, not the memory in front of it
    front = Stream()
    frames = route(6)
    for i, y in enumerate(frames):  # the front camera lays rows 1-6 on its trail
        step = observe(m, front, y, learn=True, stream="front", top_k=3, seq=i + 1,
                       code_of=CODES.__getitem__, motion=Motion(trail=trail))
        CODES[i + 1] = step.code
    place = Place(seq=3, confidence=0.6, support=5, place=m.place_map.place_of(3))
    monkeypatch.setattr(m.place_map, "step", lambda *args, **kwargs: place)
    monkeypatch.setattr(m.place_map, "consolidation", lambda *args, **kwargs: 3)
    step = observe(m, on_a_revisit(m), frames[2], learn=True, stream="rear", top_k=3, seq=7,
                   code_of=CODES.__getitem__, threshold=REVISIT, motion=Motion(trail=trail))
    assert (step.visit == 3) is consolidated


@pytest.mark.parametrize(("called", "consolidated"), [("on its path", True), ("on another path", False),
                                                       ("never", False)])
def test_an_unconfident_frame_is_consolidated_only_on_the_path_that_called_a_revisit(
        called: str, consolidated: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """A revisit is entered at the threshold and held on its path at `unsure_fraction` of it
    (docs/design/science.md §11.8): an answer at 0.6 like a stored appearance is a visit of it on the
    path that called the stream's last revisit, and a row of its own on a path that never did. A
    robot on ground the map has not seen finds paths over look-alike rows at half the threshold, and
    each frame consolidated there merged two places (docs/results.md §10.25: two robots on one map)."""
    m = model("none")
    learn_route(m, route(6), Stream())
    place = Place(seq=3, confidence=0.6, support=5, place=m.place_map.place_of(3))
    monkeypatch.setattr(m.place_map, "step", lambda *args, **kwargs: place)
    monkeypatch.setattr(m.place_map, "consolidation", lambda *args, **kwargs: 3)
    st = Stream() if called == "never" else on_a_revisit(m, called=called == "on its path")
    step = observe(m, st, route(1, seed=9)[0], learn=True, stream="b", top_k=3, seq=7,
                   code_of=CODES.__getitem__, threshold=REVISIT)
    assert (step.visit == 3) is consolidated


def test_a_robot_on_another_robots_ground_joins_its_places_only_once_its_path_called_a_revisit() -> None:
    """Robot b drives robot a's route with a noisier camera. Before its path calls its first revisit
    nothing says it is on stored ground, and none of its frames is consolidated, however confident
    (before the rule, warm-up frames at half the threshold were); from then on its
    path holds the place through frames under the threshold, which are consolidated into a's rows, the
    row each names a's row of the same place."""
    held = 0
    for seed in range(6):
        lap = slow_route(60, 1, 0.8, seed)
        m, codes = model("none"), {}
        drive(m, lap, Stream(), stream="a", codes=codes)
        again = lap + np.random.default_rng(seed + 100).normal(size=lap.shape).astype(np.float32)
        steps = drive(m, again, Stream(), stream="b", codes=codes)
        first = next(i for i, s in enumerate(steps) if s.place is not None and s.place.is_revisit(REVISIT))
        assert all(s.visit is None for s in steps[:first])
        unsure = [(i, s.visit) for i, s in enumerate(steps[first:], first)
                  if s.visit is not None and not s.place.is_revisit(REVISIT)]
        assert all(abs(row - (i + 1)) <= 1 for i, row in unsure)
        held += len(unsure)
    assert held >= 20


def test_the_path_that_called_a_revisit_survives_a_snapshot_and_a_crash() -> None:
    """Where a stream's path called its last revisit is its localiser's (`LocaliserState.revisit`):
    a snapshot (`memory_state`) and a learned step's resume state (`resume_state`) both keep it, so a
    restart mid-revisit holds the place as the process before it did; a reset forgets it."""
    m = model("none")
    st = on_a_revisit(m)
    _, streams = load_memory_state(memory_state(m.tm, {"b": st}), 0, 0)
    assert streams["b"].localiser.on_revisit_path()
    back = Stream()
    resume(back, resume_state(st), 0)
    assert back.localiser.on_revisit_path() and back.localiser.revisit == st.localiser.revisit
    after = Stream()
    resume(after, resume_state(st, reset=True), 0)
    assert after.localiser is None
    st.localiser.reset()
    assert not st.localiser.on_revisit_path()


@pytest.mark.parametrize("informative", [True, False])
def test_a_revisit_is_held_on_its_path_through_a_dip_under_half_the_threshold(
        informative: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """A revisit is entered at the threshold and held on its path at `unsure_fraction` of it until
    another path calls one or the search starts again (docs/design/science.md §11.8): a frame on the
    path under the fraction makes a row of its own, and the path's next frame above it is still held.
    Ending the revisit at such a dip (a review's proposal) cost merged places on the stress suite's
    `seasons` and `cameras` cases (docs/results.md §10.26)."""
    m = model("none")
    learn_route(m, route(6), Stream())
    st = on_a_revisit(m)
    answers = iter([Place(seq=3, confidence=0.3, support=5, place=m.place_map.place_of(3),
                          informative=informative),
                    Place(seq=4, confidence=0.6, support=6, place=m.place_map.place_of(4))])
    monkeypatch.setattr(m.place_map, "step", lambda *args, **kwargs: next(answers))
    monkeypatch.setattr(m.place_map, "consolidation", lambda *args, **kwargs: 3)
    kw = {"learn": True, "stream": "b", "top_k": 3, "code_of": CODES.__getitem__, "threshold": REVISIT}
    dip = observe(m, st, route(1, seed=9)[0], seq=7, **kw)
    assert dip.visit is None  # under the fraction: a row of its own
    CODES[7] = dip.code
    assert st.localiser.on_revisit_path()
    monkeypatch.setattr(m.place_map, "consolidation", lambda *args, **kwargs: 4)
    assert observe(m, st, route(1, seed=10)[0], seq=8, **kw).visit == 4
