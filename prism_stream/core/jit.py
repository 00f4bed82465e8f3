"""The hot loops: small numba functions, arrays in, arrays out, no I/O.

Loaded on first use through :mod:`.kernels` (importing numba and loading
its cached machine code takes most of a second). Every integer that takes
part in hashing is uint64 and every constant is typed, because numba
promotes mixed uint64/int64 arithmetic to float64.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .constants import (_GOLDEN, _MIX1, _MIX2, COUNT_BITS, COUNT_MASK, FLOOR_NONE, NO_HEAP, OCCUPIED_SHIFT,
                        RADIX_BITS, RULE_DROP, RULE_KEEP, STATE_MARKS)

_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_RB = np.int64(RADIX_BITS)
_R1 = np.uint64(64 - RADIX_BITS)
_R2 = np.uint64(64 - 2 * RADIX_BITS)
_RMASK = np.uint64((1 << RADIX_BITS) - 1)
_U32_MAX = np.uint32(0xFFFFFFFF)


@njit(cache=True, nogil=True, inline="always")
def splitmix64(x):
    z = x + _GOLDEN
    z = (z ^ (z >> _S30)) * _MIX1
    z = (z ^ (z >> _S27)) * _MIX2
    return z ^ (z >> _S31)


@njit(cache=True, nogil=True)
def splitmix64_array(x):
    out = np.empty(x.shape[0], dtype=np.uint64)
    for i in range(x.shape[0]):
        out[i] = splitmix64(x[i])
    return out


@njit(cache=True, nogil=True)
def priorities(first_id, n, seed_mix):
    """Priority of the n consecutive ids starting at first_id (SPEC 3)."""
    out = np.empty(n, dtype=np.uint64)
    for i in range(n):
        out[i] = splitmix64((first_id + np.uint64(i)) ^ seed_mix)
    return out


@njit(cache=True, nogil=True)
def priorities_of(ids, seed_mix):
    out = np.empty(ids.shape[0], dtype=np.uint64)
    for i in range(ids.shape[0]):
        out[i] = splitmix64(ids[i] ^ seed_mix)
    return out


@njit(cache=True, nogil=True, inline="always")
def _key(rv, gv, bv, chroma, bits):
    w = 8 - bits
    if chroma:
        s = rv + gv + bv
        if s == 0:
            rv = 0
            gv = 0
            bv = 0
        else:
            rv = (2 * 255 * rv + s) // (2 * s)
            gv = (2 * 255 * gv + s) // (2 * s)
            bv = (2 * 255 * bv + s) // (2 * s)
    rv >>= bits
    gv >>= bits
    bv >>= bits
    return np.uint32((rv << (2 * w)) | (gv << w) | bv)


@njit(cache=True, nogil=True)
def bin_keys(r, g, b, shift, chroma, bits):
    """Bin key of each point from integer channels (SPEC 2).

    ``shift`` turns the stored values into 8-bit ones (0 or 8); ``chroma``
    normalizes by r+g+b with integer round-half-up before quantization.
    """
    n = r.shape[0]
    out = np.empty(n, dtype=np.uint32)
    for i in range(n):
        out[i] = _key(np.int64(r[i]) >> shift, np.int64(g[i]) >> shift, np.int64(b[i]) >> shift, chroma, bits)
    return out


@njit(cache=True, nogil=True)
def bin_keys_counted(r, g, b, shift, chroma, bits, tables):
    """bin_keys, and counts[key] += 1 for each point, in one pass (pass one's loop); a key's first count marks
    its block, marks[key >> OCCUPIED_SHIFT] = 1. ``tables`` = (counts, marks): ``marks`` a byte for each block
    of ``counts``."""
    counts, marks = tables
    n = r.shape[0]
    out = np.empty(n, dtype=np.uint32)
    for i in range(n):
        k = _key(np.int64(r[i]) >> shift, np.int64(g[i]) >> shift, np.int64(b[i]) >> shift, chroma, bits)
        out[i] = k
        c = counts[k]
        if c == 0:
            marks[k >> OCCUPIED_SHIFT] = 1
        counts[k] = c + 1
    return out


@njit(cache=True, nogil=True)
def channel_range(r, g, b):
    """(smallest, largest) value over the three channels, in one pass."""
    lo = np.int64(0)
    hi = np.int64(0)
    if r.shape[0]:
        lo = np.int64(r[0])
        hi = lo
    for i in range(r.shape[0]):
        for v in (np.int64(r[i]), np.int64(g[i]), np.int64(b[i])):
            if v < lo:
                lo = v
            if v > hi:
                hi = v
    return lo, hi


@njit(cache=True, nogil=True, inline="always")
def _push(slot, point_id, seed_mix, offsets, caps, fill, heaps):
    """Offer one point's priority to its capped bin's heap (a bin with slot < 0 keeps no heap)."""
    if slot >= 0:
        p = splitmix64(point_id ^ seed_mix)
        if fill[slot] < caps[slot] or p < heaps[offsets[slot]]:
            _offer(heaps, offsets[slot], fill, slot, caps[slot], p)


@njit(cache=True, nogil=True, inline="always")
def _kept(slot, point_id, seed_mix, cut):
    """Whether a point stays: its bin keeps all, none, or the priorities at or under its cutoff (a capped bin's
    rule is its slot + 1)."""
    if slot == RULE_KEEP:
        return True
    if slot == RULE_DROP:
        return False
    return splitmix64(point_id ^ seed_mix) <= cut[slot - 1]


@njit(cache=True, nogil=True)
def keep_mask(keys, first_id, seed_mix, rule, cut):
    """True for the points their bin keeps, for the consecutive ids first_id, first_id + 1, ..."""
    n = keys.shape[0]
    out = np.empty(n, dtype=np.bool_)
    for i in range(n):
        out[i] = _kept(rule[keys[i]], first_id + np.uint64(i), seed_mix, cut)
    return out


# ---- one read of the input: the candidate filter of pass one (core/candidates.py) ----------------------------

@njit(cache=True, nogil=True, inline="always")
def _sift_down(h, base, j, size):
    while True:
        left = 2 * j + 1
        if left >= size:
            break
        big = left
        right = left + 1
        if right < size and h[base + right] > h[base + left]:
            big = right
        if h[base + big] > h[base + j]:
            t = h[base + big]
            h[base + big] = h[base + j]
            h[base + j] = t
            j = big
        else:
            break


@njit(cache=True, nogil=True, _nrt=False)
def _offer(h, base, fill, s, c, p):
    """Bounded max-heap h[base:base+c] of a bin's smallest priorities: True iff p enters it.

    The heap first shrinks to ``c`` (a cap only ever decreases), keeping its
    smallest entries.

    A call, without reference counting (``_nrt=False``: it allocates nothing), not inlined: inlined, numba
    bound its arrays to new names at each call, a reference count up and down an array (atomic operations),
    and with :func:`_count_levels` that was 1.7% of a 100M-point LAZ run's samples (bench/PROFILE.md).
    """
    m = fill[s]
    while m > c:
        m -= 1
        h[base] = h[base + m]
        _sift_down(h, base, 0, m)
    if m < c:
        j = m
        h[base + j] = p
        while j > 0:
            parent = (j - 1) >> 1
            if h[base + parent] < h[base + j]:
                t = h[base + parent]
                h[base + parent] = h[base + j]
                h[base + j] = t
                j = parent
            else:
                break
        fill[s] = m + 1
        return True
    fill[s] = m
    if p < h[base]:
        h[base] = p
        _sift_down(h, base, 0, m)
        return True
    return False


_CB = np.int64(COUNT_BITS)
_NO_FLOOR = np.zeros(0, dtype=np.uint8)
_CM = np.int64(COUNT_MASK)


@njit(cache=True, nogil=True, inline="always")
def _slot(k, table, fill, state, slot_key):
    """The heap slot of key k, given out on first sight (``slot_key[slot] = k``); -2: no heap (every point a
    candidate); -1: pool full. Every key reaches here before its first count: its block of the table is
    marked in ``state`` (constants.OCCUPIED_SHIFT)."""
    hi = table[k] >> _CB
    if hi == 0:
        state[STATE_MARKS + (k >> OCCUPIED_SHIFT)] = 1
        if state[0] >= state[1]:
            if state[2] == 0:
                return -1
            table[k] += np.int64(NO_HEAP) << _CB
            return -2
        s = state[0]
        state[0] += 1
        table[k] += (s + 1) << _CB
        fill[s] = 0
        slot_key[s] = k
        return s
    if hi == NO_HEAP:
        return -2
    return hi - 1


@njit(cache=True, nogil=True, _nrt=False)
def _count_levels(p, s, level, lvl, cnt, tau, ccap):
    """A point of priority ``p`` below level ``level`` + 1 of slot ``s`` (the caller checked): counted at each
    level of the window it lies below, and the slot moved past every level whose count has reached ``ccap``
    (see ``candidate_scan``). Not inlined: most points never come here once a bin's levels are deep; without
    reference counting, as :func:`_offer` (the arrays one by one: a tuple of them was made at each call)."""
    window = cnt.shape[0] // lvl.shape[0]
    base = s * window
    first = level + 1
    j = 0
    while j < window and p < tau[first + j]:
        cnt[base + j] += np.uint32(1)
        j += 1
    # a count moves only here; a cap that fell since is met at the bin's next count (later is only looser)
    if np.int64(cnt[base]) >= ccap:
        d = 1
        while d < window and np.int64(cnt[base + d]) >= ccap:
            d += 1
        if level + d > tau.shape[0] - 1 - window:
            d = tau.shape[0] - 1 - window - level  # the deepest level the table holds with its window
        if d > 0:
            for j in range(window):
                cnt[base + j] = cnt[base + j + d] if j + d < window else np.uint32(0)
            lvl[s] = level + d


@njit(cache=True, nogil=True)
def candidate_scan(colors, ids, heaps, levels, caps, out, keys_in=None):
    """Pass one's loop with the candidate filter: bin key, count, and "may this point be selected?".

    The arguments come in groups (numba unpacks them at no cost): ``colors`` = (r, g, b, shift, chroma, bits);
    ``ids`` = (first_id, seed_mix, start); ``heaps`` = (table, ge, pool, fill, roots, state, slot_key);
    ``levels`` = (lvl, cnt, tau, floor); ``caps`` = (cap, target, width, cap_hi, slack, prune_k, theta,
    bin_mix); ``out`` = (keys_out, cand_out).

    ``table[key]`` packs the bin's count and heap slot (see COUNT_BITS); ``ge[m]`` (bins with at least m
    points, m < len(ge)) follows each point. Each bin's slot holds ``width`` words of ``pool``: a
    max-heap of its min(width, cap) smallest priorities, whose root ``roots[slot]`` repeats in a compact
    array (most points are ruled out there without touching the pool). ``state`` = [slots used, slots
    available, no more slots].
    Each slot also counts its points below the priority levels ``tau`` (decreasing; level l is tau[l]):
    ``lvl[slot]`` is its level, ``cnt[slot * window + j]`` the points seen below level lvl + 1 + j since that
    level entered the window. A count that reaches the cap proves the bin's cap-th smallest priority lies
    below that level, and the slot moves to it: a point at or above tau[lvl] (lvl >= 1) is no candidate,
    whatever the heap can tell (a cap above its width, a heap not yet full).
    A point is a candidate iff neither its bin's heap nor its levels rule it out; a bin with no heap slot
    keeps every point.
    With ``target`` >= 0 (T), cap is recomputed every 1024 points (64 while it is above the width):
    K_t + slack (1; the tests try 0), K_t the largest k with ge[1] + ... + ge[k] <= T, for the heaps up
    to width (width + 1 standing for anything larger) and for the levels up to len(ge) - 2, beyond which
    ``cap_hi`` (an upper bound of cap_t) stands in. With ``target`` < 0 (``--k``) both caps are ``cap``.
    ``keys_in``: the chunk's bin keys, computed beforehand (a float quantization step); else each key
    is made here from r, g, b.
    Exact mode's second rule (``prune_k`` >= 0, while K_t == prune_k): a point that enters its bin's heap
    as its (K_t+1)-th smallest, in a bin whose bin priority (``bin_mix``) is above ``theta``, is no
    candidate; ``theta`` is at least the E_t-th smallest bin priority among the bins holding more than
    K_t points (:meth:`.candidates.CandidateFilter._theta`).
    ``floor[key]`` (an empty array: none yet): a level the bin's points must lie below to be candidates, whether it has a
    slot or not (0: none; FLOOR_NONE: the bin can give no more points), as a compaction of the spill proved
    (:meth:`.candidates.CandidateFilter.tighten`).
    Returns where it stopped: len(r), or the first point whose bin needs a slot the pool lacks.
    """
    r, g, b, shift, chroma, bits = colors
    first_id, seed_mix, start = ids
    table, ge, pool, fill, roots, state, slot_key = heaps
    lvl, cnt, tau, floor = levels
    cap, target, width, cap_hi, slack, prune_k, theta, bin_mix = caps
    keys_out, cand_out = out
    n = r.shape[0]
    floors = floor.shape[0] > 0
    top = ge.shape[0] - 1
    c = cap if cap < width else width
    every = cap > width
    kt = cap - slack
    ccap = np.int64(cap) if target < 0 or kt < width else np.int64(cap_hi)
    past = False  # K_t past what ge tracks: cap_hi stands in, and a recompute can change nothing
    if keys_in is None:
        # the keys first, in a loop of their own: the main loop then reads one word a point instead of three
        # channels and the color arithmetic (13% less time on a 10M-point cloud, bench/PROFILE.md)
        for i in range(start, n):
            keys_out[i] = _key(np.int64(r[i]) >> shift, np.int64(g[i]) >> shift, np.int64(b[i]) >> shift, chroma, bits)
    for i in range(start, n):
        # every 1024 points, or every 64 while the heaps cannot rule (the warm-up: K_t falls fastest then)
        if target >= 0 and (i & (63 if every and not past else 1023)) == 0:
            total = np.int64(0)
            kfull = 0
            for k in range(1, top):
                total += ge[k]
                if total > target:
                    break
                kfull = k
            kt = kfull if kfull < width else width
            cap = kt + slack
            c = cap if cap < width else width
            every = cap > width
            past = kfull >= top - 1
            ccap = np.int64(cap_hi) if past else np.int64(kfull + slack)
        if keys_in is None:
            k = np.int64(keys_out[i])
        else:
            k = np.int64(keys_in[i])
        hi = table[k] >> _CB
        if hi != 0 and hi != NO_HEAP:
            s = hi - 1  # the common case, kept out of _slot: inlined whole, it makes the loop half as fast
        else:
            s = _slot(k, table, fill, state, slot_key)
        if s == -1:
            return i
        cand = True
        p = np.uint64(0)
        if s >= 0:
            p = splitmix64((first_id + np.uint64(i)) ^ seed_mix)
            level = np.int64(lvl[s])
            below = level == 0 or p < tau[level]  # the levels cannot rule it out
            if fill[s] == c and p >= roots[s]:
                cand = every and below
            else:
                entered = _offer(pool, s * width, fill, s, c, p)
                roots[s] = pool[s * width]
                cand = (entered or every) and below
                if cand and not every and kt == prune_k and c == kt + 1 and fill[s] == c and roots[s] == p:
                    # the (K_t+1)-th of its bin: kept only if its bin is among the E_t first by bin priority
                    if splitmix64(np.uint64(k) ^ bin_mix) > theta:
                        cand = False
            if p < tau[level + 1]:
                _count_levels(p, s, level, lvl, cnt, tau, ccap)
        if floors and cand:
            fl = np.int64(floor[k])
            if fl == FLOOR_NONE:
                cand = False
            elif fl != 0:
                if s < 0:  # a bin with no slot: its point's priority is not known yet
                    p = splitmix64((first_id + np.uint64(i)) ^ seed_mix)
                if p >= tau[fl]:
                    cand = False
        v = table[k] + 1
        table[k] = v
        m = v & _CM
        if m <= top:
            ge[m] += 1
        if keys_in is not None:  # else the key loop above wrote it
            keys_out[i] = k
        cand_out[i] = cand
    return n


@njit(cache=True, nogil=True)
def heap_evidence(pool, width, fill, base, tau, counts):
    """counts[s, w] = max(counts[s, w], entries of slot s's heap below tau[base[s] + w]) (a unit's evidence)."""
    window = counts.shape[1]
    tmp = np.zeros(window, dtype=np.int64)
    for s in range(fill.shape[0]):
        tmp[:] = 0
        b = base[s]
        for e in range(fill[s]):
            p = pool[s * width + e]
            for w in range(window):
                if p < tau[b + w]:
                    tmp[w] += 1
                else:
                    break  # tau falls with w: no deeper level holds it either
        for w in range(window):
            if tmp[w] > counts[s, w]:
                counts[s, w] = tmp[w]


@njit(cache=True, nogil=True)
def heap_refill(keys, ids, seed_mix, start, heaps, caps):
    """Offer (key, id) pairs to the bins' heaps (their rebuild from the spill index); returns where it stopped.
    ``heaps`` = (table, pool, fill, state, slot_key); ``caps`` = (cap, width)."""
    table, pool, fill, state, slot_key = heaps
    cap, width = caps
    c = cap if cap < width else width
    for i in range(start, keys.shape[0]):
        s = _slot(keys[i], table, fill, state, slot_key)
        if s == -1:
            return i
        if s >= 0:
            _offer(pool, s * width, fill, s, c, splitmix64(ids[i] ^ seed_mix))
    return keys.shape[0]


@njit(cache=True, nogil=True)
def seed_levels(keys, levels, start, table, slots, lvl):
    """Give each key a slot at least at its level (a bound another unit proved); returns where it stopped
    (the pool is full: grow it and call again). A key past the pool's budget keeps no slot and no level."""
    fill, state, slot_key = slots  # the pool's fill, its state and each slot's key
    for i in range(start, keys.shape[0]):
        s = _slot(np.int64(keys[i]), table, fill, state, slot_key)
        if s == -1:
            return i
        if s >= 0 and levels[i] > lvl[s]:
            lvl[s] = levels[i]
    return keys.shape[0]


