"""Which points of pass one may still be selected: the candidate filter of the one-read path.

The output keeps, in each bin, its q_b smallest priorities, and q_b <= K + 1
for the final K (exact mode; paper mode's k* <= K + 1; with ``--k`` q_b <= k).
With N known before the first point, T is known too. Let K_t be the largest k
with S_t(k) <= T on the counts seen so far: counts only grow, so K_t >= K,
and cap_t = K_t + 1 never increases. A point whose priority is not among the
cap_t smallest of its bin *at its arrival* can never be selected (later
points only push it further down), so only the others ("candidates") are kept
for pass two. Every bin's q_b smallest are candidates, so the cutoffs found
over the candidates alone are the exact ones.

Bookkeeping: ``ge[m]`` = bins with at least m points (m <= MAX_WIDTH + 1)
gives S_t(k) = ge[1] + ... + ge[k], enough to know K_t whenever it is at
most MAX_WIDTH. Each bin has a heap of its min(width, cap) smallest
priorities in a flat pool, slots given out as bins first appear; past the
memory budget new bins get no heap and all their points are candidates
(still exact, just more spill). The heaps start WIDTH words wide; a cloud
of few bins (a high final K) has its heaps widened once K_t has come down
within MAX_WIDTH (:meth:`CandidateFilter._fit`): with cap_t above the
width a heap cannot rule. They narrow again once K_t has fallen below half
their width, and, once every slot is in use, below WIDTH down to MIN_WIDTH
words, so that the budget (the heaps and their slots' arrays) holds a heap
for more bins: millions of bins come with a small K. Where no heap can rule (cap_t above every width the budget
allows), each slot's priority levels do: it counts its points below a
ladder of priorities 1/sqrt(2) apart and rules out the points above the
level where cap_t of them already lie (``TAU``, :meth:`CandidateFilter.cap_hi`,
``kernels.candidate_scan``; docs/DESIGN.md has the proof).

The streamed color depth (SPEC 1, ``auto``): while a file has shown no value
above 255, each of its points may yet move to key 0 (if a larger value comes
later). Outcome "stays 8-bit" is what the bins' heaps test. Outcome "16-bit"
puts all the file's points so far in one bin (key 0), under a bound computed
as if they were: a point is also a candidate if it is among the cap smallest
of the file's points so far, with that outcome's cap (the ``undecided``
heap; the merged counts give a smaller S, so a larger cap). When the switch
comes, the run refiles the counts and :meth:`CandidateFilter.rebuild` makes
the heaps again from the candidates spilled so far.
"""

from __future__ import annotations

import math

import numpy as np

from . import kernels
from .bins import BinSpec
from .histogram import Histogram
from .quotas import Options
from .sparse import mark, sparse_zeros, table_runs

POOL_BUDGET = 192 << 20  # bytes of bin heaps and their slots' arrays; past it, new bins keep every point
WIDTH = 16  # heap words per bin at the start (exact and paper modes)
MIN_WIDTH = 2  # narrowest heaps, once every slot is in use and cap_t allows (millions of bins, a small K)
MAX_WIDTH = 1024  # widest heaps (the counts track m up to it); past it only the priority levels rule
WIDEN_BYTES = 32 << 20  # heaps widen only while the bins in use fit this at the new width: at 64 MiB, pf7 100M
# (129,253 bins) widened to 64 words during the warm-up and its peak RSS rose 70 MiB above the 10M run's; with no
# bound, 1,024 words over 60,000 bins touched 480 MB (peak RSS 1,040 MiB on a 60M-point Parquet file)
MAX_K_WIDTH = 256  # --k above this: heaps of WIDTH words, which cannot rule; the priority levels do
UNDECIDED_WORDS = 1 << 22  # largest heap over an undecided file's points (32 MiB)
SLACK = 1  # cap = K_t + SLACK; the tests set 0 to show that a cap one too small loses selected points
UNDECIDED_BLOCK = 8192  # points between two updates of the undecided bound
BLOCK = 256  # points between two updates of exact mode's second-rule threshold: at least this (T + 1 for a
# smaller target: a first block of 256 points, all candidates, was alone past 2 T (1 + ln(N/T)) at T = 10),
DIV = 4  # at least the bins with a heap over DIV (an update reads each of them),
LATE = 8  # and at least the points seen so far over LATE: updates at geometric steps, O(log N) of them


# The priority levels: level l is tau[l] = floor(2^64 / sqrt(2)^l) (level 0 rules nothing out), so each level
# holds a bin's points below it with probability 1/sqrt(2) of the one above. Each slot counts its points below
# the LEVEL_WINDOW levels under its own (4 bytes each): a cap-th smallest priority is found within a factor
# sqrt(2), at a cost of one comparison a point once the levels are deep.
LEVELS = 128
TAU = np.array([min(math.isqrt(1 << (128 - level)), (1 << 64) - 1) for level in range(LEVELS)], dtype=np.uint64)
LEVEL_WINDOW = 6
UNBOUNDED = 1 << 62  # a cap no count reaches


