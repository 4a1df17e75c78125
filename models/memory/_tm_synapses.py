"""Synapse storage of the Temporal Memory, compiled (docs/design/science.md §3.3, §3.5, §3.6): the flat
arrays, the reverse index and the primitives that change them (adapt, grow, create and destroy),
inlined into the kernels of `_tm_kernels`.

Layout (flattened so that one integer names a segment or a synapse slot):
    segment g = cell * S + slot,            g in [0, C*S)
    synapse q = g * K + k,                  q in [0, C*S*K), k < nsyn[g] (creation order)
The reverse index `rx` makes segment activation cost proportional to the synapses of the active cells
rather than to all synapses, and reads memory contiguously: each presynaptic cell owns a chain of
blocks of B entries, each entry `((g << kb | k) << 1) | connected` for synapse k of segment g from that
cell (kb = `slot_bits(K)`, so g = entry >> (kb + 1); the connected bit is kept in step with the
permanence, so activation never touches the permanence array). `rpos[q]` is the entry of synapse q, for
O(1) removal: the cell's last entry fills the hole, and because entries name their synapse slot, its
`rpos` is fixed up directly (issue 25: finding the moved synapse by scanning its segment's presynaptic
cells was most of the index upkeep, 1.84 ms of the service preset's 4.38 ms step); the price is that a
synapse that shifts within its segment (decay, overrun compaction) rewrites its entry. All blocks come
from one pool sized ceil(C*S*K / B) + C, enough because only a cell's last block can be partly filled;
the index is fixed-capacity, rebuilt from the canonical arrays on load, and counted in the reported bytes.
Block size: walking a cell's chain is a dependent pointer chase with a cache miss per block, and it,
not the per-segment counters, dominated activation (issue 25: 490 entries per cell, 16 per block,
0.73 ms for 160 active cells; 128 per block, 0.12 ms). Entries beyond a cell's fill cost at most
C * B * 4 bytes, about what the 8x fewer block headers save at 2048x4. The entries' order within the
index never changes a result (counts are sums, segment lists are sorted).
`rx` = (rev, rpos, bprev, bfill, tail, pool) with pool[0] the head of the free-block list.

`p` (float32): initialPermanence, connectedPermanence - EPS, permanenceIncrement,
permanenceDecrement, predictedSegmentDecrement.
`ip` (int64): cellsPerColumn, maxSegmentsPerCell, maxSynapsesPerSegment, activationThreshold,
minThreshold, maxNewSynapseCount, slot_bits(maxSynapsesPerSegment).
`counters` (int64): 0 segments evicted (LRU), 1 synapses destroyed by overrun, 2 synapses destroyed by
decay, 3 segments destroyed empty.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# NuPIC's EPSILON: permanences below it are destroyed; the connected test is perm >= connected - EPS.
EPS = 1e-5

P_INIT, P_CONN, P_INC, P_DEC, P_PDEC = 0, 1, 2, 3, 4
I_CPC, I_S, I_K, I_ACT, I_MIN, I_NEW, I_KB = 0, 1, 2, 3, 4, 5, 6
C_EVICT, C_OVERRUN, C_DECAY, C_EMPTY = 0, 1, 2, 3


B = 128  # entries per reverse-index block (8 cache lines of int32; why so many: see the module docstring)

# The small helpers are inlined: a call that passes arrays costs reference-count updates per array,
# which dominated adapt (about 100 ns per synapse) before.


def pool_blocks(n_slot: int, n_cells: int) -> int:
    """Blocks the reverse index needs at most (see module docstring)."""
    return -(-n_slot // B) + n_cells


@njit(cache=True)
def slot_bits(K):
    """Bits of a synapse's slot k < K in a reverse-index entry (see module docstring)."""
    kb = 1
    while (1 << kb) < K:
        kb += 1
    return kb


@njit(cache=True, inline="always")
def _entry(g, k, kb, connected):
    return (((g << kb) | k) << 1) | (1 if connected else 0)


@njit(cache=True, inline="always")
def _rx_add(q, cell, e, rev, rpos, bprev, bfill, tail, pool):
    t = tail[cell]
    if t == -1 or bfill[t] == B:
        b = pool[0]
        pool[0] = bprev[b]
        bprev[b] = t
        bfill[b] = 0
        tail[cell] = b
        t = b
    pos = t * B + bfill[t]
    rev[pos] = e
    rpos[q] = pos
    bfill[t] += 1


@njit(cache=True, inline="always")
def _rx_remove(q, cell, K, kb, rev, rpos, bprev, bfill, tail, pool):
    """Drop synapse q (from `cell`) from the index; the cell's last entry fills the hole."""
    pos = rpos[q]
    t = tail[cell]
    last = t * B + bfill[t] - 1
    if pos != last:
        moved = np.int64(rev[last])
        rev[pos] = moved
        # The moved entry names its synapse: segment and slot.
        rpos[(moved >> (kb + 1)) * K + ((moved >> 1) & ((1 << kb) - 1))] = pos
    bfill[t] -= 1
    if bfill[t] == 0:
        tail[cell] = bprev[t]
        bprev[t] = pool[0]
        pool[0] = t