@njit(cache=True, nogil=True)
def offer_all(first_id, n, seed_mix, heap_fill, rule, cand_out):
    """The points first_id.. offered to one heap (a file's undecided points as one bin): cand_out |= entered.

    Its cap is the one bin 0 would have if the file proved 16-bit, recomputed every ``block`` points from
    the file's ``points`` so far (:meth:`.candidates.CandidateFilter._undecided_base` says what
    ``base`` and ``n0`` are); ``fixed_cap`` >= 0 (``--k``) stands instead. A cap above the heap's length
    makes every point a candidate. One call a chunk: one a block, with the cap in numpy between calls, was
    slower under cProfile.
    """
    heap, fill = heap_fill  # the heap's words and its fill
    base, n0, points, target, fixed_cap, block, slack = rule
    words = heap.shape[0]
    w = base.shape[0] - 1
    c = 0
    every = False
    for i in range(n):
        if i % block == 0:
            if fixed_cap >= 0:
                cap = fixed_cap
            else:
                total0 = n0 + points + i
                if base[w] + min(total0, w) > target:
                    cap = 0
                    for k in range(w + 1):
                        if base[k] + min(total0, k) <= target:
                            cap = k
                    cap += slack
                elif total0 <= target - base[w]:
                    cap = words + 1  # unbounded
                else:
                    cap = target - base[w] + 1
            c = cap if cap < words else words
            every = cap > words
        p = splitmix64((first_id + np.uint64(i)) ^ seed_mix)
        if fill[0] == c and p >= heap[0]:  # the common case, tested here: through _offer it costs half again
            if every:
                cand_out[i] = True
        elif _offer(heap, 0, fill, 0, c, p) or every:
            cand_out[i] = True


