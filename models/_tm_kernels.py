"""Compiled inner loops of the Temporal Memory (science.md §3.3, §3.5, §3.6).

Layout (flattened so that one integer names a segment or a synapse slot):
    segment g = cell * S + slot,            g in [0, C*S)
    synapse q = g * K + k,                  q in [0, C*S*K), k < nsyn[g] (creation order)
A per-presynaptic-cell doubly linked list over synapse slots (head/nxt/prv) is the reverse index that
makes segment activation cost proportional to the synapses of the active cells, not to all synapses.
It is fixed-capacity (one link pair per slot), rebuilt from the canonical arrays on load, and counted
in the reported bytes.

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


@njit(cache=True, inline="always")
def _link(q, cell, head, nxt, prv):
    h = head[cell]
    nxt[q] = h
    prv[q] = -1
    if h != -1:
        prv[h] = q
    head[cell] = q


@njit(cache=True, inline="always")
def _unlink(q, cell, head, nxt, prv):
    a = prv[q]
    b = nxt[q]
    if a == -1:
        head[cell] = b
    else:
        nxt[a] = b
    if b != -1:
        prv[b] = a


@njit(cache=True)
def _destroy_synapse(g, k, K, presyn, perm, nsyn, head, nxt, prv):
    """Remove synapse k of segment g; later synapses shift down so creation order is kept."""
    base = g * K
    n = np.int64(nsyn[g])
    q = base + k
    _unlink(q, presyn[q], head, nxt, prv)
    for j in range(k + 1, n):
        src = base + j
        dst = src - 1
        cell = presyn[src]
        presyn[dst] = cell
        perm[dst] = perm[src]
        # Re-point the neighbours of the moved slot at its new position.
        a = prv[src]
        b = nxt[src]
        prv[dst] = a
        nxt[dst] = b
        if a == -1:
            head[cell] = dst
        else:
            nxt[a] = dst
        if b != -1:
            prv[b] = dst
    nsyn[g] = n - 1


@njit(cache=True)
def _destroy_segment(g, S, K, presyn, nsyn, seg_count, head, nxt, prv):
    base = g * K
    for k in range(np.int64(nsyn[g])):
        q = base + k
        _unlink(q, presyn[q], head, nxt, prv)
    nsyn[g] = 0
    seg_count[g // S] -= 1


@njit(cache=True)
def _adapt(g, inc, dec, prev_active_mask, ip, presyn, perm, nsyn, seg_count, head, nxt, prv, counters):
    """NuPIC _adaptSegment: +inc for synapses from previously active cells, -dec for the others."""
    S = ip[I_S]
    K = ip[I_K]
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
            _destroy_synapse(g, k, K, presyn, perm, nsyn, head, nxt, prv)
            counters[C_DECAY] += 1
        else:
            perm[q] = v
    if nsyn[g] == 0:
        _destroy_segment(g, S, K, presyn, nsyn, seg_count, head, nxt, prv)
        counters[C_EMPTY] += 1


@njit(cache=True)
def _grow(g, n_desired, prev_winner, prev_winner_mask, scratch_mask, cand, p, ip, rng,
          presyn, perm, nsyn, head, nxt, prv, counters):
    """NuPIC _growSynapses with the overrun rule of science.md §3.5 and one draw per growth (§3.6)."""
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
        _destroy_synapse(g, best, K, presyn, perm, nsyn, head, nxt, prv)
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
    for i in range(n_actual):
        q = base + n + i
        cell = cand[i]
        presyn[q] = cell
        perm[q] = init
        _link(q, cell, head, nxt, prv)
    nsyn[g] = n + n_actual


@njit(cache=True)
def _create_segment(cell, iteration, ip, presyn, nsyn, last_used, seg_count, head, nxt, prv, counters):
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
        _destroy_segment(lru, S, K, presyn, nsyn, seg_count, head, nxt, prv)
        counters[C_EVICT] += 1
    for s in range(S):
        g = base + s
        if nsyn[g] == 0:
            last_used[g] = iteration
            seg_count[cell] += 1
            return g
    return -1  # unreachable: the loop above freed a slot


@njit(cache=True)
def activity(active_cells, learn, iteration, p, ip, presyn, perm, nsyn, last_used, head, nxt,
             cnt_conn, cnt_pot, touched):
    """activateDendrites (science.md §3.3): active and matching segments for `active_cells`.

    Returns:
        active_segs (a,), active_pot (a,), matching_segs (m,), matching_pot (m,): segment ids sorted
        ascending (so grouped by cell and column) with their counts of active potential synapses;
        n_predictive: number of distinct cells owning an active segment.
    """
    K = ip[I_K]
    S = ip[I_S]
    conn = p[P_CONN]
    thr_act = ip[I_ACT]
    thr_min = ip[I_MIN]
    # Segments reaching minThreshold are collected as they cross it, so only those are sorted; every
    # touched segment is remembered (from the end of `touched`) to zero its counters afterwards.
    n_m = 0
    n_t = 0
    last = touched.size - 1
    for i in range(active_cells.size):
        q = head[active_cells[i]]
        while q != -1:
            g = q // K
            c = cnt_pot[g]
            if c == 0:
                touched[last - n_t] = g
                n_t += 1
            c += 1
            cnt_pot[g] = c
            if c == thr_min:
                touched[n_m] = g
                n_m += 1
            if perm[q] >= conn:
                cnt_conn[g] += 1
            q = nxt[q]
    segs = np.sort(touched[:n_m]).astype(np.int64)
    n_act = 0
    for i in range(n_m):
        if cnt_conn[segs[i]] >= thr_act:
            n_act += 1
    active_segs = np.empty(n_act, np.int64)
    active_pot = np.empty(n_act, np.int32)
    matching_pot = np.empty(n_m, np.int32)
    a = 0
    n_predictive = 0
    last_cell = -1
    for i in range(n_m):
        g = segs[i]
        matching_pot[i] = cnt_pot[g]
        if cnt_conn[g] >= thr_act:
            active_segs[a] = g
            active_pot[a] = cnt_pot[g]
            a += 1
            if learn:
                last_used[g] = iteration
            if g // S != last_cell:
                last_cell = g // S
                n_predictive += 1
    for i in range(n_t):
        g = touched[last - i]
        cnt_pot[g] = 0
        cnt_conn[g] = 0
    return active_segs, active_pot, segs, matching_pot, n_predictive


@njit(cache=True)
def step(columns, learn, prev_active, prev_winner, act_segs, act_pot, match_segs, match_pot,
         iteration, p, ip, rng, presyn, perm, nsyn, last_used, seg_count, head, nxt, prv,
         prev_active_mask, prev_winner_mask, scratch_mask, cand, counters):
    """activateCells (science.md §3.3) for sorted `columns`, learning when `learn`.

    Returns:
        active_cells, winner_cells (sorted int64), n_predicted_columns, n_bursting_columns,
        changed (whether the connections were modified).
    """
    cpc = ip[I_CPC]
    S = ip[I_S]
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
                    _adapt(g, inc, dec, prev_active_mask, ip, presyn, perm, nsyn, seg_count,
                           head, nxt, prv, counters)
                    if nsyn[g] > 0:
                        _grow(g, max_new - act_pot[t], prev_winner, prev_winner_mask, scratch_mask, cand,
                              p, ip, rng, presyn, perm, nsyn, head, nxt, prv, counters)
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
                    _adapt(g, inc, dec, prev_active_mask, ip, presyn, perm, nsyn, seg_count,
                           head, nxt, prv, counters)
                    if nsyn[g] > 0:
                        _grow(g, max_new - match_pot[best], prev_winner, prev_winner_mask, scratch_mask,
                              cand, p, ip, rng, presyn, perm, nsyn, head, nxt, prv, counters)
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
                # A localisation step draws nothing (science.md §3.6): lowest cell among the ties.
                winner = cand[rng.integers(0, n_ties)] if learn else cand[0]
                if learn and n_prev_winner > 0:
                    changed = True
                    g = _create_segment(winner, iteration, ip, presyn, nsyn, last_used, seg_count,
                                        head, nxt, prv, counters)
                    _grow(g, min(max_new, n_prev_winner), prev_winner, prev_winner_mask, scratch_mask,
                          cand, p, ip, rng, presyn, perm, nsyn, head, nxt, prv, counters)
            winners[n_w] = winner
            n_w += 1
        elif learn and pdec > 0:
            # Matching segments of a column that stayed silent predicted wrongly: punish them.
            for t in range(m0, ims):
                changed = True
                _adapt(match_segs[t], -pdec, zero, prev_active_mask, ip, presyn, perm, nsyn, seg_count,
                       head, nxt, prv, counters)

    for i in range(prev_active.size):
        prev_active_mask[prev_active[i]] = False
    for i in range(prev_winner.size):
        prev_winner_mask[prev_winner[i]] = False
    return active[:n_a].copy(), winners[:n_w].copy(), n_pred, n_burst, changed


@njit(cache=True)
def rebuild_links(nsyn, presyn, K, head, nxt, prv):
    """Rebuild the reverse index from the canonical arrays (after a load)."""
    head[:] = -1
    for g in range(nsyn.size):
        base = g * K
        for k in range(np.int64(nsyn[g])):
            q = base + k
            _link(q, presyn[q], head, nxt, prv)
