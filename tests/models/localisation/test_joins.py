"""Warm-up joins (docs/design/science.md §11.8): the rows a learning stream made before it knew where it
was, that its confident path then explains, join the old places that path passed through, never a place
of the stream's short-term memory or of the trail the row lies on."""

from __future__ import annotations

import numpy as np
import pytest

from models.localisation import LocaliserOptions, Place, PlaceMap
from models.localisation.graph import SequenceGraph
from models.localisation.motion import NO_MOTION, Motion
from models.localisation.trail import code_dice

#: Codes as wide and as sparse as a served map's (2,048 columns, s 0.15 of 2 × 1,024 projections on): with
#: 24 bits of 256 one unrelated row in a few reached `join_kept` by chance, as a served map's rows do not
WIDTH, BITS = 2048, 307


def code(seed: int) -> np.ndarray:
    return np.sort(np.random.default_rng(seed).choice(WIDTH, BITS, replace=False)).astype(np.int64)


OLD = 40  # rows 1-40: an old route of stream "old"
A = (41, 42, 43)  # stream "a" driving on from it: its short-term memory
WARM = 44  # "a"'s warm-up row after a restart


def build(warm: int = 39, stm_place: int | None = None, flat: frozenset[int] = frozenset(),
          motion: Motion = NO_MOTION) -> tuple[PlaceMap, dict[int, np.ndarray]]:
    """The rows above; the warm-up row is the frame of row `warm`. `stm_place`: row 43 joined that row's
    place. `flat`: the rows that are flat rows (§11.7). `motion`: the warm-up frame's."""
    place_map = PlaceMap(LocaliserOptions.of({"short_term": 20}), WIDTH)
    codes = {r: code(r) for r in range(0, WARM)}
    place_map.add(0, None, codes[0], stream="z")  # seq 0 unused by a store; keeps row ids = seqs
    for r in range(1, OLD + 1):
        place_map.add(r, r - 1 if r > 1 else None, codes[r], stream="old", flat=r in flat)
    for r in A:
        place_map.add(r, r - 1, codes[r], stream="a", place=stm_place if r == A[-1] and stm_place else -1)
    codes[WARM] = codes[warm].copy()
    place_map.add(WARM, None, codes[WARM], stream="a", flat=WARM in flat, motion=motion)
    return place_map, codes


def at(seq: int, support: int = 10) -> Place:
    """The stream's confident answer: its path on row `seq`, `support` frames long."""
    return Place(seq, 0.99, support, place=seq)


def test_a_warm_up_row_joins_the_old_place_the_confident_path_stood_on() -> None:
    place_map, codes = build()
    assert set(place_map.short_term_rows("a").tolist()) == {*A, WARM}
    # the path is on row 40 now, so on the frame before (the warm-up row's) it stood on row 39
    assert place_map.explained("a", at(40), 1, codes.__getitem__) == ([(WARM, 39)], [])
    place_map.fold(WARM, 39, WARM + 1)
    place_map.drop(WARM)  # (the caller's: it adds no appearance)
    assert place_map.place_of(WARM) == place_map.place_of(39) and place_map.graph.members(WARM) == []
    assert WARM not in place_map.short_term_rows("a")
    assert place_map.explained("a", at(40), 1, codes.__getitem__) == ([], [])


def test_a_row_the_path_does_not_cover_or_stood_far_from_is_not_joined() -> None:
    place_map, codes = build()
    # the path began after it
    assert place_map.explained("a", at(40, support=1), 1, codes.__getitem__) == ([], [])
    # the path stood on row 29, not row 39
    assert place_map.explained("a", at(30), 1, codes.__getitem__) == ([], [])
    # never ahead of the path: on row 38 running along the stored direction, it stood on row 37 then;
    # run against it (row 38 reached from row 39) it stood on row 39
    assert place_map.explained("a", at(38), 1, codes.__getitem__) == ([], [])
    assert place_map.explained("a", at(38), -1, codes.__getitem__) == ([(WARM, 39)], [])


@pytest.mark.parametrize(("warm", "flat", "joined"), [
    (40, {38, 39, 40, WARM}, 39),  # like the tunnel's next row (before: joined to it, a place off)
    (10, {38, 39, 40, WARM}, 39),  # like no row near: still the path's
    (40, {38, 40, WARM}, 40),      # the path's row is not flat: a flat row a step off, the most alike
    (40, {WARM}, 40),              # no flat row there: its code decides, as any row's
    (10, {WARM}, None),
    (40, {38, 39, 40}, 40),        # a row that is not flat: its code decides whatever the rows near
])
def test_a_flat_row_joins_the_flat_row_the_path_stood_on_whatever_its_code(
        warm: int, flat: set[int], joined: int | None) -> None:
    """§11.7: a flat row's code is noise, and a noisy tunnel frame may be more like the tunnel's row a
    step off than like the one the path stood on (a short loop's seam merged two places so, docs/results.md
    §11): a flat row joins the flat row the path stood on then, whatever its code."""
    place_map, codes = build(warm=warm, flat=frozenset(flat))
    # the path is on row 40 now, so on the warm-up row's frame it stood on row 39
    got = place_map.explained("a", at(40), 1, codes.__getitem__)
    assert got == ([] if joined is None else [(WARM, joined)], [])


