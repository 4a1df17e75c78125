"""Places (docs/design/science.md §11.8, §11.9): rows of one place are no rivals of each other, a place
keeps at most `appearances` rows (the least recently used goes), forgetting takes whole places least
recently used first, and the index drops rows it no longer holds."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from models.localisation import (
    InvertedIndex,
    LocaliserOptions,
    Place,
    PlaceMap,
    SequenceGraph,
    SequenceLocaliser,
)
from tests.models.localisation.test_localiser import place_similarity, run


def three_passes(n: int, joined: bool) -> SequenceGraph:
    """Rows 0..3n-1: the same route of n places stored three times (passes 1, 2, 3), each a chain; with
    `joined` every row of passes 2 and 3 is known to show pass 1's place."""
    g = SequenceGraph()
    for p in range(3):
        for i in range(n):
            g.append(p * n + i, -1 if i == 0 else p * n + i - 1, place=i if joined and p else -1)
    return g


def test_other_passes_of_a_place_are_no_rivals():
    n = 40
    db = np.tile(np.arange(n), 3)
    S = place_similarity(db, np.arange(n), seed=3)
    alone = run(S, three_passes(n, joined=False))  # rows: each pass's row a rival of the others
    places = run(S, three_passes(n, joined=True))
    conf_rows = np.array([p.confidence for p in alone[10:]])
    conf_places = np.array([p.confidence for p in places[10:]])
    assert np.median(conf_rows) < 0.7 and conf_rows.max() < 0.9 < conf_places.min()
    for i, p in enumerate(places):
        if p is not None:
            assert p.place == int(p.seq) % n  # the place names pass 1's row, whichever pass matched
            assert abs(p.place - i) <= 1


def test_a_place_s_rows_join_drop_and_link_as_told():
    g = SequenceGraph.chain(5)
    g.append(5, 2, place=2, joins=False)  # a consolidated stream made row 5 after visiting row 2
    assert g.place.tolist() == [0, 1, 2, 3, 4, 2] and g.members(2) == [2, 5]
    assert g.trail[5] == 5 and g.next[2] == 3  # its own trail; row 2's route stays whole
    g.append(6, 5)
    g.link(6, 4)  # then it moved onto row 4: a neighbour, not a successor
    assert g.next[6] == -1 and 4 in g.within(6, 1).tolist()
    g.link(6, 3, successor=True)  # a successor where it had none
    assert g.next[6] == 3 and g.walk(np.array([5]), np.array([1]), 2).tolist() == [3]
    g.drop(2)
    assert g.members(2) == [5] and g.place[2] == 2  # its links stay: paths still walk through it


def place_map_with(appearances: int, **options: Any) -> PlaceMap:
    loc = PlaceMap(LocaliserOptions.of({"appearances": appearances, **options}), 64)
    for seq in range(1, 4):  # places 1, 2, 3
        loc.add(seq, None if seq == 1 else seq - 1, np.array([seq]), stream="a")
    return loc


def test_the_cap_drops_the_least_recently_used_appearance_never_the_new_one():
    loc = place_map_with(appearances=2)
    loc.add(4, None, np.array([1]), stream="b", place=1)  # place 1: rows 1, 4
    loc.touch(1, 10)  # row 1 used later than row 4
    loc.add(5, None, np.array([1]), stream="c", place=1)
    assert loc.over_cap(1, 5) == [4]  # the least recently used of 1 and 4; never 5
    loc.drop(4)
    assert loc.appearances(1) == [1, 5] and loc.over_cap(1, 5) == [] and loc.held == 4


def test_the_cap_spares_the_row_the_step_s_frame_is_consolidated_into():
    """A kept warm-up join (§11.8) fills a place on a step whose frame is consolidated into one of its
    appearances: that one stays, the next least recently used goes."""
    loc = place_map_with(appearances=2)
    loc.add(4, None, np.array([1]), stream="b", place=1)  # place 1: rows 1, 4
    loc.touch(4, 10)  # row 1 the least recently used
    loc.add(5, None, np.array([1]), stream="c", place=1)
    assert loc.over_cap(1, 5) == [1]
    assert loc.over_cap(1, 5, 1) == [4]


