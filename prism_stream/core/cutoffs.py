"""Per-bin priority cutoffs: what makes pass two exact and order-independent.

A bin keeps its q_b points of smallest priority (SPEC 5). For a bin that
keeps some but not all of its points ("capped"), the cutoff is its q_b-th
smallest priority; pass two then keeps a point iff its priority is at or
under its bin's cutoff, whatever order the points arrive in. Priorities of
distinct ids never tie (splitmix64 is a bijection on 64-bit words), so the
cutoff alone decides.

Memory: one bounded heap per capped bin, q_b words each, T words at most.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kernels, keyblocks
from .constants import RADIX_BITS
from .quotas import Plan
from .sparse import sparse_zeros


@dataclass(frozen=True)
class Cutoffs:
    """The q_b-th smallest priority of each capped bin."""

    keys: np.ndarray  # uint32, the capped bins, sorted
    cut: np.ndarray  # uint64


RULES_BLOCK = 1 << 20  # bins a step while the rules are made


def _whole_keys(plan: Plan):
    """The keys of the bins ``plan`` keeps whole, a block at a time: no temporary of a bin's size beside the plan."""
    for a in range(0, plan.bins, RULES_BLOCK):
        keys, counts, quotas = (x[a:a + RULES_BLOCK] for x in (plan.keys, plan.counts, plan.quotas))
        yield keys[(quotas == counts) & (counts > 0)]


