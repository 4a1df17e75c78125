"""Compiled kernels of one Temporal Memory step (docs/design/science.md §3.3, §3.5, §3.6): `step` (active
and winner cells, learning) and `activity` (dendrite activity for the next step). The array layout, the
parameter vectors `p` / `ip`, the counters and the synapse primitives are in `_tm_synapses`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from models.memory._tm_synapses import (
    EPS,
    I_ACT,
    I_CPC,
    I_K,
    I_KB,
    I_MIN,
    I_NEW,
    I_S,
    P_CONN,
    P_DEC,
    P_INC,
    P_PDEC,
    B,
    _adapt,
    _create_segment,
    _grow,
)


@njit(cache=True, inline="always")
def count_bits(K):
    """Bits per count in `activity`'s packed per-segment word (a count never exceeds K): 6 in a
    uint16 word when K < 64, 8 in a uint32 when K < 256, else 16 in an int64 (`temporal_memory._layout`
    picks the word)."""
    return 6 if K < 64 else 8 if K < 256 else 16


@njit(cache=True)
def activity(active_cells, learn, iteration, ip, last_used, rx, seg_act, epoch, matching):
    """activateDendrites (docs/design/science.md §3.3): active and matching segments for `active_cells`.

    `seg_act[g]` packs (epoch << 2w | connected << w | potential) so that one random access per
    synapse both tests "first touch in this call" and counts, and no pass is needed to clear counts
    (only when the epoch outgrows its bits, every 15 calls in a uint16 word). The count width w is
    `count_bits(maxSynapsesPerSegment)`: 6 bits in a uint16 word for K < 64 (every preset), 8 in a
    uint32 for K < 256, else 16 in an int64. These random read-modify-writes are most of the call, and
    their cost is the cache the array misses: at 2048x4 with 32 segments per cell a uint16 word keeps
    it to 512 KiB, within one core's L2 (issue 40: 0.47 -> 0.19 ms for 160 active cells after 5,000
    like-for-like steps, against a uint32 word).

    Returns:
        active_segs (a,), active_pot (a,), matching_segs (m,), matching_pot (m,): segment ids sorted
        ascending (so grouped by cell and column) with their counts of active potential synapses;
        n_predictive: number of distinct cells owning an active segment.
    """
    rev, _, bprev, bfill, tail, _ = rx
    S = ip[I_S]
    sh = ip[I_KB] + 1  # an entry's segment: entry >> sh
    thr_act = ip[I_ACT]
    thr_min = ip[I_MIN]
    w = count_bits(ip[I_K])
    cmask = (1 << w) - 1
    epoch[0] += 1
    word = seg_act.itemsize * 8 - (1 if seg_act.itemsize == 8 else 0)  # bits a stamp can use (int64: 63)
    if epoch[0] >= 1 << (word - 2 * w):  # wrap-around: forget every stamp
        seg_act[:] = 0
        epoch[0] = 1
    stamp = epoch[0] << (2 * w)
    n_m = 0
    for i in range(active_cells.size):
        t = tail[active_cells[i]]
        while t != -1:
            start = t * B
            for pos in range(start, start + bfill[t]):
                e = rev[pos]
                g = e >> sh
                v = np.int64(seg_act[g])
                if v < stamp:
                    v = stamp
                v += 1 + ((e & 1) << w)
                seg_act[g] = v
                if (v & cmask) == thr_min:
                    matching[n_m] = g
                    n_m += 1
            t = bprev[t]
    segs = np.sort(matching[:n_m]).astype(np.int64)
    n_act = 0
    for i in range(n_m):
        if (seg_act[segs[i]] >> w) & cmask >= thr_act:
            n_act += 1
    active_segs = np.empty(n_act, np.int64)
    active_pot = np.empty(n_act, np.int32)
    matching_pot = np.empty(n_m, np.int32)
    a = 0
    n_predictive = 0
    last_cell = -1
    for i in range(n_m):
        g = segs[i]
        v = seg_act[g]
        pot = v & cmask
        matching_pot[i] = pot
        if (v >> w) & cmask >= thr_act:
            active_segs[a] = g
            active_pot[a] = pot
            a += 1
            if learn:
                last_used[g] = iteration
            if g // S != last_cell:
                last_cell = g // S
                n_predictive += 1
    return active_segs, active_pot, segs, matching_pot, n_predictive


@njit(cache=True)
def step(columns, learn, prev_active, prev_winner, act_segs, act_pot, match_segs, match_pot,
         iteration, p, ip, rng, presyn, perm, nsyn, last_used, seg_count, rx,
         prev_active_mask, prev_winner_mask, scratch_mask, cand, counters):
    """activateCells (docs/design/science.md §3.3) for sorted `columns`, learning when `learn`.

    Returns:
        active_cells, winner_cells (sorted int64), n_predicted_columns, n_bursting_columns,
        changed (whether the connections were modified).
    """
    rev, rpos, bprev, bfill, tail, pool = rx
    cpc = ip[I_CPC]
    S = ip[I_S]
    Kc = ip[I_K]
    conn = p[P_CONN]
    max_new = ip[I_NEW]
    inc = p[P_INC]
    dec = p[P_DEC]
    pdec = p[P_PDEC]
    zero = np.float32(0.0)
    hit = np.empty(Kc, np.int64)  # a punished segment's active synapses
    for i in range(prev_active.size):
        prev_active_mask[prev_active[i]] = True
    for i in range(prev_winner.size):
        prev_winner_mask[prev_winner[i]] = True
    n_prev_winner = prev_winner.size

    active = np.empty(columns.size * cpc, np.int64)
    winners = np.empty(columns.size * cpc, np.int64)
    n_a = 0
    n_w = 0
    n_pred = 0
    n_burst = 0
    changed = False
    seg_per_col = S * cpc

    ia = 0
    isg = 0
    ims = 0
    n_cols = columns.size
    n_as = act_segs.size
    n_ms = match_segs.size
    while ia < n_cols or isg < n_as or ims < n_ms:
        c = np.iinfo(np.int64).max
        if ia < n_cols:
            c = min(c, columns[ia])
        if isg < n_as:
            c = min(c, act_segs[isg] // seg_per_col)
        if ims < n_ms:
            c = min(c, match_segs[ims] // seg_per_col)
        a0 = isg
        while isg < n_as and act_segs[isg] // seg_per_col == c:
            isg += 1
        m0 = ims
        while ims < n_ms and match_segs[ims] // seg_per_col == c:
            ims += 1
        is_active = ia < n_cols and columns[ia] == c
        if is_active:
            ia += 1
        if is_active and isg > a0:
            # Predicted column: the cells with active segments fire and win.
            n_pred += 1
            last_cell = -1
            for t in range(a0, isg):
                g = act_segs[t]
                cell = g // S
                if cell != last_cell:
                    active[n_a] = cell
                    winners[n_w] = cell
                    n_a += 1
                    n_w += 1
                    last_cell = cell
                if learn:
                    changed = True
                    _adapt(g, inc, dec, prev_active_mask, p, ip, presyn, perm, nsyn, seg_count,
                           rev, rpos, bprev, bfill, tail, pool, counters)
                    if nsyn[g] > 0:
                        _grow(g, max_new - act_pot[t], prev_winner, prev_winner_mask, scratch_mask, cand,
                              p, ip, rng, presyn, perm, nsyn, rev, rpos, bprev, bfill, tail, pool, counters)
        elif is_active:
            # Burst: every cell fires; one winner learns the transition.
            n_burst += 1
            first = c * cpc
            for i in range(cpc):
                active[n_a] = first + i
                n_a += 1
            if ims > m0:
                best = m0
                for t in range(m0 + 1, ims):
                    if match_pot[t] > match_pot[best]:
                        best = t
                g = match_segs[best]
                winner = g // S
                if learn:
                    changed = True
                    _adapt(g, inc, dec, prev_active_mask, p, ip, presyn, perm, nsyn, seg_count,
                           rev, rpos, bprev, bfill, tail, pool, counters)
                    if nsyn[g] > 0:
                        _grow(g, max_new - match_pot[best], prev_winner, prev_winner_mask, scratch_mask,
                              cand, p, ip, rng, presyn, perm, nsyn, rev, rpos, bprev, bfill, tail, pool,
                              counters)
            else:
                fewest = np.iinfo(np.int64).max
                n_ties = 0
                for i in range(cpc):
                    sc = np.int64(seg_count[first + i])
                    if sc < fewest:
                        fewest = sc
                        n_ties = 0
                    if sc == fewest:
                        cand[n_ties] = first + i
                        n_ties += 1
                # A localisation step draws nothing (docs/design/science.md §3.6): lowest cell among the ties.
                winner = cand[rng.integers(0, n_ties)] if learn else cand[0]
                if learn and n_prev_winner > 0:
                    changed = True
                    g = _create_segment(winner, iteration, ip, presyn, nsyn, last_used, seg_count,
                                        rev, rpos, bprev, bfill, tail, pool, counters)
                    _grow(g, min(max_new, n_prev_winner), prev_winner, prev_winner_mask, scratch_mask,
                          cand, p, ip, rng, presyn, perm, nsyn, rev, rpos, bprev, bfill, tail, pool, counters)
            winners[n_w] = winner
            n_w += 1
        elif learn and pdec > 0:
            # Matching segments of a column that stayed silent predicted wrongly: punish them.
            # This runs for every chance match, so the common case (nothing decays below EPS) is
            # written out here; a segment that would lose a synapse takes the general path.
            changed = changed or ims > m0
            # The first pass lists the segment's active synapses (a few of its K), so the second
            # touches only those.
            for t in range(m0, ims):
                g = match_segs[t]
                base = g * Kc
                n = np.int64(nsyn[g])
                dies = False
                n_hit = 0
                for k in range(n):
                    q = base + k
                    if prev_active_mask[presyn[q]]:
                        if perm[q] - pdec < EPS:
                            dies = True
                            break
                        hit[n_hit] = q
                        n_hit += 1
                if dies:
                    _adapt(g, -pdec, zero, prev_active_mask, p, ip, presyn, perm, nsyn, seg_count,
                           rev, rpos, bprev, bfill, tail, pool, counters)
                    continue
                for i in range(n_hit):
                    q = hit[i]
                    old = perm[q]
                    v = old - pdec
                    if (v >= conn) != (old >= conn):
                        rev[rpos[q]] ^= 1
                    perm[q] = v

    for i in range(prev_active.size):
        prev_active_mask[prev_active[i]] = False
    for i in range(prev_winner.size):
        prev_winner_mask[prev_winner[i]] = False
    return active[:n_a].copy(), winners[:n_w].copy(), n_pred, n_burst, changed