def test_the_cap_drops_as_many_as_the_place_is_over_whatever_the_rows_it_spares():
    """A review: two rows kept into one place in one step were capped one at a time, and the first cap's
    drop of the second kept row still counted at the second: the place lost one appearance too many. Once
    for the place, sparing both, it drops what it is over."""
    loc = place_map_with(appearances=3)
    loc.add(4, None, np.array([1]), stream="b", place=1)  # place 1: rows 1, 4
    loc.add(5, None, np.array([5]), stream="c")
    loc.add(6, None, np.array([6]), stream="c")
    for row in (5, 6):  # kept joins into place 1: 4 appearances, one over
        loc.fold(row, 1, 10)
    loc.touch(4, 9)
    assert loc.over_cap(1, 5, 6) == [4]  # one, never the kept rows
    loc.drop(4)
    assert loc.appearances(1) == [1, 5, 6] and loc.over_cap(1, 5, 6) == []


def test_forgetting_takes_whole_places_least_recently_used_first():
    loc = place_map_with(appearances=8)
    loc.add(4, None, np.array([1]), stream="b", place=1)  # place 1 used at 4
    loc.touch(2, 9)  # place 2 used last
    # place 3 (used at 3) goes first, then place 1 (its latest row used at 4), whole
    assert loc.least_recent(1) == [3]
    assert loc.least_recent(2) == [3, 1, 4]
    for s in loc.least_recent(2):
        loc.drop(s)
    assert loc.places() == 1 and loc.least_recent(5) == [2]


def test_removed_rows_are_no_candidates_and_compaction_ranks_as_a_fresh_index():
    rng = np.random.default_rng(0)
    cells = [np.sort(rng.choice(512, 20, replace=False)) for _ in range(40)]
    idx = InvertedIndex(512, 40)
    for seq, c in enumerate(cells, 1):
        idx.add(seq, c, "a" if seq % 2 else "b")
    gone = list(range(1, 40, 3))
    idx.remove(gone[:5])  # below a quarter: marked, not compacted
    assert len(idx) == 35 and all(m.seq not in gone[:5] for m in idx.rank(cells[0], 40))
    idx.remove(gone)  # a quarter or more: compacted
    fresh = InvertedIndex(512, 40)
    for seq, c in enumerate(cells, 1):
        if seq not in gone:
            fresh.add(seq, c, "a" if seq % 2 else "b")
    for q in cells[:10]:
        assert idx.rank(q, 10) == fresh.rank(q, 10)
        assert idx.rank(q, 10, exclude_own=("a", 20)) == fresh.rank(q, 10, exclude_own=("a", 20))
    assert len(idx) == len(fresh) and idx.postings() == fresh.postings()
    idx.add(41, cells[0], "a")  # room again after the compaction
    assert idx.rank(cells[0], 1)[0].seq in (1, 41)


def test_a_full_index_compacts_its_removed_rows_before_refusing():
    idx = InvertedIndex(64, 3)
    for seq in (1, 2, 3):
        idx.add(seq, [seq], "a")
    idx.remove([1])
    idx.add(4, [4], "a")
    assert len(idx) == 3 and [m.seq for m in idx.rank([4], 3)] == [4]


def test_the_localiser_answers_the_place_of_its_best_row():
    g = three_passes(10, joined=True)
    state = SequenceLocaliser(LocaliserOptions.of({"warmup": 1})).new_state()
    loc = SequenceLocaliser(LocaliserOptions.of({"warmup": 1}))
    place = loc.step(state, g, np.array([25]), np.array([1.0]))
    assert place is not None and place.seq == 25 and place.place == 5


def test_the_cap_rule_forgets_nothing_below_it_and_at_least_one_percent_of_it_at_it():
    """`forgetting.to_forget` (issue 38 item 4: the one home of the rule the writer and the evaluation
    apply): nothing under the cap; at it, whole least recently used places, at least 1 % of the cap."""
    from models.localisation import forgetting

    loc = place_map_with(appearances=8)
    loc.add(4, None, np.array([1]), stream="b", place=1)  # place 1: rows 1 and 4, used at 4
    loc.touch(2, 9)
    index = InvertedIndex(64, 5)
    for seq in range(1, 5):
        index.add(seq, [seq], "a")
    assert forgetting.to_forget(index, loc) == []  # 4 rows held of 5
    index.add(5, [5], "a")
    assert forgetting.to_forget(index, loc) == [3]  # at the cap: at least one row, place 3 whole
    assert [forgetting.batch(c) for c in (1, 99, 100, 250, 1_000_000)] == [1, 1, 1, 2, 10_000]
    big = InvertedIndex(64, 200)  # a cap of 200 forgets at least 2 rows: places 3 and then 1, whole
    for seq in range(1, 201):
        big.add(seq, [seq % 64], "a")
    assert forgetting.to_forget(big, loc) == [3, 1, 4]


