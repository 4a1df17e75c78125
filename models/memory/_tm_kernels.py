"""Compiled inner loops of the Temporal Memory (docs/design/science.md §3.3, §3.5, §3.6).

Layout (flattened so that one integer names a segment or a synapse slot):
    segment g = cell * S + slot,            g in [0, C*S)
    synapse q = g * K + k,                  q in [0, C*S*K), k < nsyn[g] (creation order)
The reverse index `rx` makes segment activation cost proportional to the synapses of the active cells
rather than to all synapses, and reads memory contiguously: each presynaptic cell owns a chain of
blocks of B entries, each entry `g*2 + connected` for one synapse from that cell (the connected bit is
kept in step with the permanence, so activation never touches the permanence array). `rpos[q]` is the
entry of synapse q, for O(1) removal (swap with the cell's last entry). All blocks come from one pool
sized ceil(C*S*K / B) + C, enough because only a cell's last block can be partly filled; the index is
fixed-capacity, rebuilt from the canonical arrays on load, and counted in the reported bytes.
`rx` = (rev, rpos, bprev, bfill, tail, pool) with pool[0] the head of the free-block list.

`p` (float32): initialPermanence, connectedPermanence - EPS, permanenceIncrement,
permanenceDecrement, predictedSegmentDecrement.
`ip` (int64): cellsPerColumn, maxSegmentsPerCell, maxSynapsesPerSegment, activationThreshold,
minThreshold, maxNewSynapseCount.
`counters` (int64): 0 segments evicted (LRU), 1 synapses destroyed by overrun, 2 synapses destroyed by
decay, 3 segments destroyed empty.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# NuPIC's EPSILON: permanences below it are destroyed; the connected test is perm >= connected - EPS.
EPS = 1e-5

P_INIT, P_CONN, P_INC, P_DEC, P_PDEC = 0, 1, 2, 3, 4
I_CPC, I_S, I_K, I_ACT, I_MIN, I_NEW = 0, 1, 2, 3, 4, 5
C_EVICT, C_OVERRUN, C_DECAY, C_EMPTY = 0, 1, 2, 3


B = 16  # entries per reverse-index block: one 64-byte cache line of int32

# The small helpers are inlined: a call that passes arrays costs reference-count updates per array,
# which dominated adapt (about 100 ns per synapse) before.


def pool_blocks(n_slot: int, n_cells: int) -> int:
    """Blocks the reverse index needs at most (see module docstring)."""
    return -(-n_slot // B) + n_cells


@njit(cache=True, inline="always")
def _rx_add(q, cell, g, connected, rev, rpos, bprev, bfill, tail, pool):
    t = tail[cell]
    if t == -1 or bfill[t] == B:
        b = pool[0]
        pool[0] = bprev[b]
        bprev[b] = t
        bfill[b] = 0
        tail[cell] = b
        t = b
    pos = t * B + bfill[t]
    rev[pos] = g * 2 + (1 if connected else 0)
    rpos[q] = pos
    bfill[t] += 1


@njit(cache=True, inline="always")
def _rx_remove(q, cell, K, presyn, nsyn, rev, rpos, bprev, bfill, tail, pool):
    """Drop synapse q (from `cell`) from the index; the cell's last entry fills the hole."""
    pos = rpos[q]
    t = tail[cell]
    last = t * B + bfill[t] - 1
    if pos != last:
        moved = rev[last]
        rev[pos] = moved
        # A segment holds at most one synapse per presynaptic cell: find the moved entry's slot.
        g2 = np.int64(moved >> 1)
        base = g2 * K
        for k in range(np.int64(nsyn[g2])):
            if presyn[base + k] == cell:
                rpos[base + k] = pos
                break
    bfill[t] -= 1
    if bfill[t] == 0:
        tail[cell] = bprev[t]
        bprev[t] = pool[0]
        pool[0] = t


@njit(cache=True, inline="always")
def _destroy_synapse(g, k, K, presyn, perm, nsyn, rev, rpos, bprev, bfill, tail, pool):
    """Remove synapse k of segment g; later synapses shift down so creation order is kept."""
    base = g * K
    n = np.int64(nsyn[g])
    q = base + k
    _rx_remove(q, np.int64(presyn[q]), K, presyn, nsyn, rev, rpos, bprev, bfill, tail, pool)
    for j in range(k + 1, n):
        src = base + j
        presyn[src - 1] = presyn[src]
        perm[src - 1] = perm[src]
        rpos[src - 1] = rpos[src]  # the entry (segment id + connected bit) itself is unchanged
    nsyn[g] = n - 1