@njit(cache=True, nogil=True)
def push_bottom_range(keys, ids, seed_mix, rule, lo, bottoms):
    """Feed points of explicit ids into per-bin bounded max-heaps, for the capped slots [lo, lo + len(caps))
    alone, with arrays of that group's length (no array as long as every capped slot, which can be millions).

    For every point whose bin's slot (``rule[key] - 1``, for a capped bin) is in the group, keep the ``caps[slot - lo]``
    smallest priorities seen so far in ``heaps[offsets[slot - lo]:][:caps[slot - lo]]``. Priorities of
    distinct ids are distinct (splitmix64 is a bijection), so no tie-break by id is ever needed.
    """
    caps, offsets, fill, heaps = bottoms  # the group's caps, heap offsets, fills and heap words
    hi = lo + caps.shape[0]
    for i in range(keys.shape[0]):
        slot = rule[keys[i]] - 1  # drop and keep-all are below 0
        if slot >= lo and slot < hi and caps[slot - lo] > 0:  # a cap of 0: a slot cut elsewhere (SlotRadix)
            _push(slot - lo, ids[i], seed_mix, offsets, caps, fill, heaps)


@njit(cache=True, nogil=True)
def radix_count(keys, ids, seed_mix, rule, where, prefix, tally):
    """One pass of ``cutoffs.SlotRadix`` over points of explicit ids (``R = RADIX_BITS``). ``where``: the first
    slot counted, a map from a slot's offset from it to its place (-1: not counted), and the sorted slots
    (searched when the map is empty). For each point whose bin's slot (``rule[key] - 1``) has a place ``j``,
    count its priority's top ``R`` bits in ``counts[j << R:][:2^R]`` (the first pass: ``prefix`` empty) or,
    when those bits are ``prefix[j]``, the next ``R`` bits (the second). ``tally``: the uint32 counts and a
    flag a place, set instead of a count that would pass 2^32 - 1 (the slot then keeps every point)."""
    first, place, slots = where
    counts, full = tally
    span = place.shape[0]
    n_slots = slots.shape[0]
    second = prefix.shape[0] > 0
    for i in range(keys.shape[0]):
        slot = np.int64(rule[keys[i]]) - 1
        if slot < 0:
            continue
        if span > 0:
            at = slot - first
            if at < 0 or at >= span:
                continue
            j = np.int64(place[at])
            if j < 0:
                continue
        else:
            j = np.int64(np.searchsorted(slots, slot))
            if j >= n_slots or slots[j] != slot:
                continue
        p = splitmix64(ids[i] ^ seed_mix)
        bucket = np.int64(p >> _R1)
        if second:
            if bucket != prefix[j]:
                continue
            bucket = np.int64((p >> _R2) & _RMASK)
        x = (j << _RB) + bucket
        if counts[x] == _U32_MAX:
            full[j] = 1
        else:
            counts[x] += 1