@njit(cache=True, inline="always")
def _destroy_synapse(g, k, K, kb, presyn, perm, nsyn, rev, rpos, bprev, bfill, tail, pool):
    """Remove synapse k of segment g; later synapses shift down so creation order is kept."""
    base = g * K
    n = np.int64(nsyn[g])
    q = base + k
    _rx_remove(q, np.int64(presyn[q]), K, kb, rev, rpos, bprev, bfill, tail, pool)
    for j in range(k + 1, n):
        src = base + j
        presyn[src - 1] = presyn[src]
        perm[src - 1] = perm[src]
        rpos[src - 1] = rpos[src]
        rev[rpos[src]] -= 2  # its entry names slot j - 1 now
    nsyn[g] = n - 1


@njit(cache=True, inline="always")
def _destroy_segment(g, S, K, kb, presyn, nsyn, seg_count, rev, rpos, bprev, bfill, tail, pool):
    base = g * K
    for k in range(np.int64(nsyn[g])):
        q = base + k
        _rx_remove(q, np.int64(presyn[q]), K, kb, rev, rpos, bprev, bfill, tail, pool)
    nsyn[g] = 0
    seg_count[g // S] -= 1


@njit(cache=True, inline="always")
def _adapt(g, inc, dec, prev_active_mask, p, ip, presyn, perm, nsyn, seg_count,
           rev, rpos, bprev, bfill, tail, pool, counters):
    """NuPIC _adaptSegment: +inc for synapses from previously active cells, -dec for the others."""
    S = ip[I_S]
    K = ip[I_K]
    kb = ip[I_KB]
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
            _destroy_synapse(g, k, K, kb, presyn, perm, nsyn, rev, rpos, bprev, bfill, tail, pool)
            counters[C_DECAY] += 1
        else:
            # Keep the reverse-index entry's connected bit in step with the permanence (written out
            # here rather than in a helper: a call per synapse cost more than the whole loop).
            if (v >= conn) != (perm[q] >= conn):
                rev[rpos[q]] ^= 1
            perm[q] = v
    if nsyn[g] == 0:
        _destroy_segment(g, S, K, kb, presyn, nsyn, seg_count, rev, rpos, bprev, bfill, tail, pool)
        counters[C_EMPTY] += 1


@njit(cache=True, inline="always")
def _grow(g, n_desired, prev_winner, prev_winner_mask, scratch_mask, cand, p, ip, rng,
          presyn, perm, nsyn, rev, rpos, bprev, bfill, tail, pool, counters):
    """NuPIC _growSynapses with the overrun rule of docs/design/science.md §3.5 and one draw per growth
    (§3.6)."""
    if n_desired <= 0:
        return
    K = ip[I_K]
    kb = ip[I_KB]
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
    destroyed = 0
    while overrun > 0:
        # Lowest permanence, never a synapse from a current previous winner; ties: the oldest.
        # A victim leaves the index at once but keeps its slot, marked by an infinite permanence
        # that no later scan picks; the survivors close ranks in one pass below, in creation order.
        # Same victims, same order, same final arrays as destroying each at once (one shift per
        # victim was most of the cost when the caps bind, issue 25).
        best = -1
        best_v = np.inf
        for k in range(n):
            q = base + k
            if prev_winner_mask[presyn[q]]:
                continue
            if perm[q] < best_v - EPS:
                best = k
                best_v = perm[q]
        if best == -1:
            break
        q = base + best
        _rx_remove(q, np.int64(presyn[q]), K, kb, rev, rpos, bprev, bfill, tail, pool)
        perm[q] = np.inf
        destroyed += 1
        counters[C_OVERRUN] += 1
        overrun -= 1
    if destroyed:
        j = base
        for q in range(base, base + n):
            if perm[q] != np.inf:
                if j != q:
                    presyn[j] = presyn[q]
                    perm[j] = perm[q]
                    rpos[j] = rpos[q]
                    rev[rpos[q]] -= (q - j) << 1  # its entry names slot j now
                j += 1
        nsyn[g] = j - base
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
        _rx_add(q, cell, _entry(g, n + i, kb, connected), rev, rpos, bprev, bfill, tail, pool)
    nsyn[g] = n + n_actual


@njit(cache=True, inline="always")
def _create_segment(cell, iteration, ip, presyn, nsyn, last_used, seg_count,
                    rev, rpos, bprev, bfill, tail, pool, counters):
    S = ip[I_S]
    K = ip[I_K]
    kb = ip[I_KB]
    base = cell * S
    while seg_count[cell] >= S:
        lru = -1
        lru_t = np.iinfo(np.int64).max
        for s in range(S):
            g = base + s
            if nsyn[g] > 0 and last_used[g] < lru_t:
                lru = g
                lru_t = last_used[g]
        _destroy_segment(lru, S, K, kb, presyn, nsyn, seg_count, rev, rpos, bprev, bfill, tail, pool)
        counters[C_EVICT] += 1
    for s in range(S):
        g = base + s
        if nsyn[g] == 0:
            last_used[g] = iteration
            seg_count[cell] += 1
            return g
    return -1  # unreachable: the loop above freed a slot


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
    kb = slot_bits(K)
    for g in range(nsyn.size):
        base = g * K
        for k in range(np.int64(nsyn[g])):
            q = base + k
            _rx_add(q, np.int64(presyn[q]), _entry(g, k, kb, perm[q] >= conn), rev, rpos, bprev, bfill, tail,
                    pool)
