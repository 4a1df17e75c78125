"""Every rule of docs/design/science.md §3.3-§3.6, on small memories whose outcome can be worked out by
hand."""

from __future__ import annotations

import numpy as np
import pytest

from models import presets
from models.evaluation.bench import random_sequence
from models.memory import _tm_synapses as syn
from models.memory.temporal_memory import TemporalMemory

CPC = 4


def small(**over) -> TemporalMemory:
    """A 32x4 memory with one-shot connected synapses, so one presentation is enough to predict."""
    params = {
        "columnDimensions": 32,
        "cellsPerColumn": CPC,
        "activationThreshold": 3,
        "minThreshold": 2,
        "initialPermanence": 0.6,
        "connectedPermanence": 0.5,
        "maxNewSynapseCount": 4,
        "permanenceIncrement": 0.1,
        "permanenceDecrement": 0.05,
        "predictedSegmentDecrement": 0.0,
        "maxSegmentsPerCell": 8,
        "maxSynapsesPerSegment": 8,
        "seed": 7,
    }
    params.update(over)
    return TemporalMemory(presets.TmOptions.of(params))


A, B, C, D, E = (np.arange(4) + 4 * i for i in range(5))


def cells_of(columns: np.ndarray) -> np.ndarray:
    return (np.asarray(columns)[:, None] * CPC + np.arange(CPC)).ravel()