@njit(cache=True, nogil=True)
def keep_mask_ids(keys, ids, seed_mix, rule, cut):
    """keep_mask for explicit ids."""
    n = keys.shape[0]
    out = np.empty(n, dtype=np.bool_)
    for i in range(n):
        out[i] = _kept(rule[keys[i]], ids[i], seed_mix, cut)
    return out


@njit(cache=True, nogil=True)
def cell_winners(sorted_keys, by, rarity, prio, counts):
    """Runs of equal cells (``sorted_keys``: packed keys ascending, ``by``: where each came from): for each
    run, the index of its point of the smallest (rarity, priority) and the sum of its counts (``core/space``,
    SPEC 9's cell winner)."""
    n = sorted_keys.shape[0]
    win = np.empty(n, dtype=np.int64)
    sums = np.empty(n, dtype=np.int64)
    m = 0
    i = 0
    while i < n:
        best = by[i]
        best_r = rarity[best]
        best_p = prio[best]
        total = np.int64(0)
        j = i
        while j < n and sorted_keys[j] == sorted_keys[i]:
            b = by[j]
            r = rarity[b]
            p = prio[b]
            if r < best_r or (r == best_r and p < best_p):
                best, best_r, best_p = b, r, p
            total += counts[b]
            j += 1
        win[m] = best
        sums[m] = total
        m += 1
        i = j
    return win[:m], sums[:m]