def test_the_maps_forget_percent_is_the_batch_the_cap_rule_forgets_and_states() -> None:
    """`forget_percent` (LocaliserOptions; 1 by default): at a cap of 200 rows, 1 % forgets places 3 and
    1 (2 rows at least), 0 % place 3 alone (one row at least), 2 % every place (4 rows); the rule the map
    resource states names the map's value."""
    from models.localisation import forgetting

    big = InvertedIndex(64, 200)
    for seq in range(1, 201):
        big.add(seq, [seq % 64], "a")
    for percent, gone in ((1, [3, 1, 4]), (0, [3]), (2, [3, 1, 4, 2])):
        loc = place_map_with(appearances=8, forget_percent=percent)
        loc.add(4, None, np.array([1]), stream="b", place=1)
        loc.touch(2, 9)
        assert forgetting.to_forget(big, loc) == gone
    assert forgetting.batch(1000, 5) == 50
    assert "at least 5% of max_rows" in forgetting.rule(5) and "at least 1% of" in forgetting.rule(1)


class Row(NamedTuple):
    """A stored row as `PlaceMap.rebuild` reads it."""

    seq: int
    context_prev_seq: int | None
    input_sdr: np.ndarray
    stream: str
    place: int | None


def b_visits_a(named: bool) -> tuple[PlaceMap, dict[int, np.ndarray], list[tuple[Any, ...]]]:
    """Stream a's route, rows 0-9; stream b made row 10 (a second appearance of place 2), had its frames
    consolidated into rows 3-7 (visits that name their stream where `named`), then made row 11 (place 8)
    after row 7. Returns the map, the rows' codes and b's visits."""
    rng = np.random.default_rng(0)
    width = 2048
    codes = {s: np.sort(rng.choice(width, 40, replace=False)).astype(np.int64) for s in range(12)}
    codes[10], codes[11] = codes[2], codes[8]
    pm = PlaceMap(LocaliserOptions.of({"short_term": 0}), code_width=width)
    for s in range(10):
        pm.add(s, s - 1 if s else None, codes[s], stream="a")
    pm.add(10, None, codes[10], stream="b", place=2)
    last, visits = 10, []
    for v in (3, 4, 5, 6, 7):
        visits.append((last, v, 11, "b", codes[v]) if named else (last, v, 11))
        pm.visit(*visits[-1])
        last = v
    pm.add(11, last, codes[11], stream="b", place=8)
    return pm, codes, visits


def test_consolidation_reads_the_route_neighbours_not_a_successor_across_consolidated_frames() -> None:
    """A frame is a visit of the place just before or after its path's row along the route (docs/design/
    science.md §11.8), and only that: stream b made row 10 (a second appearance of place 2), had its
    frames 3-7 consolidated, then made row 11 after row 7, which `add` also makes row 10's successor
    where the visits did not say whose they were (a visit log from before they did). Six places on from
    row 10, row 11's place is no neighbour of it (the successor counts only where it continues the row),
    while row 3, row 2's successor on its route, is one of row 2."""
    pm, codes, _ = b_visits_a(named=False)
    assert pm.graph.next[10] == 11  # the link the rule must not read as the route
    on10 = Place(seq=10, confidence=0.99, support=5, place=2)
    assert pm.consolidation(on10, codes[8], codes.__getitem__) is None
    on2 = Place(seq=2, confidence=0.99, support=5, place=2)
    assert pm.consolidation(on2, codes[3], codes.__getitem__) == 3  # row 2's successor on its route
    assert pm.consolidation(on2, codes[3], codes.__getitem__, neighbours=False) is None