def test_a_join_never_targets_the_short_term_memory() -> None:
    place_map, codes = build(warm=A[1])  # the warm-up frame looks like the stream's own recent row 42
    assert place_map.explained("a", at(A[2]), 1, codes.__getitem__) == ([], [])
    place_map, codes = build(stm_place=39)  # the stream's row 43 shows old row 39's place
    assert not place_map.graph.alone(np.array([A[-1]]))[0]
    assert place_map.explained("a", at(40), 1, codes.__getitem__) == ([], [])


@pytest.mark.parametrize("one_frame", [True, False])
def test_two_rows_of_one_pass_never_join_one_place(one_frame: bool) -> None:
    """Two warm-up rows a move apart that both look like old row 39 (a stretch where the route barely
    changes): the newer joins 39's place, the older joins no place, whether both are joined on one
    confident frame or the older on the next. Before, each was joined to 39 (the second after the first
    had been folded away, so no held row showed the place), and the place then spanned both moves: the
    stress suite's two cameras merged a place so (docs/results.md §10.31)."""
    place_map, codes = build()  # the warm-up row 44 is the frame of row 39
    codes[WARM + 1] = seen_otherwise(39, 0.5)  # and the next, a move on, is represented by row 39 too
    if one_frame:
        place_map.add(WARM + 1, WARM, codes[WARM + 1], stream="a")
        # the path on row 40 now: on row 39 at row 45's frame, on row 38 at row 44's
        assert place_map.explained("a", at(40), 1, codes.__getitem__) == ([(WARM + 1, 39)], [])
        return
    assert place_map.explained("a", at(40), 1, codes.__getitem__) == ([(WARM, 39)], [])
    place_map.fold(WARM, 39, WARM + 1)
    place_map.drop(WARM)  # (the caller's: it adds no appearance)
    place_map.add(WARM + 1, WARM, codes[WARM + 1], stream="a")
    # the path on row 41 now: on row 40 at row 45's frame, give or take one
    assert place_map.explained("a", at(41), 1, codes.__getitem__) == ([], [])


@pytest.mark.parametrize("more", [14, 15])
def test_a_join_reaches_back_over_warmup_plus_exclusion_rows_only(more: int) -> None:
    """The warm-up row, then `more` rows of the stream: with 15 it is the 16th newest (reach: 15)."""
    assert PlaceMap(LocaliserOptions(), WIDTH).reach() == 15
    place_map, codes = build(warm=20)
    for r in range(WARM + 1, WARM + 1 + more):  # the stream goes on making rows, joined to old places
        codes[r] = code(r)
        place_map.add(r, r - 1, codes[r], stream="a", place=1)
    # the path stood on row 20 on the warm-up row's frame, `more` + 1 frames ago
    got = place_map.explained("a", at(20 + more + 1, support=100), 1, codes.__getitem__)
    assert got == ([(WARM, 20)] if more < 15 else [], [])


def test_rejoin_takes_only_a_row_that_is_a_place_of_its_own() -> None:
    g = SequenceGraph.chain(4)
    g.join(3, 0)
    with pytest.raises(ValueError):
        g.rejoin(3, 1)  # already of another place
    with pytest.raises(ValueError):
        g.rejoin(0, 1)  # another row joined it
    g.rejoin(2, 1)
    assert g.place.tolist() == [0, 1, 1, 0] and g.members(1) == [1, 2] and g.members(2) == []


def seen_otherwise(row: int, share: float) -> np.ndarray:
    """Row `row`'s code with some of its bits moved elsewhere: about `share` of the way from the background
    likeness (random codes this sparse: BITS / WIDTH) to the same code (the scale of `consolidate`)."""
    base, rng, b = code(row), np.random.default_rng(10_000 + row), BITS / WIDTH
    keep = rng.choice(base, round((b + share * (1 - b)) * BITS), replace=False)
    others = rng.choice(np.setdiff1d(np.arange(WIDTH), base), BITS - keep.size, replace=False)
    return np.sort(np.r_[keep, others]).astype(np.int64)