def columns_of(cells: np.ndarray) -> np.ndarray:
    return np.unique(np.asarray(cells) // CPC)


def cell_segments(tm: TemporalMemory, cell: int) -> list[dict]:
    """Live segments of `cell` with their synapses, in slot order, read from the TM's slot arrays:
    [{"slot", "last_used", "presyn": (n,) int64, "perm": (n,) float32}, ...]."""
    S, Kc = int(tm._ip[syn.I_S]), int(tm._ip[syn.I_K])
    out = []
    for s in range(S):
        g = cell * S + s
        n = int(tm.nsyn[g])
        if n:
            q = g * Kc
            out.append({"slot": s, "last_used": int(tm.last_used[g]),
                        "presyn": tm.presyn[q:q + n].astype(np.int64), "perm": tm.perm[q:q + n].copy()})
    return out


def learn_sequence(tm: TemporalMemory, seq, times: int = 1) -> list[np.ndarray]:
    out = []
    for _ in range(times):
        tm.reset()
        out = [tm.compute(x, learn=True) for x in seq]
    return out


def snapshot(tm: TemporalMemory) -> dict[str, np.ndarray]:
    return {k: v for k, v in tm.state_dict().items() if not k.startswith("ctx.")}


def assert_same_state(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_unpredicted_columns_burst_with_one_winner_each():
    tm = small()
    winners = tm.compute(A)
    np.testing.assert_array_equal(tm.context.active_cells, cells_of(A))
    assert len(winners) == len(A)
    np.testing.assert_array_equal(columns_of(winners), A)
    assert tm.context.stats.bursting_columns == 4 and tm.context.stats.predicted_columns == 0


def test_predicted_columns_activate_only_predicted_cells():
    tm = small()
    first = learn_sequence(tm, [A, B])
    tm.reset()
    tm.compute(A, learn=False)
    predicted = tm.predictive_cells()
    np.testing.assert_array_equal(predicted, first[1])  # B's winners of the first pass
    winners = tm.compute(B, learn=False)
    np.testing.assert_array_equal(tm.context.active_cells, predicted)
    np.testing.assert_array_equal(winners, predicted)
    assert tm.context.stats.predicted_columns == 4 and tm.context.stats.bursting_columns == 0


def test_learned_sequence_predicts_next_element_and_reset_breaks_context():
    tm = small()
    learn_sequence(tm, [A, B, C, D], times=3)
    tm.reset()
    for x in (A, B, C):
        tm.compute(x, learn=False)
    np.testing.assert_array_equal(columns_of(tm.predictive_cells()), D)
    tm.compute(D, learn=False)
    assert tm.context.stats.bursting_columns == 0
    tm.reset()
    tm.compute(C, learn=False)  # no B before it: C is a surprise again
    assert tm.context.stats.bursting_columns == 4


def test_new_segment_grows_to_previous_winners_up_to_max_new():
    tm = small(maxNewSynapseCount=3)
    wa = tm.compute(A)
    wb = tm.compute(B)
    for cell in wb:
        (seg,) = cell_segments(tm, int(cell))
        assert len(seg["presyn"]) == 3
        assert set(seg["presyn"]) <= set(wa)
        np.testing.assert_allclose(seg["perm"], np.float32(0.6))
    for cell in set(cells_of(B)) - set(wb):
        assert cell_segments(tm, int(cell)) == []


def test_active_segment_reinforced_and_inactive_synapses_decremented():
    tm = small(maxNewSynapseCount=4, maxSynapsesPerSegment=8)
    wa = learn_sequence(tm, [A, B])[0]
    tm.reset()
    tm.compute(A, learn=False)
    cell = int(tm.predictive_cells()[0])
    (seg,) = cell_segments(tm, cell)
    # Make one synapse come from a cell that will not be active: swap A for a pattern sharing 3 columns.
    tm.reset()
    partial = np.array([A[0], A[1], A[2], E[0]])
    tm.compute(partial, learn=True)
    active_prev = set(tm.context.active_cells)
    assert cell in tm.predictive_cells()  # 3 active connected synapses >= activationThreshold 3
    tm.compute(B, learn=True)
    (after,) = cell_segments(tm, cell)
    by_cell = dict(zip(after["presyn"].tolist(), after["perm"].tolist(), strict=False))
    for pre, p0 in zip(seg["presyn"].tolist(), seg["perm"].tolist(), strict=True):
        expected = p0 + 0.1 if pre in active_prev else p0 - 0.05
        assert by_cell[pre] == pytest.approx(expected, abs=1e-6)
    # and it grew towards the new previous winners up to maxNewSynapseCount active synapses
    assert set(wa) & set(after["presyn"].tolist())


def test_bursting_column_winner_is_best_matching_cell_else_least_used():
    # Synapses below connectedPermanence: segments only ever match, never activate.
    tm = small(initialPermanence=0.3, activationThreshold=4, minThreshold=2)
    first = learn_sequence(tm, [A, B])[1]
    second = learn_sequence(tm, [A, B])[1]
    np.testing.assert_array_equal(first, second)  # the matching segment's cell won again
    assert tm.context.stats.bursting_columns == 4
    # A new context (E before B): no matching segment, so the least-used cell of each column wins,
    # which cannot be the cell that already owns a segment.
    tm.reset()
    tm.compute(E)
    third = tm.compute(B)
    assert not set(third) & set(first)


def test_least_used_tie_break_is_lowest_cell_when_not_learning():
    tm = small()
    winners = tm.compute(A, learn=False)
    np.testing.assert_array_equal(winners, A * CPC)


def test_matching_segments_in_inactive_columns_are_punished():
    tm = small(predictedSegmentDecrement=0.05, initialPermanence=0.3, activationThreshold=4, minThreshold=2)
    wb = learn_sequence(tm, [A, B])[1]
    before = {int(c): cell_segments(tm, int(c))[0]["perm"].copy() for c in wb}
    tm.reset()
    tm.compute(A, learn=True)
    tm.compute(C, learn=True)  # B's matching segments predicted wrongly
    for c, p0 in before.items():
        np.testing.assert_allclose(cell_segments(tm, c)[0]["perm"], p0 - np.float32(0.05), atol=1e-6)


def test_decayed_synapses_and_empty_segments_are_destroyed():
    tm = small(predictedSegmentDecrement=0.3, initialPermanence=0.25, activationThreshold=4, minThreshold=2)
    wb = learn_sequence(tm, [A, B])[1]
    tm.reset()
    tm.compute(A, learn=True)
    tm.compute(C, learn=True)  # 0.25 - 0.3 < 1e-5: every synapse dies, then the segment
    for c in wb:
        assert cell_segments(tm, int(c)) == []
    size = tm.size()
    assert size["decay_destroyed"] == 16 and size["empty_destroyed"] == 4


def test_caps_hold_and_least_recently_used_segment_is_evicted():
    tm = small(cellsPerColumn=1, maxSegmentsPerCell=2, maxSynapsesPerSegment=4, columnDimensions=32)
    target = np.array([31])
    contexts = [np.array([0, 1, 2, 3]), np.array([4, 5, 6, 7]), np.array([8, 9, 10, 11])]
    for ctx in contexts[:2]:
        tm.reset()
        tm.compute(ctx)
        tm.compute(target)
    # Use the first segment again (it becomes active), so the second is the least recently used.
    tm.reset()
    tm.compute(contexts[0])
    assert 31 in tm.predictive_cells(), "segment from context 0 should be active"
    tm.compute(target)
    tm.reset()
    tm.compute(contexts[2])
    tm.compute(target)
    kept = [set(s["presyn"].tolist()) for s in cell_segments(tm, 31)]
    assert len(kept) == 2
    assert set(contexts[0].tolist()) in kept and set(contexts[2].tolist()) in kept
    assert tm.size()["evictions"] == 1


def test_caps_are_never_exceeded_on_random_input():
    tm = small(maxSegmentsPerCell=3, maxSynapsesPerSegment=5, maxNewSynapseCount=4, minThreshold=2)
    for x in random_sequence(300, 32, 6, seed=3):
        tm.compute(x)
        size = tm.size()
        assert size["segments"] <= size["segment_capacity"]
    S, K = 3, 5
    nsyn = tm.nsyn.reshape(-1, S)
    assert nsyn.max() <= K
    assert ((nsyn > 0).sum(axis=1) <= S).all()
    assert tm.size()["evictions"] > 0 and tm.size()["overrun_destroyed"] > 0
    # no segment holds the same presynaptic cell twice
    for cell in range(tm.n_cells):
        for seg in cell_segments(tm, cell):
            assert len(set(seg["presyn"].tolist())) == len(seg["presyn"])


def reverse_index(tm: TemporalMemory) -> tuple[dict[int, list[int]], dict[int, int]]:
    """The reverse index as the kernels left it: {cell: sorted entries of its chain} and
    {synapse q: the entry at rpos[q]} for every live synapse."""
    rev, rpos, bprev, bfill, tail, _ = tm._rx
    chains = {}
    for cell in range(tm.n_cells):
        got, t = [], int(tail[cell])
        while t != -1:
            got += rev[t * syn.B:t * syn.B + int(bfill[t])].tolist()
            t = int(bprev[t])
        chains[cell] = sorted(got)
    K = int(tm._ip[syn.I_K])
    live = [g * K + k for g in np.flatnonzero(tm.nsyn) for k in range(int(tm.nsyn[g]))]
    return chains, {int(q): int(rev[rpos[q]]) for q in live}


@pytest.mark.parametrize("K", [5, 8])
def test_reverse_index_kept_equal_to_one_rebuilt_from_the_synapses(K):
    """Every removal (overrun, decay, eviction) and every shift within a segment keeps each presynaptic
    cell's entries and each synapse's `rpos` what a rebuild from the canonical arrays gives (the
    entries name their synapse slot, docs/design/science.md §3.5), for K a power of two or not."""
    tm = small(maxSegmentsPerCell=3, maxSynapsesPerSegment=K, maxNewSynapseCount=4, minThreshold=2,
               activationThreshold=2, initialPermanence=0.21, predictedSegmentDecrement=0.2)
    for x in random_sequence(400, 32, 6, seed=5):
        tm.compute(x)
    size = tm.size()
    assert all(size[k] for k in ("evictions", "overrun_destroyed", "decay_destroyed", "empty_destroyed"))
    kept = reverse_index(tm)
    again = TemporalMemory.from_state(tm.state_dict())
    assert kept == reverse_index(again)
    # Each live synapse's entry names its own segment and slot, with its connected bit.
    kb = syn.slot_bits(K)
    conn = tm._p[syn.P_CONN]
    for q, e in kept[1].items():
        g, k = divmod(q, K)
        assert (e >> (kb + 1), (e >> 1) & ((1 << kb) - 1), e & 1) == (g, k, int(tm.perm[q] >= conn))


def test_overrun_destroys_lowest_permanence_never_previous_winners():
    tm = small(cellsPerColumn=1, maxSynapsesPerSegment=4, maxNewSynapseCount=4, initialPermanence=0.3,
               activationThreshold=4, minThreshold=1, permanenceIncrement=0.1, permanenceDecrement=0.1)
    target = np.array([31])
    tm.compute(np.array([0, 1, 2, 3]))
    tm.compute(target)
    (seg,) = cell_segments(tm, 31)
    assert sorted(seg["presyn"].tolist()) == [0, 1, 2, 3]
    q = (31 * 8 + seg["slot"]) * 4  # flattened synapse slot of the segment's first synapse
    start = {0: 0.05, 1: 0.3, 2: 0.25, 3: 0.9}
    tm.perm[q:q + 4] = np.array([start[c] for c in seg["presyn"].tolist()], dtype=np.float32)
    tm.reset()
    tm.compute(np.array([0, 1, 8, 9]))
    tm.compute(target)
    # adapt: 0 -> 0.15, 1 -> 0.4, 2 -> 0.15, 3 -> 0.8; growing 8 and 9 overruns the cap by two.
    # Synapse 0 ties with 2 at the lowest permanence and is older, but comes from a previous winner.
    (seg,) = cell_segments(tm, 31)
    got = dict(zip(seg["presyn"].tolist(), seg["perm"].tolist(), strict=True))
    assert got == pytest.approx({0: 0.15, 1: 0.4, 8: 0.3, 9: 0.3}, abs=1e-6)
    assert tm.size()["overrun_destroyed"] == 2


def test_learn_false_changes_nothing():
    tm = small()
    learn_sequence(tm, [A, B, C, D], times=2)
    before = snapshot(tm)
    rng_before = tm.rng.bit_generator.state
    tm.reset()
    for x in (A, C, E, B):
        tm.compute(x, learn=False)
    assert_same_state(before, snapshot(tm))
    assert tm.rng.bit_generator.state == rng_before


def test_same_inputs_give_bit_identical_results():
    seq = random_sequence(200, 32, 5, seed=1) * 2
    runs = []
    for _ in range(2):
        tm = small(minThreshold=1)
        runs.append(([tm.compute(x) for x in seq], snapshot(tm)))
    for a, b in zip(runs[0][0], runs[1][0], strict=True):
        np.testing.assert_array_equal(a, b)
    assert_same_state(runs[0][1], runs[1][1])
    other = small(minThreshold=1, seed=8)
    assert any(not np.array_equal(other.compute(x), w) for x, w in zip(seq, runs[0][0], strict=True))


def test_save_load_continues_bit_identically():
    seq = random_sequence(60, 32, 5, seed=4) * 4
    k = 130
    ref = small(minThreshold=1)
    ref_w = [ref.compute(x) for x in seq]
    tm = small(minThreshold=1)
    head = [tm.compute(x) for x in seq[:k]]
    state = {n: np.copy(v) for n, v in tm.state_dict().items()}
    del tm
    restored = TemporalMemory.from_state(state)
    tail = [restored.compute(x) for x in seq[k:]]
    for a, b in zip(head + tail, ref_w, strict=True):
        np.testing.assert_array_equal(a, b)
    assert_same_state(snapshot(restored), snapshot(ref))


def test_named_streams_round_trip_through_the_state():
    tm = small(seed=np.int64(7))  # numpy scalars in the parameters must still serialise
    learn_sequence(tm, [A, B, C, D], times=2)
    s1 = tm.new_context()
    tm.compute(A, learn=False, context=s1)
    state = tm.state_dict(streams={"robot-1": s1})
    restored = TemporalMemory.from_state(state)
    streams = TemporalMemory.load_streams(state)
    assert set(streams) == {"robot-1"}
    np.testing.assert_array_equal(
        restored.compute(B, learn=False, context=streams["robot-1"]), tm.compute(B, learn=False, context=s1))
    assert streams["robot-1"].stats.bursting_columns == 0
    with pytest.raises(ValueError, match="boolean"):
        tm.compute(np.ones(32, dtype=bool))


def test_streams_keep_separate_contexts():
    tm = small()
    learn_sequence(tm, [A, B, C, D], times=2)
    s1, s2 = tm.new_context(), tm.new_context()
    tm.compute(A, learn=False, context=s1)
    tm.compute(C, learn=False, context=s2)
    # s1 expects B, s2 expects D, independently of the order they are stepped in.
    np.testing.assert_array_equal(columns_of(tm.predictive_cells(s2)), D)
    np.testing.assert_array_equal(columns_of(tm.predictive_cells(s1)), B)
    tm.compute(B, learn=False, context=s1)
    assert s1.stats.bursting_columns == 0


def test_other_stream_learning_refreshes_stale_segment_lists():
    tm = small()
    s1, s2 = tm.new_context(), tm.new_context()
    tm.compute(A, learn=True, context=s1)  # s1 saw A; nothing connects from A yet
    tm.compute(A, learn=True, context=s2)
    tm.compute(B, learn=True, context=s2)  # s2 learns A -> B
    winners = tm.compute(B, learn=False, context=s1)  # s1 must see the segments learned meanwhile
    assert s1.stats.predicted_columns == 4
    np.testing.assert_array_equal(columns_of(winners), B)


def test_validation_and_warnings():
    with pytest.raises(ValueError, match="minThreshold"):
        TemporalMemory(presets.TmOptions.of({"minThreshold": 20, "activationThreshold": 13,
                                             "maxSegmentsPerCell": 1, "maxSynapsesPerSegment": 1,
                                             "columnDimensions": 8}))
    with pytest.raises(ValueError, match="initialPermanence"):
        small(initialPermanence=1.5)
    with pytest.raises(ValueError, match="unknown"):
        small(bogus=1)
    grid = TemporalMemory(presets.TmOptions.of(presets.tm_params("cba2020-grid")))
    assert any("never predict" in w for w in grid.warnings)
    with pytest.raises(ValueError, match="out of range"):
        small().compute(np.array([40]))


def test_reported_bytes_match_reference_layout():
    grid = TemporalMemory(presets.TmOptions.of(presets.tm_params("cba2020-grid")))
    size = grid.size()
    assert size["canonical_bytes"] == 688_128  # docs/design/science.md §3.7: C·S·(6K + 10)
    assert size["segment_capacity"] == 8192 * 3 and size["synapse_capacity"] == 8192 * 9
    assert size["bytes"] > size["canonical_bytes"]


def test_grid_preset_never_predicts_but_predicting_preset_does():
    seq = random_sequence(30, 2048, 40, seed=2)
    frac = {}
    for name in ("cba2020-grid", "cortexloc-grid"):
        tm = TemporalMemory(presets.TmOptions.of(presets.tm_params(name)))
        learn_sequence(tm, seq, times=3)
        tm.reset()
        predicted = 0
        for x in seq:
            tm.compute(x, learn=False)
            predicted += tm.context.stats.predicted_columns
        frac[name] = predicted / (len(seq) * 40)
    assert frac["cba2020-grid"] == 0.0
    # docs/design/science.md §3.7: > 90 % predicted from the second repetition
    assert frac["cortexloc-grid"] > 0.9


def test_default_preset_predicts_repeats_of_its_own_codes_and_rarely_by_chance():
    """docs/design/science.md §3.7/§3.8 for `cortexloc-default` at its sLSBH density (2n of 2048 columns
    active).

    At 15 % density with minThreshold 2 most segments match by chance, so bursting columns re-use them
    and an exact repeat is predicted in only about a quarter of its columns (docs/results.md §7 gives
    the trade-off: minThreshold 10 predicts 97 % of repeats but loses most of the cross-season gain).
    What must hold: repeats are predicted far above the chance-prediction rate, which stays low.
    """
    conf = presets.get("cortexloc-default")
    active = 2 * round(conf["slsbh"]["s"] * conf["slsbh"]["k"])
    seq = random_sequence(30, 2048, active, seed=5)
    tm = TemporalMemory(presets.TmOptions.of(presets.tm_params("cortexloc-default")))
    learn_sequence(tm, seq, times=2)

    def predicted_fraction(frames) -> float:
        tm.reset()
        pred = 0
        for x in frames:
            tm.compute(x, learn=False)
            pred += tm.context.stats.predicted_columns
        return pred / (len(frames) * active)

    in_order = predicted_fraction(seq)
    order = np.random.default_rng(0).permutation(len(seq))
    chance = predicted_fraction([seq[i] for i in order])  # chance-prediction rate (§3.8)
    assert chance < 0.1
    assert in_order > 0.2 and in_order > 4 * chance
    assert tm.size()["bytes"] <= 256 * 2**20


def test_planned_bytes_equal_the_allocated_bytes():
    from models.memory.temporal_memory import planned_bytes

    for name in ("cba2020-grid", "cortexloc-grid"):
        params = presets.tm_params(name)
        options = presets.TmOptions.of(params)
        assert planned_bytes(options) == TemporalMemory(options).size()["bytes"]
    small_params = {"columnDimensions": 64, "cellsPerColumn": 3, "maxSegmentsPerCell": 5,
                    "maxSynapsesPerSegment": 7, "minThreshold": 2, "activationThreshold": 3}
    small = presets.TmOptions.of(small_params)
    assert planned_bytes(small) == TemporalMemory(small).size()["bytes"]
    # the paper's Nordland preset is sized without being allocated
    assert planned_bytes(presets.TmOptions.of(presets.tm_params("cba2020-nordland"))) > 3_997_696_000


def test_connected_presyn_lists_a_segments_connected_cells() -> None:
    tm = TemporalMemory(presets.TmOptions.of(presets.tm_params("cortexloc-grid", {"columnDimensions": 64})))
    first = tm.compute(np.array([1, 5, 9]))
    tm.compute(np.array([20, 30, 40]))
    segs = np.flatnonzero(tm.nsyn)
    assert segs.size == 3  # one per bursting column, grown to the previous winners (one-shot: connected)
    g = int(segs[0])
    cells = tm.connected_presyn(g)
    np.testing.assert_array_equal(cells, first)
    K = int(tm.params["maxSynapsesPerSegment"])
    weak = int(np.flatnonzero(tm.presyn[g * K:g * K + int(tm.nsyn[g])] == first[0])[0])
    tm.perm[g * K + weak] = 0.1  # below connectedPermanence
    np.testing.assert_array_equal(tm.connected_presyn(g), first[1:])
    assert tm.connected_presyn(int(np.flatnonzero(tm.nsyn == 0)[0])).size == 0