@njit(cache=True, inline="always")
def _destroy_segment(g, S, K, presyn, nsyn, seg_count, rev, rpos, bprev, bfill, tail, pool):
    base = g * K
    for k in range(np.int64(nsyn[g])):
        q = base + k
        _rx_remove(q, np.int64(presyn[q]), K, presyn, nsyn, rev, rpos, bprev, bfill, tail, pool)
    nsyn[g] = 0
    seg_count[g // S] -= 1


@njit(cache=True, inline="always")
def _adapt(g, inc, dec, prev_active_mask, p, ip, presyn, perm, nsyn, seg_count,
           rev, rpos, bprev, bfill, tail, pool, counters):
    """NuPIC _adaptSegment: +inc for synapses from previously active cells, -dec for the others."""
    S = ip[I_S]
    K = ip[I_K]
    conn = p[P_CONN]
    base = g * K
    # Descending so that destroying slot k only shifts slots already visited.
    for k in range(np.int64(nsyn[g]) - 1, -1, -1):
        q = base + k
        v = perm[q]
        if prev_active_mask[presyn[q]]:
            v = v + inc
        else:
            v = v - dec
        if v < 0:
            v = np.float32(0.0)
        elif v > 1:
            v = np.float32(1.0)
        if v < EPS:
            _destroy_synapse(g, k, K, presyn, perm, nsyn, rev, rpos, bprev, bfill, tail, pool)
            counters[C_DECAY] += 1
        else:
            # Keep the reverse-index entry's connected bit in step with the permanence (written out
            # here rather than in a helper: a call per synapse cost more than the whole loop).
            if (v >= conn) != (perm[q] >= conn):
                rev[rpos[q]] ^= 1
            perm[q] = v
    if nsyn[g] == 0:
        _destroy_segment(g, S, K, presyn, nsyn, seg_count, rev, rpos, bprev, bfill, tail, pool)
        counters[C_EMPTY] += 1


@njit(cache=True, inline="always")
def _grow(g, n_desired, prev_winner, prev_winner_mask, scratch_mask, cand, p, ip, rng,
          presyn, perm, nsyn, rev, rpos, bprev, bfill, tail, pool, counters):
    """NuPIC _growSynapses with the overrun rule of docs/design/science.md §3.5 and one draw per growth
    (§3.6)."""
    if n_desired <= 0:
        return
    K = ip[I_K]
    base = g * K
    n = np.int64(nsyn[g])
    for k in range(n):
        scratch_mask[presyn[base + k]] = True
    m = 0
    for i in range(prev_winner.size):
        c = prev_winner[i]
        if not scratch_mask[c]:
            cand[m] = c
            m += 1
    for k in range(n):
        scratch_mask[presyn[base + k]] = False
    n_actual = min(n_desired, m)
    overrun = n + n_actual - K
    while overrun > 0:
        # Lowest permanence, never a synapse from a current previous winner; ties: the oldest.
        best = -1
        best_v = np.inf
        for k in range(np.int64(nsyn[g])):
            q = base + k
            if prev_winner_mask[presyn[q]]:
                continue
            if perm[q] < best_v - EPS:
                best = k
                best_v = perm[q]
        if best == -1:
            break
        _destroy_synapse(g, best, K, presyn, perm, nsyn, rev, rpos, bprev, bfill, tail, pool)
        counters[C_OVERRUN] += 1
        overrun -= 1
    n_actual = min(n_actual, K - np.int64(nsyn[g]))
    if n_actual <= 0:
        return
    # Partial Fisher-Yates over the sorted candidates: n_actual distinct cells, seeded generator.
    for i in range(n_actual):
        j = rng.integers(i, m)
        t = cand[i]
        cand[i] = cand[j]
        cand[j] = t
    n = np.int64(nsyn[g])
    init = p[P_INIT]
    connected = init >= p[P_CONN]
    for i in range(n_actual):
        q = base + n + i
        cell = cand[i]
        presyn[q] = cell
        perm[q] = init
        _rx_add(q, cell, g, connected, rev, rpos, bprev, bfill, tail, pool)
    nsyn[g] = n + n_actual


@njit(cache=True, inline="always")
def _create_segment(cell, iteration, ip, presyn, nsyn, last_used, seg_count,
                    rev, rpos, bprev, bfill, tail, pool, counters):
    S = ip[I_S]
    K = ip[I_K]
    base = cell * S
    while seg_count[cell] >= S:
        lru = -1
        lru_t = np.iinfo(np.int64).max
        for s in range(S):
            g = base + s
            if nsyn[g] > 0 and last_used[g] < lru_t:
                lru = g
                lru_t = last_used[g]
        _destroy_segment(lru, S, K, presyn, nsyn, seg_count, rev, rpos, bprev, bfill, tail, pool)
        counters[C_EVICT] += 1
    for s in range(S):
        g = base + s
        if nsyn[g] == 0:
            last_used[g] = iteration
            seg_count[cell] += 1
            return g
    return -1  # unreachable: the loop above freed a slot


@njit(cache=True)
def activity(active_cells, learn, iteration, ip, last_used, rx, seg_act, epoch, matching):
    """activateDendrites (docs/design/science.md §3.3): active and matching segments for `active_cells`.

    `seg_act[g]` packs (epoch << 32 | connected << 16 | potential) so that one random access per
    synapse both tests "first touch in this call" and counts, and no pass is needed to clear counts.

    Returns:
        active_segs (a,), active_pot (a,), matching_segs (m,), matching_pot (m,): segment ids sorted
        ascending (so grouped by cell and column) with their counts of active potential synapses;
        n_predictive: number of distinct cells owning an active segment.
    """
    rev, _, bprev, bfill, tail, _ = rx
    S = ip[I_S]
    thr_act = ip[I_ACT]
    thr_min = ip[I_MIN]
    epoch[0] += 1
    if epoch[0] >= 2**31:  # wrap-around: forget every stamp once in 2**31 calls
        seg_act[:] = 0
        epoch[0] = 1
    stamp = epoch[0] << 32
    n_m = 0
    for i in range(active_cells.size):
        t = tail[active_cells[i]]
        while t != -1:
            start = t * B
            for pos in range(start, start + bfill[t]):
                e = rev[pos]
                g = e >> 1
                v = seg_act[g]
                if v < stamp:
                    v = stamp
                v += 1 + ((e & 1) << 16)
                seg_act[g] = v
                if (v & 0xFFFF) == thr_min:
                    matching[n_m] = g
                    n_m += 1
            t = bprev[t]
    segs = np.sort(matching[:n_m]).astype(np.int64)
    n_act = 0
    for i in range(n_m):
        if (seg_act[segs[i]] >> 16) & 0xFFFF >= thr_act:
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
        pot = v & 0xFFFF
        matching_pot[i] = pot
        if (v >> 16) & 0xFFFF >= thr_act:
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
            for t in range(m0, ims):
                g = match_segs[t]
                base = g * Kc
                n = np.int64(nsyn[g])
                dies = False
                for k in range(n):
                    q = base + k
                    if prev_active_mask[presyn[q]] and perm[q] - pdec < EPS:
                        dies = True
                        break
                if dies:
                    _adapt(g, -pdec, zero, prev_active_mask, p, ip, presyn, perm, nsyn, seg_count,
                           rev, rpos, bprev, bfill, tail, pool, counters)
                    continue
                for k in range(n):
                    q = base + k
                    if prev_active_mask[presyn[q]]:
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


@njit(cache=True)
def rebuild_index(nsyn, presyn, perm, p, K, rx):
    """Rebuild the reverse index from the canonical arrays (after a load)."""
    rev, rpos, bprev, bfill, tail, pool = rx
    tail[:] = -1
    for b in range(bprev.size):
        bprev[b] = b + 1 if b + 1 < bprev.size else -1
    bfill[:] = 0
    pool[0] = 0
    conn = p[P_CONN]
    for g in range(nsyn.size):
        base = g * K
        for k in range(np.int64(nsyn[g])):
            q = base + k
            _rx_add(q, np.int64(presyn[q]), g, perm[q] >= conn, rev, rpos, bprev, bfill, tail, pool)