@njit(inline="always")
def _next_free(other, pos, base, passed, end):
    """One side's next id for merge_walk: from position ``pos`` (its block starting at ``base``), the first
    whose place in the other order (``other``, -1: not there) the other side has not passed (``passed``),
    before position ``end``. Returns the position after it, its index in the block (-1: none before
    ``end``), and whether the block ran out first."""
    while pos < end:
        k = pos - base
        if k >= other.shape[0]:
            return pos, -1, True
        q = other[k]
        pos += 1
        if q < 0 or q >= passed:
            return pos, k, False
    return pos, -1, False


@njit(cache=True, nogil=True)
def merge_walk(s_ids, s_other, p_ids, p_other, state, out):
    """SPEC 9's merge of two orders of ids (``core/space.merge`` over one block of each, and
    ``engines/spatial_merge.py`` a block at a time): place i is spatial when share(i + 1) > share(i) and
    takes the spatial order's next id not already taken (PRISM's when none is left), else PRISM's next.
    ``s_ids`` and ``p_ids`` hold the orders' ids from positions s0 and p0, ``s_other``/``p_other`` where each
    id is in the other order (-1: not there); a side skips an id the other side has already passed, since
    that side took it. ``state``: [place, next spatial position, next PRISM position, places the
    spatial order filled, the spatial order's length, s0, p0, a, t], the first four carried from call to
    call. Writes the next places' ids to ``out`` (until it is full, the ``t`` places are done, or a block is
    used up) and returns how many, and what it needs next: 0 nothing, 1 the spatial order's next block, 2
    PRISM's."""
    place = state[0]
    i_s = state[1]
    i_p = state[2]
    filled = state[3]
    ns = state[4]
    s0 = state[5]
    p0 = state[6]
    a = state[7]
    t = state[8]
    n = 0
    need = 0
    while place < t and n < out.shape[0]:
        took = False
        if (a * (place + 1) + 500000) // 1000000 > (a * place + 500000) // 1000000:
            i_s, at, short = _next_free(s_other, i_s, s0, i_p, ns)
            if short:
                need = 1
                break
            if at >= 0:
                out[n] = s_ids[at]
                n += 1
                filled += 1
                took = True
        if not took:
            i_p, at, short = _next_free(p_other, i_p, p0, i_s, i_p + p_other.shape[0] + 1)
            if short:
                need = 2
                break
            out[n] = p_ids[at]
            n += 1
        place += 1
    state[0] = place
    state[1] = i_s
    state[2] = i_p
    state[3] = filled
    return n, need