class Rules:
    """Dense per-key lookups built from a plan: drop, keep all, or compare to a slot's cutoff."""

    def __init__(self, plan: Plan):
        capped = plan.capped
        capped_keys = plan.keys[capped]
        caps = plan.quotas[capped].astype(np.int64, copy=False)
        del capped
        self._make(plan.spec.key_space, plan.seed, _whole_keys(plan), capped_keys, caps)

    @classmethod
    def of_parts(cls, key_space: int, seed: int, whole_keys: np.ndarray, capped_keys: np.ndarray,
                 caps: np.ndarray) -> "Rules":
        """The rules of a plan from its :meth:`parts` (what a cluster's workers are sent instead of the plan):
        the same tables, the arrays given kept as they are."""
        rules = cls.__new__(cls)
        rules._make(key_space, seed, [whole_keys], np.asarray(capped_keys, np.uint32), np.asarray(caps, np.int64))
        return rules

    def _make(self, key_space: int, seed: int, whole_blocks, capped_keys: np.ndarray, caps: np.ndarray) -> None:
        self.seed_mix = kernels.seed_mix(seed)
        self.capped_keys, self.caps = capped_keys, caps
        rule = sparse_zeros(key_space, np.int32)  # RULE_DROP: pages only where bins are
        for keys in whole_blocks:
            rule[keys] = kernels.RULE_KEEP
        for a in range(0, len(capped_keys), RULES_BLOCK):
            keys = capped_keys[a:a + RULES_BLOCK]
            rule[keys] = np.arange(a + 1, a + len(keys) + 1, dtype=np.int32)  # slot + 1
        self.rule = rule

    def parts(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(the keys of the bins kept whole, the capped bins' keys, their caps): what :meth:`of_parts` makes the
        same rules of, 4 bytes a whole bin and 12 a capped one."""
        whole = [np.flatnonzero(self.rule[a:a + RULES_BLOCK] == kernels.RULE_KEEP).astype(np.uint32) + np.uint32(a)
                 for a in range(0, len(self.rule), RULES_BLOCK)]
        return np.concatenate(whole or [np.zeros(0, np.uint32)]), self.capped_keys, self.caps

    def drop_caps(self) -> None:
        """Once the cutoffs are found: pass two reads the rule table and the cuts alone, so the caps (8 bytes
        a capped bin) go before the output's writer needs room."""
        self.caps = None


CUTOFF_WORDS = 1 << 24  # heap words held at once (128 MiB): a larger sample takes a scan a group of bins


class CutoffFinder:
    """Streams (keys, first id) runs and keeps each capped bin's q_b smallest priorities.

    ``lo``, ``hi``: only the capped bins of slots [lo, hi) keep a heap (a group of bins whose quotas fit
    the memory at hand, :func:`cutoffs_by_groups`), in arrays of the group's length: the caps are a view of
    the rules' own (or ``caps``: a compaction's, widened to int64), the offsets and fill 16 bytes a slot of the
    group. Over 8.4M capped bins the finder
    held 24 bytes for every capped slot beside the rules' caps, 200 MB at the run's peak.
    """

    def __init__(self, rules: Rules, lo: int = 0, hi: int | None = None, caps: np.ndarray | None = None):
        self.rules = rules
        self.lo, self.hi = lo, len(rules.caps) if hi is None else hi
        self.caps = rules.caps[self.lo:self.hi] if caps is None else caps  # int64 (the kernel's type)
        self.offsets = np.empty(len(self.caps), dtype=np.int64)
        if len(self.caps):
            self.offsets[0] = 0
            np.cumsum(self.caps[:-1], out=self.offsets[1:])
        self.fill = np.zeros(len(self.caps), dtype=np.int64)
        self.heaps = np.zeros(int(self.caps.sum()), dtype=np.uint64)

    def add(self, keys: np.ndarray, first_id: int) -> None:
        self.add_ids(keys, np.arange(first_id, first_id + len(keys), dtype=np.uint64))

    def add_ids(self, keys: np.ndarray, ids: np.ndarray) -> None:
        """Like :meth:`add`, for points with explicit ids (a spill index)."""
        r = self.rules
        keys, ids = kernels.read_only(keys, np.uint32), kernels.read_only(ids, np.uint64)  # one compiled type
        kernels.push_bottom_range(keys, ids, r.seed_mix, r.rule, np.int64(self.lo),
                                  (self.caps, self.offsets, self.fill, self.heaps))

    def bottoms(self) -> tuple[np.ndarray, np.ndarray]:
        """Each capped bin's retained priorities: (slot per entry, priority), for merging."""
        slots = self.lo + np.repeat(np.arange(len(self.fill)), self.fill)
        idx = [np.arange(o, o + f) for o, f in zip(self.offsets, self.fill) if f]
        return slots, self.heaps[np.concatenate(idx) if idx else np.zeros(0, np.int64)]

    def cuts(self, out: np.ndarray | None = None) -> np.ndarray:
        """The cutoffs of slots [lo, hi): each heap's root, the largest of its q_b smallest (into ``out``)."""
        if np.any(self.fill != self.caps):
            raise AssertionError("cutoff scan saw fewer points than the histogram counted")
        return np.take(self.heaps, self.offsets, out=out, mode="clip")  # "raise" buffers all of out first

    def result(self) -> Cutoffs:
        if (self.lo, self.hi) != (0, len(self.rules.caps)):
            raise ValueError("a group's finder holds part of the cutoffs: use cuts()")
        return Cutoffs(self.rules.capped_keys, self.cuts())


class PriorityCounter:
    """One bin's priorities in [lo, lo + 2^bits), counted in 2^16 buckets (or, once they are few, kept):
    a pass of the radix select of a bin whose quota is too large for the heaps' memory."""

    BUCKET_BITS = 16

    def __init__(self, rules: Rules, key: int, lo: int, bits: int, keep: bool):
        self.rules, self.key, self.lo, self.bits, self.keep = rules, np.uint32(key), lo, bits, keep
        self.counts = np.zeros(1 << self.BUCKET_BITS, dtype=np.int64)
        self.kept: list = []

    def add(self, keys: np.ndarray, first_id: int) -> None:
        at = np.flatnonzero(keys == self.key).astype(np.uint64)
        self._count(kernels.priorities_of_np(np.uint64(first_id) + at, self.rules.seed_mix))

    def add_ids(self, keys: np.ndarray, ids: np.ndarray) -> None:
        self._count(kernels.priorities_of_np(ids[keys == self.key], self.rules.seed_mix))

    def _count(self, prios: np.ndarray) -> None:
        if self.bits < 64:
            prios = prios[(prios >= np.uint64(self.lo)) & ((prios - np.uint64(self.lo)) >> np.uint64(self.bits) == 0)]
        if self.keep:
            self.kept.append(prios)
        else:
            shift = np.uint64(self.bits - self.BUCKET_BITS)
            self.counts += np.bincount(((prios - np.uint64(self.lo)) >> shift).astype(np.int64),
                                       minlength=len(self.counts))


def radix_cut(rules: Rules, slot: int, feed, words: int = CUTOFF_WORDS) -> int:
    """The q-th smallest priority of one capped bin, holding at most ``words`` of them: each pass of
    ``feed`` counts the bin's priorities within the range known to hold it in 2^16 buckets and narrows
    the range to one bucket, until the range holds few enough to keep and select from."""
    key, q = int(rules.capped_keys[slot]), int(rules.caps[slot])
    lo, bits, below, inside = 0, 64, 0, None
    while True:
        if inside is not None and inside <= words:
            counter = PriorityCounter(rules, key, lo, bits, keep=True)
            feed(counter)
            prios = np.concatenate(counter.kept) if counter.kept else np.zeros(0, np.uint64)
            if len(prios) != inside or not 0 < q - below <= len(prios):
                raise AssertionError("cutoff scan saw other points than the histogram counted")
            return int(np.partition(prios, q - below - 1)[q - below - 1])
        counter = PriorityCounter(rules, key, lo, bits, keep=False)
        feed(counter)
        cum = np.cumsum(counter.counts)
        j = int(np.searchsorted(cum, q - below))  # the first bucket where the count reaches q
        if j >= len(cum):
            raise AssertionError("cutoff scan saw fewer points than the histogram counted")
        below += int(cum[j - 1]) if j else 0
        bits -= PriorityCounter.BUCKET_BITS
        lo += j << bits
        inside = int(counter.counts[j])


FINDER_SLOT_WORDS = 2  # a finder's words a slot beside its heap: its offset and fill (int64)


def slot_groups(caps: np.ndarray, words: int, per_slot: int = 0) -> list[tuple[int, int]]:
    """Consecutive slot ranges whose quotas, plus ``per_slot`` a slot, sum to at most ``words`` (a bin past
    it alone): the plain loop :func:`quota_groups` is held to."""
    groups, lo, total = [], 0, 0
    for i, c in enumerate(caps.tolist()):
        c += per_slot
        if total + c > words and i > lo:
            groups.append((lo, i))
            lo, total = i, 0
        total += c
    if lo < len(caps):
        groups.append((lo, len(caps)))
    return groups


def cutoffs_by_groups(rules: Rules, feed, words: int = CUTOFF_WORDS) -> Cutoffs:
    """The cutoffs with at most about ``words`` words held at once (8 bytes each: a heap's, and a slot's
    offset and fill), whatever T and the number of capped bins are.

    ``feed(finder)`` gives every point to ``finder.add`` (consecutive ids) or ``finder.add_ids``, and is
    called once for each group of bins whose quotas fit ``words`` (once, for a sample that fits), and a few
    times more for a bin whose quota alone does not (:func:`radix_cut`).
    """
    cut = np.zeros(len(rules.caps), dtype=np.uint64)
    for lo, hi in quota_groups(rules.caps, words, per_slot=FINDER_SLOT_WORDS):
        if hi - lo == 1 and rules.caps[lo] > words:
            cut[lo] = radix_cut(rules, lo, feed, words)
            continue
        finder = CutoffFinder(rules, lo, hi)
        feed(finder)
        finder.cuts(out=cut[lo:hi])
        del finder  # before the next group's arrays
    return Cutoffs(rules.capped_keys, cut)  # the rules' own keys, not a copy: 4 bytes a capped bin


STANDING_WORDS = 1 << 22  # words a spill compaction's finder holds at once (32 MiB: heaps, and per slot its cap,
# offset and fill), beside pass one's own memory
EXACT_PASSES = 2  # a compaction's exact heaps take at most this many passes over the spill's index; past it the
# wide slots (quota over RADIX_MIN_CAP) are counted instead (SlotRadix: two passes for up to STANDING_WORDS / 64
# slots). 10^10 points sorted by color, 10,000 bins at 0.05: quotas of about 50,000 over thousands of slots made
# about 60 groups, a pass over a 36 GB index each (30 of them took 25 minutes; bench/RESULTS_SCALE.md)
RADIX_MIN_CAP = 512  # a quota past which counting (128 words a slot, two passes) is cheaper than a heap


def quota_groups(caps: np.ndarray, words: int, block: int = 1 << 20, per_slot: int = 0) -> list[tuple[int, int]]:
    """:func:`slot_groups` without a Python loop over the slots (millions of capped bins: a list of them
    took 8 bytes a bin, and more for caps past 256), and without a running sum as long as the slots:
    ``block`` of them at a time."""
    edges, n, used = [0], len(caps), 0  # used: words of the open group before the block
    for a in range(0, n, block):
        cum = np.cumsum(caps[a:a + block], dtype=np.int64) + used
        if per_slot:
            cum += per_slot * np.arange(1, len(cum) + 1, dtype=np.int64)
        while True:
            j = int(np.searchsorted(cum, words, side="right"))  # the first slot past ``words``
            if j >= len(cum):
                used = int(cum[-1])
                break
            g = a + j if a + j > edges[-1] else a + j + 1  # a slot past ``words`` alone is a group
            edges.append(g)
            if g - a >= len(cum):
                used = 0
                break
            cum = cum - (int(cum[g - a - 1]) if g > a else used)
    if edges[-1] < n:
        edges.append(n)
    return list(zip(edges[:-1], edges[1:]))


def counted_slots(caps: np.ndarray, words: int = STANDING_WORDS) -> tuple[np.ndarray, np.ndarray, list]:
    """The capped slots a compaction counts (:class:`SlotRadix`) instead of holding in heaps: those with quotas
    over ``RADIX_MIN_CAP``, when heaps for every slot would take more than ``EXACT_PASSES`` passes over the index
    and counting them takes fewer passes in all (a few wide slots among many narrow ones would only add two).
    Returns (those slots, the quotas held in heaps: 0 for a counted slot, the heaps' groups of slots)."""
    groups = quota_groups(caps, words, per_slot=FINDER_SLOT_WORDS + 1)
    wide = np.flatnonzero(caps > RADIX_MIN_CAP)
    if len(groups) <= EXACT_PASSES or not len(wide):
        return wide[:0], caps, groups
    held = caps.copy()
    held[wide] = 0  # no heap (push_bottom_range skips a cap of 0): the groups stay runs of slots
    fewer = quota_groups(held, words, per_slot=FINDER_SLOT_WORDS + 1)
    passes = sum(1 for lo, hi in fewer if held[lo:hi].any()) + 2 * -(-len(wide) // SlotRadix.per_pass(words))
    return (wide, held, fewer) if passes < len(groups) else (wide[:0], caps, groups)


def standing_cuts(rules, feed, words: int = STANDING_WORDS) -> np.ndarray:
    """Each capped slot's q-th smallest priority among the points ``feed`` gives (``feed(finder)`` calls
    ``finder.add_ids``), for a compaction of the spill in the middle of pass one (``rules``:
    :class:`.candidates.Standing`), a group of slots whose quotas, and 3 words a slot, fit ``words`` at a time.

    Unlike :func:`cutoffs_by_groups` a slot may see fewer than its quota: its cut is the largest priority,
    which keeps every point of it. A slot whose quota alone passes ``words`` gets an upper bound of its cut
    instead (:class:`SlotBuckets`: one pass for many such slots, a compaction keeps a few more rather than
    hold more); it kept every point, and a cloud of few bins with quotas past 4M points (10^10 points, 100
    bins, 1%) was never compacted: its spill reached 1.5 times the bound."""
    cut = np.full(len(rules.caps), np.iinfo(np.uint64).max, dtype=np.uint64)
    big = []
    wide, exact, groups = counted_slots(rules.caps, words)  # groups: + 3 words a slot, its caps widened
    per_pass = SlotRadix.per_pass(words)
    for lo, hi in groups:
        caps = np.ascontiguousarray(exact[lo:hi], dtype=np.int64)
        if hi - lo == 1 and caps[0] > words:
            big.append(lo)
            continue
        if not caps.any():  # every slot of the group counted instead: no pass for it
            continue
        finder = CutoffFinder(rules, lo, hi, caps)
        feed(finder)
        full = np.flatnonzero((finder.fill >= caps) & (caps > 0))
        cut[lo + full] = finder.heaps[finder.offsets[full]]
        del finder, full, caps  # before the next group's arrays: two groups' at once were the compaction's peak
    for a in range(0, len(wide), per_pass):
        slots = wide[a:a + per_pass]
        cut[slots] = SlotRadix(rules, slots).upper_cuts(rules.caps[slots], feed)
    at_once = max(1, words >> SlotBuckets.BUCKET_BITS)
    for a in range(0, len(big), at_once):
        slots = np.array(big[a:a + at_once], dtype=np.int64)
        counter = SlotBuckets(rules, slots)
        feed(counter)
        cut[slots] = counter.upper_cuts(rules.caps[slots])
        del counter
    return cut


class SlotBuckets:
    """Some capped slots' priorities counted in 2^16 buckets of their top bits, in one pass (``add_ids``, as a
    spill's index gives them): ``BUCKET_BITS`` words a slot, whatever its quota.

    :meth:`upper_cuts`: for each slot, the top of the bucket that holds its q-th smallest priority, an upper
    bound of the q-th smallest (the largest priority where the slot has fewer than q points). A compaction
    that keeps the points at or under it keeps every point the exact cut keeps, and those of the slot's
    points in the same bucket above it: about 1/65,536 of them."""

    BUCKET_BITS = PriorityCounter.BUCKET_BITS  # the radix select's buckets, a slot at a time

    def __init__(self, rules, slots: np.ndarray):
        self.rules, self.slots = rules, slots  # sorted slot numbers
        self.counts = np.zeros(len(slots) << self.BUCKET_BITS, dtype=np.int64)

    def add_ids(self, keys: np.ndarray, ids: np.ndarray) -> None:
        slot = self.rules.rule[keys].astype(np.int64) - 1  # a capped bin's rule is its slot + 1
        j = np.minimum(np.searchsorted(self.slots, slot), len(self.slots) - 1)
        inside = self.slots[j] == slot
        prios = kernels.priorities_of_np(ids[inside], self.rules.seed_mix)
        bucket = (prios >> np.uint64(64 - self.BUCKET_BITS)).astype(np.int64)
        np.add.at(self.counts, (j[inside] << self.BUCKET_BITS) + bucket, 1)

    def upper_cuts(self, caps: np.ndarray) -> np.ndarray:
        cum = np.cumsum(self.counts.reshape(len(self.slots), -1), axis=1)
        out = np.full(len(self.slots), np.iinfo(np.uint64).max, dtype=np.uint64)
        for r in range(len(self.slots)):
            b = int(np.searchsorted(cum[r], int(caps[r])))  # the first bucket where the count reaches q
            if b < cum.shape[1] - 1:
                out[r] = np.uint64(((b + 1) << (64 - self.BUCKET_BITS)) - 1)
        return out


class SlotRadix:
    """Upper bounds of many capped slots' q-th smallest priorities in two passes, ``2^BITS`` counts a slot: the
    first pass counts each slot's priorities by their top ``BITS`` bits and finds the bucket where the count
    reaches q; the second counts, inside that bucket only, the next ``BITS`` bits. The cut is the top of the
    2^-16-wide range so found (the same bound as :class:`SlotBuckets`, which holds 2^16 counts a slot): a
    compaction that keeps the points at or under it keeps every point the exact cut keeps, and those of the
    slot's points in the same range above it. A slot with fewer than q points keeps all, and so does one whose
    count in a bucket would pass 2^32 - 1 (4 bytes a count: past 10^12 points of one slot in the index)."""

    BITS = RADIX_BITS
    BLOCK = 1 << 10  # slots whose counts are summed at a time (a table of int64 sums, 2 MiB)
    _no_prefix = np.zeros(0, dtype=np.int64)

    MAP_SLOTS = 1 << 22  # slot numbers spanned by a map from slot to place (4 bytes each); past it, a search

    @classmethod
    def per_pass(cls, words: int) -> int:
        """Slots counted in one pair of passes within ``words`` 8-byte words twice over (what SlotBuckets and
        the exact heaps' finder hold: counts and their sums): 4 bytes a count, 2^BITS counts a slot."""
        return max(1, (16 * words) // (4 << cls.BITS))

    def __init__(self, rules, slots: np.ndarray):
        self.rules, self.slots = rules, np.ascontiguousarray(slots, dtype=np.int64)  # sorted slot numbers
        self.prefix = None  # pass two: each slot's first-pass bucket
        self.counts = np.zeros(len(slots) << self.BITS, dtype=np.uint32)
        self.full = np.zeros(len(slots), dtype=np.uint8)  # a count would have passed 2^32 - 1: keep all
        place = np.zeros(0, dtype=np.int32)  # rule value - the first slot's rule -> the slot's place, or -1
        span = int(self.slots[-1] - self.slots[0]) + 1 if len(slots) else 0
        if span <= self.MAP_SLOTS:  # a gather instead of a binary search: 10 times faster a point
            place = np.full(span, -1, dtype=np.int32)
            place[self.slots - self.slots[0]] = np.arange(len(slots), dtype=np.int32)
        self.where = (np.int64(self.slots[0] if len(slots) else 0), place, self.slots)

    def add_ids(self, keys: np.ndarray, ids: np.ndarray) -> None:
        prefix = self._no_prefix if self.prefix is None else self.prefix
        if len(keys) != len(ids):  # the loop reads both to the keys' end
            raise ValueError(f"{len(keys)} keys for {len(ids)} ids")
        keys, ids = kernels.read_only(keys, np.uint32), kernels.read_only(ids, np.uint64)  # one compiled type
        kernels.radix_count(keys, ids, self.rules.seed_mix, self.rules.rule, self.where, prefix,
                            (self.counts, self.full))

    def _reach(self, caps: np.ndarray, below: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For each slot, the first bucket where ``below`` plus the running count reaches its cap (0 if
        none), whether one does, and the count before that bucket (``below`` included): a block of slots at a
        time, the sums in int64."""
        n = len(self.slots)
        at, reach, before = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.bool_), below.copy()
        table = self.counts.reshape(n, -1)
        for a in range(0, n, self.BLOCK):
            b = min(n, a + self.BLOCK)
            cum = np.cumsum(table[a:b], axis=1, dtype=np.int64)
            cum += below[a:b, None]
            hit = cum >= caps[a:b, None]
            reach[a:b] = hit[:, -1]
            at[a:b] = f = np.argmax(hit, axis=1)
            before[a:b] = np.where(f > 0, cum[np.arange(b - a), np.maximum(f - 1, 0)], below[a:b])
        return at, reach, before

    def upper_cuts(self, caps: np.ndarray, feed) -> np.ndarray:
        """The slots' cuts: ``feed(self)`` twice, as :func:`standing_cuts` feeds a finder."""
        caps = caps.astype(np.int64)
        n = len(self.slots)
        out = np.full(n, np.iinfo(np.uint64).max, dtype=np.uint64)
        feed(self)
        first, reach, below = self._reach(caps, np.zeros(n, dtype=np.int64))  # the bucket where it reaches q
        reach &= self.full == 0  # the others keep every point
        self.prefix = np.where(reach, first, -1)  # a slot that never reaches q counts nothing more
        self.counts[:] = 0
        feed(self)
        second, again, _ = self._reach(caps, below)
        reach &= self.full == 0  # a count would have passed 2^32 - 1 in the second pass: keeps every point
        if (reach & ~again).any():  # the second pass saw fewer points than the first
            raise AssertionError("a compaction's second counting pass saw fewer points than its first")
        at = np.flatnonzero(reach)
        top = (((first[at] << self.BITS) | second[at]) + 1).astype(np.uint64)  # the range above the q-th
        out[at] = (top << np.uint64(64 - 2 * self.BITS)) - np.uint64(1)  # top = 2^16 wraps to the largest
        return out


def find_cutoffs(rules: Rules, sources, chunk_size: int, keys_of, bar=None, words: int = CUTOFF_WORDS) -> Cutoffs:
    """Cutoffs from scans of every source's bin keys, ``chunk_size`` points at a time (one scan while the
    sample's heaps fit ``words``).

    ``keys_of(source, start, n)`` gives the keys of records [start, start + n)
    of a source (a key cache, a memory map...); nothing is read when no bin
    is capped. ``bar`` follows the first scan.
    """
    scans = [0]

    def feed(finder):
        for src in sources:
            for a in range(0, src.count, chunk_size):
                n = min(chunk_size, src.count - a)
                finder.add(keys_of(src, a, n), (src.ordinal << kernels.ID_SHIFT) | a)
                if bar is not None and not scans[0]:
                    bar.update(n)
        scans[0] += 1

    return cutoffs_by_groups(rules, feed, words)


def merge_bottom_sets(caps: np.ndarray, lo: int, hi: int, *parts) -> tuple[np.ndarray, np.ndarray]:
    """Bottom sets (slot, priority) of slots [lo, hi) merged: each slot's ``caps[slot]`` smallest priorities.

    The bounded merge of every reduce: associative, so partial results can
    be merged in any grouping (a tree on a cluster, or all at once). Parts
    in slot order (what this merge returns) are cut to [lo, hi) without a
    copy and merged a range of slots at a time (:func:`.keyblocks.merged`:
    the temporaries one range's, not a sort's index and copies of all of
    them); if any part is in another order (a unit's pairs as read, before
    :func:`bounded_bottoms` merges them), all of them are merged whole.
    """
    parts = [(np.asarray(p[0]), np.asarray(p[1])) for p in parts]
    if all(not (p[0][1:] < p[0][:-1]).any() for p in parts):
        within = []
        for slots, prios in parts:
            a, b = np.searchsorted(slots, [lo, hi], side="left")
            within.append((slots[a:b], prios[a:b]))
        return keyblocks.merged(lambda some: _smallest_of_slots(caps, some), within)
    return _smallest_of_slots(caps, parts, lo, hi)


def _smallest_of_slots(caps: np.ndarray, parts, lo: int | None = None,
                       hi: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each slot's ``caps[slot]`` smallest priorities of ``parts`` (of slots [lo, hi) only, when given), by slot."""
    slots = np.concatenate([p[0] for p in parts]).astype(np.int64) if parts else np.zeros(0, np.int64)
    prios = np.concatenate([p[1] for p in parts]).astype(np.uint64) if parts else np.zeros(0, np.uint64)
    if lo is not None:
        inside = (slots >= lo) & (slots < hi)
        slots, prios = slots[inside], prios[inside]
    order = np.lexsort((prios, slots))
    slots, prios = slots[order], prios[order]
    rank = np.arange(len(slots)) - np.searchsorted(slots, slots, side="left")
    keep = rank < caps[slots]
    return slots[keep], prios[keep]


def spill_bottoms(rules: Rules, index_chunks, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`bounded_bottoms` from a unit's candidate spill (``index_chunks`` yields its (keys, ids))
    instead of its records. Not the same set, but merged over every unit the same cutoffs: each point the
    sample selects is a candidate of its unit, so the union holds every bin's q_b smallest, and a bound
    under the cutoff still leaves fewer than q_b points (and the bin is redone)."""
    slots, prios = [np.zeros(0, np.int64)], [np.zeros(0, np.uint64)]
    for keys, ids in index_chunks:
        slot, prio = _under_bounds(rules, keys, kernels.priorities_of(ids, rules.seed_mix), bounds)
        slots.append(slot)
        prios.append(prio)
    return merge_bottom_sets(rules.caps, 0, len(rules.caps), (np.concatenate(slots), np.concatenate(prios)))


def _under_bounds(rules: Rules, keys: np.ndarray, prios: np.ndarray, bounds: np.ndarray) -> tuple:
    """(slot, priority) of the points in capped bins whose priority is at or under their bin's bound."""
    slot = rules.rule[keys] - 1  # a capped bin's slot (drop and keep-all are below 0)
    capped = slot >= 0
    slot, prio = slot[capped], prios[capped]
    under = prio <= bounds[slot]
    return slot[under], prio[under]


def bounded_bottoms(rules: Rules, keyed_chunks, ordinal: int, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One unit's bottom set (slot, priority), keeping only priorities at or under each capped bin's bound.

    ``keyed_chunks`` yields (first record, keys). The unit's q_b smallest
    among its priorities under the bound are exactly its q_b smallest
    intersected with "under the bound"; a bound near the cutoff leaves about
    q_b/n_b of the points, so no heap as large as the sample is allocated.
    """
    slots, prios = [], []
    for start, keys in keyed_chunks:
        prio = kernels.priorities(np.uint64((ordinal << kernels.ID_SHIFT) | start), len(keys), rules.seed_mix)
        slot, prio = _under_bounds(rules, keys, prio, bounds)
        slots.append(slot)
        prios.append(prio)
    if not slots:
        return np.zeros(0, np.int64), np.zeros(0, np.uint64)
    return merge_bottom_sets(rules.caps, 0, len(rules.caps), (np.concatenate(slots), np.concatenate(prios)))


def read_cutoffs(caps: np.ndarray, lo: int, hi: int, merged) -> tuple[np.ndarray, np.ndarray]:
    """(slots of [lo, hi) with fewer than their cap, cutoff of every slot) from a merged bottom set.

    A short slot's cutoff is meaningless (0): its bin was not fully seen.
    """
    slots, prios = merged
    have = np.bincount(np.asarray(slots, np.int64) - lo, minlength=hi - lo)
    want = caps[lo:hi]
    short = np.flatnonzero(have < want)
    starts = np.searchsorted(slots, np.arange(lo, hi), side="left")
    cut = np.zeros(hi - lo, dtype=np.uint64)
    full = have >= want
    cut[full] = prios[starts[full] + want[full] - 1]
    return short + lo, cut


def merge_bottoms(rules: Rules, parts: list[tuple[np.ndarray, np.ndarray]]) -> Cutoffs:
    """Cutoffs from several units' bottom sets (slot, priority): the whole reduce at once."""
    n = len(rules.caps)
    short, cut = read_cutoffs(rules.caps, 0, n, merge_bottom_sets(rules.caps, 0, n, *parts))
    if len(short):
        raise AssertionError("cutoff merge saw fewer points than the histogram counted")
    return Cutoffs(rules.capped_keys.copy(), cut)


def cutoff_table(plan: Plan, cutoffs: Cutoffs, rules: Rules | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(rule, cut): the dense arrays :func:`kernels.keep_mask` reads."""
    rules = rules if rules is not None else Rules(plan)
    if not np.array_equal(rules.capped_keys, cutoffs.keys):
        raise ValueError("cutoffs do not belong to this plan")
    return rules.rule, cutoffs.cut