def test_a_streams_last_made_row_leads_where_the_stream_went_next_not_to_its_next_made_row() -> None:
    """§11.8: stream b made row 10, then its frames were consolidated into rows 3-7 of stream a's route,
    then it made row 11. Row 10 leads on to row 3, where b went, so a path on row 10 walks on along the
    route; before, `add` made row 11 its successor, and a path walked from row 10 to row 11, five places
    ahead (on the stress suite's short loop, a false revisit several files ahead). A rebuild from the
    rows and the visits in the order they were learned gives the same links."""
    pm, codes, visits = b_visits_a(named=True)
    assert pm.graph.next[10] == 3 and pm.graph.prev[11] == 7
    assert pm.graph.walk(np.array([10, 10]), np.array([1, 1]), 2).tolist() == [4, 4]
    assert 11 in pm.graph.within(10, 1)  # still its neighbour, as a link to a row it made

    rows = [Row(s, s - 1 if s else None, codes[s], "a", None) for s in range(10)]
    rows += [Row(10, None, codes[10], "b", 2), Row(11, 7, codes[11], "b", 8)]
    again = PlaceMap(LocaliserOptions.of({"short_term": 0}), code_width=2048)
    again.rebuild(rows, visited=visits)
    assert again.graph.next[:12].tolist() == pm.graph.next[:12].tolist()


def test_a_parked_robot_stays_put_however_long_it_stands() -> None:
    """§11.6: the code statistics take one code a move. A robot parked for 300 frames (each a row: its
    short-term memory holds them, nothing is consolidated into it) would otherwise fill them with its one
    place, raise that place's background likeness and its departure level, until its own copies read as
    moves: its memory aged while it stood, and rows from before the stop became its loop candidates."""
    rng = np.random.default_rng(4)
    width = 2048
    others = [np.sort(rng.choice(width, 80, replace=False)) for _ in range(30)]
    spot = np.sort(rng.choice(width, 80, replace=False))

    def copy() -> np.ndarray:  # the parked view again, 12 of its 80 bits moved (Dice 0.85)
        out = set(spot.tolist()) - set(rng.choice(spot, 12, replace=False).tolist())
        while len(out) < spot.size:
            out.add(int(rng.integers(width)))
        return np.array(sorted(out), np.int64)

    pm = PlaceMap(LocaliserOptions(), code_width=width)
    for s, code in enumerate(others):  # the robot's drive up to its stop
        pm.add(s, s - 1 if s else None, code, stream="a")
    for s in range(30, 330):
        pm.add(s, s - 1, copy(), stream="a")
    held = pm.short_term_rows("a")
    assert 11 in held and set(range(30, 330)) <= set(held.tolist())  # its last 20 moves, and the stop
    assert pm.looks.n == 31 and pm.codes.n == 330  # consolidation still reads every row (§11.8)

    codes = [*others, *[copy() for _ in range(300)]]
    again = PlaceMap(LocaliserOptions(), code_width=width)
    again.rebuild([Row(s, s - 1 if s else None, c, "a", None) for s, c in enumerate(codes)])
    assert again.looks.n == 31 and again.short_term_rows("a").tolist() == held.tolist()


def test_a_camera_of_the_robot_that_stopped_lays_no_chain_it_is_read_by() -> None:
    """§11.6: `laid_by_others` names the chains a robot's other cameras (streams naming one trail) are
    laying: while the rear camera posts, its chain; once it stopped and the front camera has moved on past
    the short-term memory, none (its old chain is no trail the robot is laying). Without the memory
    (`short_term` 0) every such chain is kept, as before."""
    from models.localisation.motion import Motion

    rng = np.random.default_rng(8)
    robot = Motion(trail="robot")
    order = ["front", "rear"] * 3 + ["front"] * 12  # then unlike frames: each a move, past a memory of 5
    for short_term in (5, 0):
        pm = PlaceMap(LocaliserOptions.of({"short_term": short_term}), code_width=2048)
        last: dict[str, int | None] = {"front": None, "rear": None}
        for seq, stream in enumerate(order):
            pm.add(seq, last[stream], np.sort(rng.choice(2048, 80, replace=False)), stream=stream,
                   motion=robot)
            last[stream] = seq
            if seq == 5:  # both cameras posting
                rear = int(pm.graph.trail[last["rear"]])
                assert pm.laid_by_others("front", "robot") == {rear}
                assert pm.laid_by_others("front", "front") == set()  # another trail: not the robot's
        assert pm.laid_by_others("front", "robot") == (set() if short_term else {rear})