@pytest.mark.parametrize(("share", "joins", "kept"), [
    (0.5, [(WARM, 39)], []),   # represented: joined, held no more
    (0.18, [], [(WARM, 39)]),  # like it, not represented (another season): joined and kept
    (0.0, [], []),             # unlike it: new ground as far as its code says, a place of its own
])
def test_a_warm_up_row_like_the_old_row_but_not_represented_is_joined_and_kept(
        share: float, joins: list, kept: list) -> None:
    """§11.8: a warm-up row of the place the path stood on, seen in other conditions, was left a place of
    its own (each later pass in those conditions made another: an outside soak's winter lap, 8-14 rows a
    pass); it is now an appearance of the old row's place, so the next pass finds it."""
    place_map, codes = build()
    codes[WARM] = seen_otherwise(39, share)
    assert place_map.explained("a", at(40), 1, codes.__getitem__) == (joins, kept)


def test_a_kept_row_is_an_appearance_of_the_old_place_and_is_not_joined_again() -> None:
    place_map, codes = build()
    codes[WARM] = seen_otherwise(39, 0.18)
    assert place_map.explained("a", at(40), 1, codes.__getitem__) == ([], [(WARM, 39)])
    place_map.fold(WARM, 39, WARM + 1)
    assert place_map.place_of(WARM) == place_map.place_of(39)
    assert place_map.appearances(place_map.place_of(39)) == [39, WARM]  # held, both
    assert place_map.explained("a", at(40), 1, codes.__getitem__) == ([], [])  # not a place of its own


@pytest.mark.parametrize(("flat", "options"), [
    (frozenset({WARM}), {}),             # a flat row's code is noise: never kept by it
    (frozenset(), {"join_kept": 0.25}),  # `join_kept` at `consolidate`: no join keeps its row
])
def test_no_kept_join_for_a_flat_row_or_with_join_kept_at_the_consolidate_level(
        flat: frozenset[int], options: dict) -> None:
    place_map, codes = build(flat=flat)
    place_map.options = LocaliserOptions.of({"short_term": 20, **options})
    codes[WARM] = seen_otherwise(39, 0.18)
    assert place_map.explained("a", at(40), 1, codes.__getitem__) == ([], [])


@pytest.mark.parametrize("like", [38, 40])
def test_the_path_names_the_place_a_kept_row_joins_not_its_code(like: int) -> None:
    """A row seen otherwise that is like the place a step off the row the path stood on (39) joins no
    place: kept by its code among the rows either side, noisy rows of a low-texture stretch were kept a
    step before and a step after one place, which then spanned three (merged places, docs/results.md §11)."""
    place_map, codes = build()
    codes[WARM] = seen_otherwise(like, 0.18)
    assert place_map.explained("a", at(40), 1, codes.__getitem__) == ([], [])


def test_a_warm_up_a_robot_stood_through_is_joined_to_where_it_stood_not_as_many_rows_back() -> None:
    """A review: the lag to the row the path stood on was counted in frames, but a path keeps pace with its
    stream's moves, and a frame its poses say stood still is none. A posed robot that stood 3 frames after
    its warm-up row had its row kept-joined 3 places back (row 36: its code is like that place too, as
    on a route that aliases), not to the place it stood at (39)."""
    base, other, rng = code(39), code(36), np.random.default_rng(7)
    ours = rng.choice(base, 80, replace=False)  # about 0.17 of the way to row 39's code, 0.12 to row 36's
    bits = np.union1d(ours, rng.choice(np.setdiff1d(other, ours), 70, replace=False))
    free = np.setdiff1d(np.arange(WIDTH), np.union1d(base, other))
    rest = rng.choice(free, BITS - bits.size, replace=False)
    warm = np.sort(np.r_[bits, rest]).astype(np.int64)
    place_map, codes = build(motion=Motion(pose=(0.0, 0.0), stamp=1.0))
    codes[WARM] = warm
    for row, lo, hi in ((39, 0.1, 0.25), (36, 0.1, 0.25)):  # like both, represented by neither
        b = place_map.codes.background(warm)
        assert lo <= (code_dice(warm, codes[row]) - b) / (1 - b) < hi
    assert place_map.explained("a", at(40), 1, codes.__getitem__) == ([], [(WARM, 39)])
    for t in (2.0, 3.0, 4.0):  # it stands: visits of its row, no move by its poses
        place_map.visit(WARM, WARM, int(t), stream="a", code=warm, motion=Motion(pose=(0.2, 0.0), stamp=t))
    assert place_map.explained("a", at(40), 1, codes.__getitem__) == ([], [(WARM, 39)])
    # this frame stood still too: the path stood on row 40 then, which the row is not like
    assert place_map.explained("a", at(40), 1, codes.__getitem__, moved=False) == ([], [])