SLOT_BYTES = 8 + 4 + 4 + 1 + 4 * LEVEL_WINDOW  # a slot's root, fill, key, level and counts below the levels


def _slots(budget: int, width: int) -> int:
    """Heap slots of ``width`` words that ``budget`` bytes hold, with their per-slot arrays."""
    return max(1, min(budget // (8 * width + SLOT_BYTES), kernels.NO_HEAP - 1))  # slot + 1 fits the table


def filter_width(options: Options) -> int:
    """Heap words per bin for these options (``--k`` k, up to MAX_K_WIDTH; past it the levels alone rule)."""
    if options.k is not None and int(options.k) <= MAX_K_WIDTH:
        return int(options.k)
    return WIDTH


class CandidateFilter:
    """Counts pass one's points into a dense histogram and says which may be selected."""

    undecided_heap = True  # False: spill nothing for points that may yet move to key 0 (a cluster unit's)

    def __init__(self, spec: BinSpec, options: Options, points: int, pool_budget: int = POOL_BUDGET):
        self.spec = spec
        self.options = options
        self.width = filter_width(options)
        self.k = None if options.k is None else int(options.k)
        self.target = None if self.k is not None else options.target(points)
        self.seed_mix = kernels.seed_mix(options.seed)
        self.chroma = spec.color_space == "chroma"
        self.bits = spec.quant_bits
        self.dense = sparse_zeros(spec.key_space, np.int64)  # count | (heap slot + 1) << 40 (kernels)
        self.ge = np.zeros(max(self.width, MAX_WIDTH) + 2, dtype=np.int64)  # ge[m], m <= len(ge) - 1
        self.pool_budget = pool_budget
        self.max_slots = _slots(pool_budget, self.width)
        # the arrays are made at the budget's size at once: np.zeros takes pages from the OS only as slots
        # are used, so a cloud of few bins holds little, and a growing pool is never copied (a copy held the
        # old pool beside the new: 384 MiB at once, the run's peak over millions of bins)
        slots = self.max_slots
        self.pool = sparse_zeros(slots * self.width, np.uint64)
        self.fill = sparse_zeros(slots, np.int32)
        self.roots = sparse_zeros(slots, np.uint64)  # pool[slot * width], compact
        self.slot_key = sparse_zeros(slots, np.uint32)  # the bin of each slot
        self.level = sparse_zeros(slots, np.uint8)  # each slot's priority level (kernels.candidate_scan)
        self.below = sparse_zeros(slots * LEVEL_WINDOW, np.uint32)  # its counts below the next levels
        self.exact = options.k is None and options.mode == "exact"  # the second rule applies
        self.bin_mix = kernels.bin_seed_mix(options.seed)
        # used, available, no more slots; then a mark a block of keys where a bin may be (constants.OCCUPIED_SHIFT)
        self.state = np.zeros(kernels.STATE_MARKS + (-(-spec.key_space >> kernels.OCCUPIED_SHIFT)), np.int64)
        self.state[1] = slots
        self.marks = self.state[kernels.STATE_MARKS:]  # the marks, a view (the kernels write them through state)
        self.undecided = None  # the current file's heap of its undecided points (as one bin)
        self.cap_trace: list[int] = []  # cap at each chunk (tests read it)
        self.widenings: list[tuple[int, int]] = []  # (points offered, new width) of each re-layout (tests)
        self.offered = 0  # points seen so far
        self.prior = None  # (keys, counts) given by count_elsewhere
        self.source_start = 0  # ``offered`` when the current source began
        self.pruning = (-1, 0)  # (K_t, theta) of the second rule's last update
        self.next_update = 0  # ``offered`` at which the next update is due
        self.floor = np.zeros(0, dtype=np.uint8)  # per key, a level its candidates lie below (:meth:`tighten`)

    # ---- the bound ------------------------------------------------------------------------------------
    def cap(self) -> int:
        """cap_t = K_t + 1 on the counts so far (or k); width + 1 stands for "more than the heaps hold"."""
        if self.k is not None:
            return self.k + SLACK - 1
        return self._k_t(self.width) + SLACK

    def cap_hi(self) -> int:
        """An upper bound of cap_t for the levels, whatever K_t is (``cap`` stops at the heaps' width).

        Exact while K_t < len(ge) - 2, the largest k the counts track. Beyond, S_t(k) for k past that is at
        least S_t(top) plus, over the bins with a slot, their points past top (``ge`` cannot see them; the
        bins with no slot are left out, which lowers S and raises the bound: still an upper bound)."""
        if self.k is not None:
            return self.k + SLACK - 1
        top = len(self.ge) - 2
        kt = self._k_t(top)
        if kt < top:
            return kt + SLACK
        used = int(self.state[0])
        counts = self.dense[self.slot_key[:used]] & kernels.COUNT_MASK
        big = counts[counts > top]
        room = self.target - int(self.ge[1:top + 1].sum())
        if int((big - top).sum()) <= room:
            return UNBOUNDED
        lo, hi = top, int(big.max())  # S_lo(lo) <= T < S_lo(hi)
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if int((np.minimum(big, mid) - top).sum()) <= room:
                lo = mid
            else:
                hi = mid
        return lo + SLACK

    def _undecided_base(self) -> np.ndarray:
        """What the undecided cap is computed from (by ``kernels.offer_all``, every UNDECIDED_BLOCK points).

        If the current file proves 16-bit, its points so far merge into key 0 with the n0 points earlier
        files put there: S(k) = base[k] + min(n0 + points, k), base[k] = S_before(k) - min(n0, k) for
        k = 0..w (w = width + 1; S_before over the earlier files' counts). The cap is K + SLACK for the
        largest k with S(k) <= T when S(w) > T; else K >= w, and S(k) = base[w] + min(total, k) beyond w,
        so K = T - base[w] (the cap then exceeds the heap: every point a candidate, if total <= K)."""
        u = self.undecided
        if u.get("base") is None or len(u["base"]) != self.width + 2:
            w = self.width + 1
            s_before = np.concatenate([[0], np.cumsum(u["ge"][1:w + 1])])
            u["base"] = s_before - np.minimum(u["n0"], np.arange(w + 1))
        return u["base"]

    def _theta(self, cap: int) -> tuple[int, int]:
        """(K_t, theta) for exact mode's second rule at ``cap`` (:meth:`cap`), or (-1, 0) when it cannot apply.

        E_t = T - S_t(K_t) bins among those holding more than K_t points get a (K_t+1)-th point at most;
        theta is the E_t-th smallest bin priority among those bins (the ones with a heap slot: a subset, so
        theta is if anything too large, which only keeps more candidates). Counts only grow, so E_t and
        this set's E_t-th smallest bin priority only fall: a point that enters as the (K_t+1)-th of a bin
        whose priority is above theta is never selected (if K ends below K_t it is too deep already).
        """
        kt = cap - SLACK
        if kt < 0 or kt >= self.width:
            return -1, 0
        e = self.target - int(self.ge[1:kt + 1].sum())
        used = int(self.state[0])
        keys = self.slot_key[:used]
        over = keys[(self.dense[keys] & kernels.COUNT_MASK) > kt]
        if e >= len(over):
            return -1, 0  # every such bin may yet get its (K_t+1)-th point
        if e <= 0:
            return kt, 0  # no bin gets one (a bin of priority 0, if any, stays: more candidates is safe)
        bp = kernels.priorities_of(over.astype(np.uint64), self.bin_mix)
        return kt, int(np.partition(bp, e - 1)[e - 1])

    def limits(self) -> tuple[np.ndarray, np.ndarray]:
        """(keys, bounds): for each bin this filter can bound, a priority with at least K + 1 of the bin's
        points at or below it, whatever the rest of the run holds (K the run's final quota).

        A heap holding at least cap = K_t + 1 >= K + 1 entries (cap within the width) bounds its bin by its
        root; a bin at level L >= 1 proved cap_t >= K + 1 points below tau[L]. Both are real points of
        this filter's, so the bound holds for the whole run: another unit may rule out any point of the bin
        above it (:meth:`count_elsewhere`)."""
        used = int(self.state[0])
        keys = self.slot_key[:used]
        bound = np.full(used, np.iinfo(np.uint64).max, dtype=np.uint64)
        lv = self.level[:used].astype(np.int64)
        deep = lv > 0
        bound[deep] = TAU[lv[deep]]
        cap = self.cap()
        if self.k is None and cap <= self.width:
            full = self.fill[:used] >= cap
            bound[full] = np.minimum(bound[full], self.roots[:used][full])
        some = bound < np.iinfo(np.uint64).max
        return keys[some].copy(), bound[some]

    def standing_rules(self, block: int = 1 << 18) -> "Standing | None":
        """Quotas that hold whatever points come later, for a compaction of the spill (None: none yet).

        Call only while every point counted has its final bin (no file's color depth undecided): counts only
        grow from here, so cap_t = K_t + 1 (``cap_hi``: exact or an upper bound; ``--k``: k) is at least every
        bin's final quota, and a spilled point outside its bin's cap_t smallest so far is never selected.
        Exact mode adds the second rule over every bin (not only those with a heap slot): of the bins holding
        more than K_t points, only the E_t = T - S_t(K_t) of smallest bin priority may get a (K_t + 1)-th,
        so the others keep K_t (see :meth:`_theta`). The spill holds each bin's cap_t smallest (every one was
        a candidate at its arrival, when the cap was larger), so the q-th smallest spilled point of a bin
        with q standing is its q-th smallest overall (``cutoffs.standing_cuts``). A cluster unit's spill may
        hold fewer (its prior's bounds rule out some of its own points); every point the sample takes from it
        is still spilled with fewer than q of the bin's spilled points below it, so the cut keeps it
        (docs/DESIGN.md, "Temporary disk, predicted": a unit compacts its own spill)."""
        cap = self.cap_hi()
        if cap >= UNBOUNDED:
            return None
        top = len(self.ge) - 2
        kt = cap - SLACK
        theta = None
        if self.exact and 0 <= kt < top:
            e = self.target - int(self.ge[1:kt + 1].sum())
            theta = self._standing_theta(kt, e, block) if e > 0 else 0
        rule = sparse_zeros(len(self.dense), np.int32)  # RULE_DROP: pages only where bins are
        if not len(self.floor):
            self.floor = sparse_zeros(len(self.dense), np.uint8)

        def standing():  # (keys, counts, standing quotas) of the bins holding points, a block at a time
            for at, c in self._bins(block):
                q = np.minimum(c, cap)
                if theta is not None:
                    over = np.flatnonzero(c > kt)
                    bp = kernels.priorities_of(at[over].astype(np.uint64), self.bin_mix)
                    q[over[bp > np.uint64(theta)]] = kt
                yield at, c, q

        # two passes over the table: the first counts the capped bins, so that their caps are one array made
        # once (a list of blocks joined at the end held them twice, and glibc kept the blocks: +120 MB over
        # 10M capped bins, the peak of a billion-point run over 2^24 keys)
        slots = sum(int(np.count_nonzero((q < c) & (q > 0))) for _, c, q in standing())
        caps = np.empty(slots, dtype=np.int32 if cap < 1 << 31 else np.int64)  # 4 bytes a bin: millions of them
        slots = 0
        for at, c, q in standing():
            rule[at[q >= c]] = kernels.RULE_KEEP
            # a bin with points and a standing quota of 0 gives no more (see tighten): said here, a block at a time
            self.floor[at[q == 0]] = kernels.FLOOR_NONE
            some = np.flatnonzero((q < c) & (q > 0))
            rule[at[some]] = slots + 1 + np.arange(len(some), dtype=np.int32)  # slot + 1, in key order
            caps[slots:slots + len(some)] = q[some]
            slots += len(some)
        return Standing(rule, caps, self.seed_mix)

    def aside(self) -> list[tuple[str, np.ndarray, int]]:
        """(attribute, array, words in use) of what a spill compaction does not read (the heaps and the slots'
        level counts): ``run.spill`` sets them aside on disk while it compacts (192 MiB at 2M slots)."""
        used = int(self.state[0])
        return [("pool", self.pool, used * self.width), ("below", self.below, used * LEVEL_WINDOW)]

    def runs(self, block: int = 1 << 20) -> list[tuple[int, int]]:
        """The ranges of the table's keys that may hold a count or a heap slot (a key outside every range
        holds 0): the blocks marked as their keys were first seen, or given counts by numpy here."""
        return table_runs(self.marks, len(self.dense), block)

    def _bins(self, block: int):
        """(keys, counts) of the bins holding points, a block of the key space at a time, in key order:
        one pass over each block of the table, and the work after it over its bins only (a cloud's bins are
        a small part of the 2^24 keys, whose full-width arithmetic cost a small run most of its time)."""
        mask = np.int64(kernels.COUNT_MASK)
        for a, b in self.runs(block):
            part = self.dense[a:b]
            at = np.flatnonzero(part != 0)  # a boolean's nonzero: 4x faster than an integer array's
            c = part[at] & mask
            held = c > 0  # the counts decide, not a heap slot's bits
            yield at[held] + a, c[held]

    def tighten(self, rules: "Standing", cut: np.ndarray, block: int = 1 << 20) -> None:
        """What a compaction proved, kept for the points to come: per bin, a level its candidates must lie
        below (``floor``, one byte a key, read by ``kernels.candidate_scan`` for every bin, with a heap slot
        or not).

        A capped bin's standing quota q (:meth:`standing_rules`) is at least its final one, and its cut is
        the q-th smallest priority of its points so far, so a point at or above the deepest level above the
        cut is never selected, whenever it comes; a bin whose standing quota is 0 gives no more points. This
        holds while counts only grow from the moment of the rules, as they do: the rules are taken only when
        every point counted has its final bin (a later file's switch to 16-bit removes only its own points,
        counted after that). Floors only deepen."""
        top = np.iinfo(np.uint64).max
        for a, b in self.runs(block):  # the bins with no more to give: standing_rules did them (over these runs)
            part = rules.rule[a:b]
            at = np.flatnonzero(part > 0)  # the capped bins: rule slot + 1
            c = cut[part[at] - 1]
            at = at + a
            seen = c < top  # a slot that showed its whole quota (else its cut keeps all)
            at, c = at[seen], c[seen]
            level = (LEVELS - 1 - np.searchsorted(TAU[::-1], c, side="right")).astype(np.uint8)
            self.floor[at] = np.maximum(self.floor[at], level)

    def _standing_theta(self, kt: int, e: int, block: int) -> int | None:
        """The e-th smallest bin priority over every bin holding more than ``kt`` points (None: there are
        at most e of them, so the second rule drops nothing): a radix select in two scans of the table,
        holding 2^16 counts and one bucket's priorities, not every bin's."""

        def over_prios():
            for at, c in self._bins(block):
                yield kernels.priorities_of(at[c > kt].astype(np.uint64), self.bin_mix)

        hist = np.zeros(1 << 16, dtype=np.int64)
        for bp in over_prios():
            hist += np.bincount((bp >> np.uint64(48)).astype(np.int64), minlength=1 << 16)
        cum = np.cumsum(hist)
        if cum[-1] <= e:
            return None
        j = int(np.searchsorted(cum, e))  # the first bucket where the count reaches e
        below = int(cum[j - 1]) if j else 0
        inside = np.concatenate([bp[(bp >> np.uint64(48)) == np.uint64(j)] for bp in over_prios()])
        return int(np.partition(inside, e - below - 1)[e - below - 1])

    def evidence(self, block: int = 1 << 18) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(keys, levels, counts): for each bin with a slot and each of ``LEVEL_WINDOW`` levels, how many of its
        points offered here are known to lie below tau[level] (a lower bound), for units elsewhere to sum
        (:func:`merge_evidence`, :meth:`count_elsewhere`).

        The window is the slot's own (the levels below its level, counted since each entered it), or, for a
        heap holding its cap smallest whose root lies deeper, the levels from its root's: there the counts
        are its entries below each level, exact. Each count is of real points of the bin below the level,
        so a sum over units that saw distinct points is a lower bound of the bin's count below it.

        Made ``block`` slots at a time (each slot's rows depend on that slot alone): the window's counts and
        levels as int64 over every slot at once took 330 MB above the filter at a 3.85M-point unit's end over
        2^24 keys (1.2M slots), the peak of its task."""
        used = int(self.state[0])
        parts = [self._evidence(a, min(used, a + block)) for a in range(0, used, block)]
        if not parts:
            return np.zeros(0, np.uint32), np.zeros(0, np.uint8), np.zeros(0, np.int64)
        return tuple(np.concatenate(column) for column in zip(*parts)) if len(parts) > 1 else parts[0]

    def _evidence(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`evidence` of slots [a, b)."""
        n = b - a
        keys = self.slot_key[a:b]
        lv = self.level[a:b].astype(np.int64)
        base = np.minimum(lv + 1, LEVELS - LEVEL_WINDOW)
        counts = self.below[a * LEVEL_WINDOW:b * LEVEL_WINDOW].reshape(n, LEVEL_WINDOW).astype(np.int64)
        counts[lv + 1 > LEVELS - LEVEL_WINDOW] = 0  # a window past the last levels: nothing to say
        fill = self.fill[a:b].astype(np.int64)
        full = fill >= min(self.width, self.cap())
        root_level = LEVELS - 1 - np.searchsorted(TAU[::-1], self.roots[a:b], side="right")
        deeper = full & (fill > 0) & (root_level > base)
        rows = np.flatnonzero(deeper)
        base[rows] = np.minimum(root_level[rows], LEVELS - LEVEL_WINDOW)
        counts[rows] = 0
        kernels.heap_evidence(self.pool[a * self.width:b * self.width], self.width, self.fill[a:b], base, TAU,
                              counts)  # the heaps' entries
        levels = base[:, None] + np.arange(LEVEL_WINDOW)
        some = counts > 0
        return (np.repeat(keys, LEVEL_WINDOW).reshape(n, LEVEL_WINDOW)[some].astype(np.uint32),
                levels[some].astype(np.uint8), counts[some].astype(np.int64))

    def count_elsewhere(self, keys: np.ndarray, counts: np.ndarray, limit_keys: np.ndarray | None = None,
                        limits: np.ndarray | None = None, evidence: tuple | None = None) -> None:
        """Before the first point: counts of points that are not offered here (a cluster's units already
        scanned), with their final bin keys. They only raise S_t, so K_t >= K still holds and the bound
        starts tighter; the heaps still hold only the points offered here, which is all the rules need
        (a point outside its bin's cap smallest here is outside them among all the bin's points).
        ``limit_keys``, ``limits``: those units' :meth:`limits` (the smallest of each bin's), as levels.
        ``evidence``: their :meth:`evidence` summed (``tasks.merge_evidence``, sorted by key and the deepest
        level first): a bin where at least cap_t of
        their points lie below tau[L] starts at level L, the deepest such (cap_t on these counts, at least
        the run's final quota)."""
        if self.offered or int(self.state[0]):
            raise AssertionError("counts from elsewhere come before the first point")
        counts = np.asarray(counts, dtype=np.int64)
        self.dense[keys] += counts  # the keys are distinct (a histogram's), and every count was 0
        mark(self.marks, keys)
        self.prior = (keys, counts)
        self._count_bins(counts)
        if evidence is not None and len(evidence[0]):
            ek, el, ec = evidence  # by key, the deepest level first (merge_evidence's order)
            proved = ec >= self.cap_hi()
            ek, el = ek[proved], el[proved].astype(np.int64)
            if len(ek):
                first = np.concatenate([[True], ek[1:] != ek[:-1]])  # each bin's deepest proved level
                # as a bound: tau[L] - 1 has the deepest level above it at L (below, as limits are turned)
                bound = TAU[el[first]] - np.uint64(1)
                lk = ek[first] if limit_keys is None else np.concatenate([limit_keys, ek[first]])
                limits = bound if limits is None else np.concatenate([np.asarray(limits, np.uint64), bound])
                limit_keys = lk
        if limit_keys is not None and len(limit_keys):
            # a bound b of another unit's (:meth:`limits`) puts its bin at the deepest level above it: at
            # least K + 1 points lie below tau[L] > b, so a point at or above tau[L] is never selected
            above = LEVELS - np.searchsorted(TAU[::-1], np.asarray(limits, dtype=np.uint64), side="right")
            level = np.minimum(above - 1, LEVELS - 1 - LEVEL_WINDOW).astype(np.uint8)
            some = level > 0
            lk = np.asarray(limit_keys, dtype=np.uint32)[some]
            lv = level[some]
            i = 0
            while i < len(lk):
                i = kernels.seed_levels(lk, lv, i, self.dense, (self.fill, self.state, self.slot_key), self.level)
                if i < len(lk):
                    self._grow()

    def _count_bins(self, counts: np.ndarray) -> None:
        """``ge`` from every bin's count: ge[m] = bins with at least m points."""
        top = len(self.ge) - 1
        at_least = np.bincount(np.minimum(counts, top), minlength=top + 1)[::-1].cumsum()[::-1]
        self.ge[1:] = at_least[1:top + 1]  # ge[0] stays 0: the kernels count m >= 1 only

    # ---- a file -----------------------------------------------------------------------------------------
    def begin_source(self) -> None:
        self.undecided = None
        self.source_start = self.offered

    @property
    def first_source(self) -> bool:
        """No point of an earlier source was offered here: every point offered so far is the current
        source's (a single-file run, a cluster's work unit), so a switch to 16-bit needs no log of their
        keys to take them out of the counts (:meth:`drop_offered`)."""
        return self.source_start == 0

    def _start_undecided(self) -> None:
        words = UNDECIDED_WORDS if self.k is None else min(self.k, UNDECIDED_WORDS)  # a cap past it: every point
        if self.target is not None:
            words = min(words, self.target + 1)
        self.undecided = {"ge": self.ge.copy(), "n0": int(self.dense[0] & kernels.COUNT_MASK), "points": 0,
                          "heap": np.zeros(max(1, words), dtype=np.uint64), "fill": np.zeros(1, np.int32)}

    def chunk(self, r, g, b, shift: int, first_id: int, undecided: bool) -> tuple[np.ndarray, np.ndarray]:
        """(keys, candidate mask) of one chunk, counted. ``undecided``: the file may still prove 16-bit. The
        channels are :meth:`.bins.ColorDepth.prepare`'s, in the loops' own types (:func:`.kernels.loop_channels`)."""
        n = len(r)
        keys = np.empty(n, dtype=np.uint32)
        cand = np.empty(n, dtype=np.bool_)
        cap = self.cap()
        self.cap_trace.append(cap)
        if undecided and self.undecided is None:
            self._start_undecided()
        target = -1 if self.target is None else self.target
        given = None if self.spec.step is None else self.spec.keys(r, g, b, shift)  # a float step's keys
        a = 0
        while a < n:
            # the second rule's threshold, updated once a block, across chunks: blocks grow with the bins in
            # use and with the points seen, so the updates cost O(bins log N), not O(bins N / BLOCK). A stale
            # threshold is only larger (more candidates, never a lost point); the kernel uses it only while
            # K_t is the one it was computed for, and a refile (rebuild) forces an update
            if self.exact and self.offered >= self.next_update:
                self.pruning = self._theta(self.cap())
                self.next_update = self.offered + max(min(BLOCK, self.target + 1), int(self.state[0]) // DIV,
                                                      self.offered // LATE)
            z = min(n, a + self.next_update - self.offered) if self.exact else n
            if self.k is None and (self.cap() > self.width or self.width > WIDTH):
                self._fit()
            elif self.k is None and self.state[2] and self.width > MIN_WIDTH:
                self._fit(MIN_WIDTH)  # every slot in use and K_t fallen: narrower heaps, for the bins left out
            prune_k, theta = self.pruning
            cap_hi = self.cap_hi()  # once a block, not again after each _grow: a stale, larger bound still holds
            i = 0
            part = slice(a, z)
            while True:
                i = kernels.candidate_scan(
                    (r[part], g[part], b[part], shift, self.chroma, self.bits),
                    (np.uint64(first_id + a), self.seed_mix, i),
                    (self.dense, self.ge, self.pool, self.fill, self.roots, self.state, self.slot_key),
                    (self.level, self.below, TAU, self.floor),
                    (self.cap(), target, self.width, cap_hi, SLACK, prune_k, np.uint64(theta), self.bin_mix),
                    (keys[part], cand[part]), None if given is None else given[part])
                if i >= z - a:
                    break
                self._grow()
            self.offered += z - a
            a = z
        if undecided:
            # the undecided bound moves with the file's points so far: the kernel recomputes it every block
            u = self.undecided
            fixed = -1 if self.k is None else self.k + SLACK - 1
            kernels.offer_all(np.uint64(first_id), n, self.seed_mix, (u["heap"], u["fill"]),
                              (self._undecided_base(), u["n0"], u["points"], -1 if self.target is None else self.target,
                               fixed, UNDECIDED_BLOCK, SLACK), cand)
            u["points"] += n
        return keys, cand

    def _k_t(self, top: int | None = None) -> int:
        """K_t, the largest k <= ``top`` with S_t(k) <= T (default: every k the counts track, len(ge) - 2)."""
        top = len(self.ge) - 2 if top is None else top
        s = np.cumsum(self.ge[1:top + 1])  # s[k-1] = S_t(k)
        within = np.flatnonzero(s <= self.target)
        return int(within[-1]) + 1 if len(within) else 0

    def _fit(self, narrowest: int = WIDTH) -> None:
        """Heaps as wide as cap_t needs: a power of two from ``narrowest`` to MAX_WIDTH, within the pool's
        budget (narrower than WIDTH only when every slot is in use: :meth:`_grow`).

        Wider (a cloud of few bins, a high K): with cap_t above the width the heaps cannot rule (only the
        priority levels, more loosely). A widened
        heap keeps its entries and fills up from the points that follow, all candidates until it holds cap
        of them. Narrower (K_t has fallen far below the width, as it does when the heaps widened during the
        warm-up, while the first points arrived): each heap keeps its smallest entries, and the budget holds
        more bins again. Rejection stays exact either way: a heap's entries are real priorities of its bin,
        so its largest, once it holds cap of them, is at least the bin's cap-th smallest; a point at or
        above it is not among the cap smallest at its arrival.
        """
        cap = self._k_t() + SLACK
        if cap > MAX_WIDTH:
            return
        width = max(narrowest, 1 << (cap - 1).bit_length())
        if width > self.width:
            if int(self.state[0]) * width * 8 > WIDEN_BYTES:
                return  # too many bins for heaps this wide: their points stay candidates (exact, more spill)
        elif 2 * width > self.width:
            return  # wide enough, and not twice too wide
        self._layout(width)

    def _layout(self, width: int, block: int = 4096) -> None:
        """The heaps laid out again ``width`` words apart (see :meth:`_fit`); the caller checked the budget."""
        used = int(self.state[0])
        max_slots = _slots(self.pool_budget, width)
        slots = max(used, max_slots)
        old = self.pool[:used * self.width].reshape(used, self.width)
        pool = sparse_zeros(slots * width, np.uint64)
        rows = pool.reshape(slots, width)
        fill = sparse_zeros(slots, np.int32)
        fill[:used] = self.fill[:used]
        if width > self.width:
            rows[:used, :self.width] = old
        else:
            top = np.uint64(np.iinfo(np.uint64).max)
            j = np.arange(width)
            for a in range(0, used, block):  # a block of heaps at a time: no copy of the whole pool
                b = min(used, a + block)
                f = fill[a:b, None]
                asc = np.sort(np.where(np.arange(self.width) < f, old[a:b], top), axis=1)[:, :width]
                keep = np.minimum(f, width)
                # each heap's smallest entries, largest first: a descending run is a max-heap
                rows[a:b] = np.take_along_axis(asc, np.where(j < keep, keep - 1 - j, j), axis=1)
                fill[a:b] = keep[:, 0]
        roots = sparse_zeros(slots, np.uint64)
        roots[:used] = rows[:used, 0]
        slot_key = sparse_zeros(slots, np.uint32)
        slot_key[:used] = self.slot_key[:used]
        self.pool, self.fill, self.roots, self.slot_key = pool, fill, roots, slot_key
        self._resize_levels(used, slots)
        self.width, self.max_slots = width, max_slots
        self.state[1] = slots
        if self.state[2] and slots > used:  # room again: the bins left without a heap may take one now
            self._readmit()
        self.pruning, self.next_update = (-1, 0), self.offered  # the second rule's K_t is another one now
        self.widenings.append((self.offered, width))

    def _readmit(self, block: int = 1 << 20) -> None:
        """The bins marked "no heap" (every point a candidate) lose the mark: each takes a slot at its next
        point, as a new bin does. Exact: a heap begun late holds real priorities of its bin, so its largest,
        once it holds cap of them, is at least the bin's cap-th smallest so far; and a slot's level counts,
        begun late too, count fewer points below each level than lie there."""
        none = np.int64(kernels.NO_HEAP) << np.int64(kernels.COUNT_BITS)
        for a, b in self.runs(block):
            part = self.dense[a:b]
            part[(part & ~np.int64(kernels.COUNT_MASK)) == none] &= np.int64(kernels.COUNT_MASK)
        self.state[2] = 0

    def _grow(self) -> None:
        """Every slot is in use: heaps narrower than they were made, if K_t allows (room for more bins), or
        else new bins keep no heap (every point of them a candidate)."""
        if self.k is None and self.width > MIN_WIDTH:
            self._fit(MIN_WIDTH)
        if int(self.state[0]) >= int(self.state[1]):
            self.state[2] = 1

    def _resize_levels(self, used: int, slots: int) -> None:
        """The slots' levels and counts, for ``slots`` slots (the first ``used`` kept)."""
        level = sparse_zeros(slots, np.uint8)
        level[:used] = self.level[:used]
        below = sparse_zeros(slots * LEVEL_WINDOW, np.uint32)
        below[:used * LEVEL_WINDOW] = self.below[:used * LEVEL_WINDOW]
        self.level, self.below = level, below

    # ---- the switch to 16-bit ---------------------------------------------------------------------------
    def drop_offered(self) -> None:
        """Remove every point offered so far from the counts (the first source's undecided points, before
        they go to key 0): what is left is the counts given by :meth:`count_elsewhere`."""
        if not self.first_source:
            raise AssertionError("points of earlier sources were offered: their counts must stay")
        self.dense &= ~np.int64(kernels.COUNT_MASK)  # the heap slots stay, for rebuild() to clear
        if self.prior is not None:
            self.dense[self.prior[0]] += self.prior[1]

    def uncount(self, keys: np.ndarray) -> None:
        """Remove points from the counts (a file's undecided points, before they go to key 0)."""
        np.subtract.at(self.dense, keys, 1)

    def rebuild(self, moved: int, index_chunks) -> None:
        """After a file proved 16-bit: ``moved`` points go to key 0; heaps made again from the spill index.

        ``index_chunks`` yields (keys, ids) of every candidate so far, the file's own already at key 0.
        Every bin's min(width, cap) smallest are candidates, so the heaps come out as if the points had
        been binned this way from the start.
        """
        self.dense[0] += moved
        mark(self.marks, [0])
        self.dense &= kernels.COUNT_MASK  # no bin has a heap now
        self.pruning, self.next_update = (-1, 0), self.offered  # bins left the set theta was taken over
        self._count_bins(self.dense)
        used = int(self.state[0])  # the slots in use (the others were never touched: zeros, not yet resident)
        self.fill[:used] = 0
        self.level[:used] = 0  # the slots go to bins anew, and the counts were of bins some points have left
        self.below[:used * LEVEL_WINDOW] = 0
        self.state[0] = 0
        self.state[2] = 0
        self.undecided = None
        cap = self.cap()
        for keys, ids in index_chunks:
            i = 0
            while True:
                i = kernels.heap_refill(keys, ids, self.seed_mix, i,
                                        (self.dense, self.pool, self.fill, self.state, self.slot_key), (cap, self.width))
                if i >= len(keys):
                    break
                self._grow()
        used = int(self.state[0])
        self.roots[:used] = self.pool[0:used * self.width:self.width]

    def counts(self, block: int = 1 << 18) -> np.ndarray:
        """The dense histogram (the heaps' slots cleared from the table: call once, at the end). Only the
        entries in use are written: ``dense &= mask`` wrote all 128 MiB, every page the OS had not yet
        mapped (most of them, for a cloud of few bins) made and zeroed."""
        mask = np.int64(kernels.COUNT_MASK)
        for a, b in self.runs(block):
            part = self.dense[a:b]
            at = np.flatnonzero(part != 0)
            part[at] &= mask
        return self.dense

    def histogram(self, prior=None) -> Histogram:
        """The bins counted (:meth:`counts`, so once, at the end), less ``prior``'s counts (a histogram
        given by :meth:`count_elsewhere`): read over :meth:`runs` alone."""
        dense = self.counts()
        if prior is not None:
            dense[prior.keys] -= prior.counts
        return Histogram.from_dense(dense, runs=self.runs())


class Standing:
    """Per-bin quotas that hold whatever comes later (:meth:`CandidateFilter.standing_rules`), in the shape
    the cutoff scan reads (:class:`.cutoffs.Rules`): ``rule`` per key (drop, keep all, or a capped slot + 1;
    the slots in key order) and ``caps``, each capped slot's quota."""

    def __init__(self, rule: np.ndarray, caps: np.ndarray, seed_mix):
        self.rule, self.caps, self.seed_mix = rule, caps, seed_mix
