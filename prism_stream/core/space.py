"""A spatial share (``--space A``, SPEC 9): the spatial order streamed, and its merge with PRISM's.

The spatial order lists, level by level from the coarsest, one winner of
every occupied cell of a grid anchored at 0 whose cells halve one axis a
level (x, then y, then z: cubes every third level), the winner of a cell
being its point of the smallest (rarity, priority), a level's new cells the
most populous first. That winner order does not depend on the level, so the
winner of a cell is the winner of each smaller cell it lies in: the winners
(and point counts) of a level follow from those of any finer level by
halving one axis's indices and keeping each cell's smallest (summing its
counts).

:class:`SpatialScan` therefore tracks one level only: every point's cell at
that level, merged chunk by chunk into one winner and one count per cell.
Whenever it holds more than ``2 T`` cells it moves up (a level has at most
twice the occupied cells of the one above, so ``occupied(l + 1) > T``), and
the level it ends on is never coarser than the first level with T occupied
cells, which is where SPEC 9's order stops. The state is 56 bytes a cell, at
most ``2 T + 1`` cells after a merge, beside the chunk winners buffered until
the next merge (a quarter as many; :func:`state_bytes` bounds it all).
:meth:`SpatialScan.order` then walks up to the top level and lists the order;
:func:`merge` interleaves it with PRISM's rank order.

Nothing here depends on how the input was cut into chunks: the tracked
level is the finest with at most ``2 T`` occupied cells (SPEC 9's last level
for the points seen so far, 186 below their top, and the first block's own
finest such level, are bounds only a finer level would cross), a cell's
winner is a minimum and its count a sum.
"""

from __future__ import annotations

import math
import numpy as np

from . import kernels
from .kernels import splitmix64_np

MILLION = 10**6
LEVELS_BELOW_TOP = 186  # SPEC 9: never past 62 halvings of each axis below the top level (indices below 2^62)
CELL_BYTES = 56  # three int64 cell indices, the rarity, the priority, the id and the count of points
BLOCK = 1 << 18  # points sorted at a time
SPREAD = 2  # a level has at most twice the occupied cells of the level above (one axis halved)
FLUSH_MIN = 1 << 16  # the fewest chunk winners a merge waits for


def parse_share(text) -> int:
    """``--space A`` as millionths: a decimal in [0, 1] written with ASCII digits and at most six of them after
    the point (SPEC 9)."""
    raw = str(text).strip()
    whole, point, frac = raw.partition(".")
    digits = set("0123456789")
    if not raw or raw == "." or not set(whole) <= digits or not set(frac) <= digits:
        raise ValueError(f"--space takes a number from 0 to 1 (a share of the target), not {text!r}")
    if len(frac) > 6:
        raise ValueError(f"--space {raw}: at most six digits after the point")
    value = int(whole or "0") * MILLION + int((frac + "000000")[:6])
    if value > MILLION:
        raise ValueError(f"--space {raw}: the spatial share is at most 1 (1: every point placed spatially)")
    return value


def share_text(a: int) -> str:
    """A share in millionths as the provenance and the summaries write it: ``0.5``, ``1``, ``0.000001``."""
    whole, frac = divmod(int(a), MILLION)
    return f"{whole}.{frac:06d}".rstrip("0").rstrip(".")


def share(a: int, t: int) -> int:
    """How many of the first ``t`` places are spatial: round(A t), halves up, in integers."""
    return (a * t + MILLION // 2) // MILLION


def state_bytes(target: int) -> int:
    """The most memory the spatial scan holds for a target of ``target`` points, a quarter over the arrays'
    own bytes (the allocator's share, measured): the state (at most ``2 T + 1`` cells past a merge) and the
    new state a merge makes (one copy), the chunk winners buffered (a quarter of the state, or 2^18, and one
    block more) with their concatenation and its sort, and one block's own sort."""
    cap = max(SPREAD * max(target, 1) + 1, 8)
    buffered = max(cap // 4, FLUSH_MIN) + BLOCK
    return (2 * cap * CELL_BYTES + buffered * (2 * CELL_BYTES + 40) + BLOCK * 150) * 5 // 4


MEMORY_BUDGET = 300 << 20  # the most an in-memory scan holds (:func:`state_bytes`); past it, the points on disk
POINT_BYTES = 36  # a point on disk: x, y, z (float64), its bin key (uint32) and id (uint64)
BIRTH_BYTES = 32  # a birth on disk: level, count, cell priority, id


def on_disk(target: int) -> bool:
    """Whether a scan for ``target`` keeps its points on disk (its cells would not fit the memory budget)."""
    return state_bytes(target) > MEMORY_BUDGET


MERGED_AT_ONCE = 256 << 21  # the most records a sort on disk merges in one pass (run/extsort: FAN_IN runs of
# 2^21); past it, passes write some of them once more


def disk_bytes(points: int, target: int | None = None) -> int:
    """The most temporary disk the scan of ``points`` points takes on disk: every point in the points' file
    and once more in the files it is routed to while the first is read (each file is removed once routed),
    the births of the files too large to load (at most one a point), and a byte a point of the small files'
    Morton order kept for their second visit. Then, with the ``target``: the sort of the listed births
    (fewer than 2 T, and at most one a point) beside the small files, the births and their order; and the
    merge's (engines/spatial_merge.py): both orders' ids (8 bytes a place each), their sort by id (24 bytes
    a record, 2 T records) and the pairs of ids in both (16 bytes, at most T a side). A sort past
    :data:`MERGED_AT_ONCE` records writes up to as many again in its passes. The largest of the three."""
    scan = points * (2 * POINT_BYTES + BIRTH_BYTES + 1)
    if target is None:
        return scan
    births = min(2 * target, points)
    listed = points * (POINT_BYTES + BIRTH_BYTES + 1) + births * BIRTH_BYTES * (2 if births > MERGED_AT_ONCE else 1)
    return max(scan, listed, _merge_bytes(target))


def _merge_bytes(target: int) -> int:
    return target * (8 + 8 + 48 + (48 if 2 * target > MERGED_AT_ONCE else 32))


def cluster_disk_bytes(points: int, target: int) -> tuple[int, int]:
    """:func:`disk_bytes` of a Dask run, split between where its parts go: (the staging folder, which holds
    the scan's files and the listed births' sorted runs; the driver's temporary folder, which holds the runs'
    merge passes and the merge with PRISM's order). On one disk, :func:`disk_bytes` is the most of both."""
    births = min(2 * target, points)
    staged = max(points * (2 * POINT_BYTES + BIRTH_BYTES + 1), points * (POINT_BYTES + BIRTH_BYTES + 1)
                 + births * BIRTH_BYTES)
    return staged, max(births * BIRTH_BYTES if births > MERGED_AT_ONCE else 0, _merge_bytes(target))


def largest_target(budget: int) -> int:
    """The largest target whose :func:`state_bytes` is within ``budget``."""
    lo, hi = 0, 1 << 40
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if state_bytes(mid) <= budget:
            lo = mid
        else:
            hi = mid - 1
    return lo


def exponents(level: int) -> tuple[int, int, int]:
    """The cell sides of ``level``: 2^ex, 2^ey, 2^ez, ex = floor(l / 3), ey = floor((l + 1) / 3), ez = floor((l + 2)
    / 3) (SPEC 9): one level finer halves x, then y, then z."""
    return level // 3, (level + 1) // 3, (level + 2) // 3


def _axis_exponent(low: float, high: float) -> int | None:
    """The smallest e with -2^e <= every coordinate < 2^e on an axis whose coordinates lie in [low, high]
    (None: every coordinate 0)."""
    need = []
    if high > 0:
        need.append(math.frexp(high)[1])  # high < 2^e
    if low < 0:
        mantissa, e = math.frexp(-low)
        need.append(e - 1 if mantissa == 0.5 else e)  # -low <= 2^e
    return max(need) if need else None


def top_level(low, high) -> int | None:
    """SPEC 9's top level of points within these bounds a axis: the finest at which every cell index is -1 or 0
    (None: every coordinate 0, one cell at every level)."""
    ex, ey, ez = (_axis_exponent(float(a), float(b)) for a, b in zip(low, high))
    need = [3 * ex if ex is not None else None, 3 * ey - 1 if ey is not None else None,
            3 * ez - 2 if ez is not None else None]
    need = [v for v in need if v is not None]
    return max(need) if need else None


def cells_at(xyz: np.ndarray, level: int) -> np.ndarray:
    """(n, 3) int64 cell indices of ``level``: floor(coordinate * 2^-e) a axis, exact in float64."""
    out = np.empty((len(xyz), 3), np.int64)
    for axis, e in enumerate(exponents(level)):
        out[:, axis] = np.floor(np.ldexp(xyz[:, axis], -e))
    return out


def shifted(cells: np.ndarray, level: int, to: int) -> np.ndarray:
    """Cells of ``level`` as the cells of the coarser level ``to`` holding them: floor(i / 2^d) a axis."""
    out = np.empty_like(cells)
    for axis, (a, b) in enumerate(zip(exponents(level), exponents(to))):
        out[:, axis] = cells[:, axis] >> (b - a)
    return out


def _bounds(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each axis's smallest and largest cell index (a column at a time: a reduce over the rows of an (n, 3)
    array strides through memory)."""
    return (np.array([cells[:, a].min() for a in range(3)], np.int64),
            np.array([cells[:, a].max() for a in range(3)], np.int64))


def _word_bits(lo: np.ndarray, hi: np.ndarray) -> list | None:
    """Each axis's bits for indices from ``lo`` to ``hi`` packed in one int64, or None when they need more."""
    span = hi - lo
    if np.any(span < 0):  # the span itself overflowed int64
        return None
    bits = [int(v).bit_length() for v in span]
    return bits if sum(bits) <= 63 else None


def _pack(cells: np.ndarray, lo: np.ndarray, bits: list) -> np.ndarray:
    """One int64 per cell, ordered as the (x, y, z) triples are (``bits`` from :func:`_word_bits`)."""
    return ((cells[:, 0] - lo[0]) << (bits[1] + bits[2])) | ((cells[:, 1] - lo[1]) << bits[2]) | (cells[:, 2] - lo[2])


def _packed(cells: np.ndarray) -> np.ndarray | None:
    """One int64 per cell ordered as the (x, y, z) triples are, when the three index ranges fit in 63 bits."""
    if len(cells) == 0:
        return np.zeros(0, np.int64)
    lo, hi = _bounds(cells)
    bits = _word_bits(lo, hi)
    return None if bits is None else _pack(cells, lo, bits)


def _cell_sort(cells: np.ndarray, *minor) -> tuple[np.ndarray, np.ndarray]:
    """The order of the cells ascending (then by ``minor``, last given first), and where a new cell starts."""
    key = _packed(cells)
    if key is not None:
        by = np.lexsort((*minor, key))
        first = np.empty(len(by), bool)
        if len(by):
            k = key[by]
            first[0] = True
            np.not_equal(k[1:], k[:-1], out=first[1:])
        return by, first
    by = np.lexsort((*minor, cells[:, 2], cells[:, 1], cells[:, 0]))
    c = cells[by]
    first = np.empty(len(by), bool)
    if len(by):
        first[0] = True
        np.any(c[1:] != c[:-1], axis=1, out=first[1:])
    return by, first


def _distinct(cells: np.ndarray) -> int:
    key = _packed(cells)
    if key is None:
        return int(np.count_nonzero(_cell_sort(cells)[1]))
    k = np.sort(key)
    return 1 + int(np.count_nonzero(k[1:] != k[:-1])) if len(k) else 0


def _winner_index(cells: np.ndarray, rarity: np.ndarray, prio: np.ndarray, counts: np.ndarray):
    """For each distinct cell (ascending), the index of its point of the smallest (rarity, priority), and the
    sum of its counts."""
    key = _packed(cells)
    if key is None:  # indices too far apart for one word: sort by the three
        by, first = _cell_sort(cells, prio, rarity)
        return by[first], np.add.reduceat(counts[by], np.flatnonzero(first))
    by = np.argsort(key)  # one word a cell; the winner is found by value, so the sort need not be stable
    win, summed = kernels.cell_winners(key[by], by, rarity, prio, counts)  # one pass over each run of equal cells
    # the sums are a view of an array of a point each: copied, a buffered chunk's winners hold their own bytes
    # alone (held as views, a block's 2 MiB each: 100M points peaked 290 MiB higher, bench/RESULTS_SPACE.md)
    return win, summed.copy()


def _winners(cells: np.ndarray, rarity: np.ndarray, prio: np.ndarray, ids: np.ndarray, counts: np.ndarray):
    """Each distinct cell once, with its point of the smallest (rarity, priority) and the sum of its counts,
    cells ascending."""
    if len(cells) == 0:
        return cells, rarity, prio, ids, counts
    keep, summed = _winner_index(cells, rarity, prio, counts)
    return cells[keep], rarity[keep], prio[keep], ids[keep], summed


def _merged(state: tuple, incoming: tuple, lo: np.ndarray, hi: np.ndarray) -> tuple:
    """Two sets of cell winners (each cells ascending, each cell once) as one: a cell in both keeps the
    smaller (rarity, priority) and the sum of the counts. ``lo`` and ``hi`` bound both sets' indices a
    axis. ``state`` is updated in place and the new cells inserted where they sort (one copy of the state,
    no sort of it); cells too far apart for one word are sorted again together."""
    cells, rarity, prio, ids, counts = state
    c_in, r_in, p_in, i_in, n_in = incoming
    bits = _word_bits(lo, hi)
    if bits is None:
        return _winners(*(np.concatenate((a, b)) for a, b in zip(state, incoming)))
    keys = _pack(cells, lo, bits)
    k_in = _pack(c_in, lo, bits)
    at = np.searchsorted(keys, k_in)
    found = at < len(keys)
    found[found] = keys[at[found]] == k_in[found]
    del keys
    hit, src = at[found], np.flatnonzero(found)
    better = (r_in[src] < rarity[hit]) | ((r_in[src] == rarity[hit]) & (p_in[src] < prio[hit]))
    take, from_in = hit[better], src[better]
    rarity[take], prio[take], ids[take] = r_in[from_in], p_in[from_in], i_in[from_in]
    counts[hit] += n_in[src]
    new = np.flatnonzero(~found)
    if len(new) == 0:
        return state
    where = at[new]
    return (np.insert(cells, where, c_in[new], axis=0), np.insert(rarity, where, r_in[new]),
            np.insert(prio, where, p_in[new]), np.insert(ids, where, i_in[new]), np.insert(counts, where, n_in[new]))


class SpatialScan:
    """The winners of one level's occupied cells, fed chunk by chunk (see the module's docstring)."""

    def __init__(self, target: int, cap: int | None = None, lowest: int | None = None, coarse: bool = False):
        self.target = int(target)
        # more cells than this: the level above has more than T; and at least 8, the most the top level has,
        # so that the scan never moves past the top level (whose number the cell priorities hash). A smaller
        # ``cap`` (a scan whose cells would not fit, :mod:`..engines.spatial_disk`) may stop coarser than the
        # first level with T cells; ``lowest``: a level it never goes below (the whole input's last level,
        # for a scan of a part of it)
        self.cap = max(SPREAD * max(self.target, 1) + 1, 8) if cap is None else max(int(cap), 8)
        self.lowest = lowest
        # start no finer than where the first chunk's cells pack in one word: the scan then may stop coarser
        # than SPEC 9's last level, which only a scan whose order goes below its level (on disk) may do
        self.coarse = coarse
        self.flush_at = max(self.cap // 4, FLUSH_MIN)  # chunk winners buffered before a merge
        self.level: int | None = None
        # every point so far at (0, 0, 0): the one cell, (0, 0, 0) at every level, fits any level, so the level
        # is not fixed yet (the next point elsewhere sets it, as a first chunk would)
        self.origin = False
        self.low = self.high = None  # each axis's smallest and largest coordinate so far
        self.state = None
        self.lo = self.hi = None  # each axis's smallest and largest index in the state
        self.buffer: list = []
        self.buffered = 0
        self.points = 0

    def add(self, xyz: np.ndarray, rarity: np.ndarray, prio: np.ndarray, ids: np.ndarray) -> None:
        """One chunk: coordinates (n, 3) float64, rarities (uint64), priorities and ids (uint64)."""
        n = len(ids)
        if n == 0:
            return
        self.points += n
        low, high = xyz.min(axis=0), xyz.max(axis=0)
        self.low = low if self.low is None else np.minimum(self.low, low)
        self.high = high if self.high is None else np.maximum(self.high, high)
        top = top_level(self.low, self.high)
        # the spec's last level for the points so far (62 halvings of each axis below the top): every index
        # below 2^62 there; it only rises as points come
        floor = 0 if top is None else top - LEVELS_BELOW_TOP
        if self.lowest is not None:
            floor = self.lowest if top is None else max(floor, self.lowest)
        if self.level is None or self.origin:  # a subset's fitting level is never coarser than the whole chunk's
            cells = cells_at(xyz[:BLOCK], floor)
            self.level = self._fitting(cells, floor)
            if self.coarse and top is not None:
                self.level = max(self.level, fitting_base(cells, floor, top))
            self.origin = top is None
        elif self.level < floor:
            self._flush()
            self._up(floor - self.level)
        for a in range(0, n, BLOCK):  # a block at a time: the sort's temporaries stay small
            b = min(n, a + BLOCK)
            part = _winners(cells_at(xyz[a:b], self.level), rarity[a:b], prio[a:b], ids[a:b],
                            np.ones(b - a, np.int64))
            self.buffer.append(part)
            self.buffered += len(part[0])
            if self.buffered > self.flush_at:
                self._flush()

    def settled(self) -> "SpatialScan":
        """This scan with its buffered chunk winners merged in (what is sent to fold into another)."""
        self._flush()
        return self

    def absorb(self, other: "SpatialScan") -> None:
        """Fold in the scan of other points (another work unit's, ids of their own): this scan then holds what
        one scan of both inputs would hold at the coarser of the two levels, or the last level the bounds of
        both allow (both are no finer than the first level with T cells: a scan moves up only to a level with
        more than T). A cell in both keeps the smaller winner and the sum of the counts; then the scan moves up
        while it holds more than ``cap`` cells, as after a chunk."""
        if other.target != self.target:
            raise ValueError(f"scans of targets {self.target} and {other.target} do not fold")
        other._flush()
        if other.state is None:
            return
        self._flush()
        if self.state is None:
            self.level, self.low, self.high, self.lo, self.hi = other.level, other.low, other.high, other.lo, other.hi
            self.state, self.points, self.origin = tuple(a.copy() for a in other.state), other.points, other.origin
            return
        self.points += other.points
        self.low, self.high = np.minimum(self.low, other.low), np.maximum(self.high, other.high)
        top = top_level(self.low, self.high)
        fixed = [lv for lv, free in ((self.level, self.origin), (other.level, other.origin)) if not free]
        level = max(*fixed, 0 if top is None else top - LEVELS_BELOW_TOP) if fixed else self.level
        if self.origin:  # the one cell (0, 0, 0), at any level
            self.level, self.origin = level, not fixed
        else:
            self._up(level - self.level)
        if other.origin:
            incoming, lo, hi = other.state, other.lo, other.hi  # read, not changed, by the merge
        else:
            cells, *rest = other.state
            incoming = _winners(shifted(cells, other.level, level), *rest)  # new arrays: ``other`` is not changed
            lo, hi = (shifted(b[None, :], other.level, level)[0] for b in (other.lo, other.hi))
        self.lo, self.hi = np.minimum(self.lo, lo), np.maximum(self.hi, hi)
        self.state = _merged(self.state, incoming, self.lo, self.hi)
        if len(self.state[0]) > self.cap:
            self._up(self._fitting(self.state[0], self.level) - self.level)

    def _fitting(self, cells: np.ndarray, level: int) -> int:
        """The finest level at or above ``level`` at which these cells (of ``level``) are at most ``cap``
        distinct ones: a finer level would be left as soon as they are merged. In Morton order two
        neighbours share a cell from a level on, so the cells of a level are one more than the neighbours
        still apart there: the level is the (n - cap)-th smallest of those (the top level has at most 8 cells,
        never more than ``cap``)."""
        n = len(cells)
        if n <= self.cap:
            return level
        _, joins = morton_order(cells, level)
        return max(level, int(np.partition(joins, n - self.cap - 1)[n - self.cap - 1]))

    def _flush(self) -> None:
        parts = self.buffer
        self.buffer, self.buffered = [], 0
        if not parts:
            return
        incoming = _winners(*(np.concatenate([p[i] for p in parts]) for i in range(5)))
        lo, hi = _bounds(incoming[0])
        if self.state is None:
            self.state, self.lo, self.hi = incoming, lo, hi
        else:
            self.lo, self.hi = np.minimum(self.lo, lo), np.maximum(self.hi, hi)
            self.state = _merged(self.state, incoming, self.lo, self.hi)
        if len(self.state[0]) > self.cap:
            self._up(self._fitting(self.state[0], self.level) - self.level)

    def _up(self, steps: int) -> None:
        """Move ``steps`` levels up: each cell there keeps its smallest winner and the sum of the counts."""
        if steps > 0:
            cells, *rest = self.state
            self.state = _winners(shifted(cells, self.level, self.level + steps), *rest)
            self.lo, self.hi = (shifted(b[None, :], self.level, self.level + steps)[0] for b in (self.lo, self.hi))
            self.level += steps

    @staticmethod
    def _plateau(cells: np.ndarray, level: int) -> int:
        """How many levels above ``level`` these distinct cells stay distinct and short of the top level: the
        levels a walk up may skip (each lists nothing). Distinct cells only merge going up, so a bisection."""
        low, high = _bounds(cells)
        if _in_top(low, high):
            return 0
        to_top = 1  # levels up to the top, from the bounds alone
        while not _in_top(*(shifted(b[None, :], level, level + to_top)[0] for b in (low, high))):
            to_top += 1
        lo, hi = 0, to_top - 1  # the answer: the largest d < to_top with no merge up to level + d
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if _distinct(shifted(cells, level, level + mid)) == len(cells):
                lo = mid
            else:
                hi = mid - 1
        return lo

    def order(self, seed: int) -> np.ndarray:
        """SPEC 9's spatial order (ids), level by level from the top level down to the first level with at
        least T occupied cells (never past 186 levels below the top).

        Walking up from the tracked level (:meth:`walk`), each cell's winner goes on to its parent cell unless
        a sibling's is smaller: then it is listed at this level (its birth), with its cell's count and
        priority here. The survivors of the top level are listed there. The order is every point born at or
        above the last level, by (level descending, count descending, cell priority, priority). Memory: a few
        words a cell of the tracked level, whatever the number of levels."""
        self._flush()
        if self.state is None or self.points == 0:
            return np.zeros(0, np.uint64)
        born, mass, cell_prio, occupied, top = self.walk(seed)
        last = last_level(occupied, self.target, max(self.level, top - LEVELS_BELOW_TOP))
        return listed_order(born, mass, cell_prio, self.state[2], self.state[3], last)

    def walk(self, seed: int) -> tuple:
        """The tracked level's winners walked up to the top level: each one's birth level, its cell's count
        and cell priority there (SPEC 9), the occupied cells of every level from the tracked one up, and the
        top level."""
        cells, rarity, prio, ids, counts = self.state
        n = len(ids)
        mix = cell_mix(seed)
        born = np.empty(n, np.int64)
        mass = np.empty(n, np.int64)
        cell_prio = np.empty(n, np.uint64)
        alive = np.arange(n)  # the tracked cells' entries still a winner at this level
        c, cnt, level = cells, counts, self.level
        occupied = {}

        def listed(at, where, here_cells, here_counts):
            born[at] = level
            mass[at] = here_counts
            cell_prio[at] = cell_priorities(mix, level, here_cells[where])

        while True:
            occupied[level] = len(alive)
            if _in_top(c.min(), c.max()):  # the top level: the finest whose every index is -1 or 0
                listed(alive, slice(None), c, cnt)
                top = level
                break
            up = shifted(c, level, level + 1)
            win, summed = _winner_index(up, rarity[alive], prio[alive], cnt)
            if len(win) == len(alive):  # no two cells merge: nothing is listed here; skip to the next level
                c, level = up, level + 1  # where two do (or the top), by bisection rather than a sort a level
                skip = self._plateau(c, level)
                for lv in range(level, level + skip):
                    occupied[lv] = len(alive)
                c, level = shifted(c, level, level + skip), level + skip
                continue
            lost = np.ones(len(alive), bool)
            lost[win] = False
            listed(alive[lost], lost, c, cnt[lost])
            alive, c, cnt = alive[win], up[win], summed
            level += 1
        return born, mass, cell_prio, occupied, top


def cell_mix(seed: int) -> np.uint64:
    """splitmix64(seed + 2): the first word of every cell priority (SPEC 9)."""
    return splitmix64_np(np.array([(seed + 2) % (1 << 64)], np.uint64))[0]


def cell_priorities(mix, level: int, cells: np.ndarray) -> np.ndarray:
    """SPEC 9's cell priority of each of ``cells`` ((n, 3) int64) of ``level`` (``mix``: :func:`cell_mix`)."""
    h = splitmix64_np(np.full(len(cells), mix, np.uint64) ^ np.uint64(level % (1 << 64)))
    for axis in range(3):
        h = splitmix64_np(h ^ np.ascontiguousarray(cells[:, axis]).view(np.uint64))
    return h


def last_level(occupied: dict, target: int, fallback: int) -> int:
    """SPEC 9's last level from the occupied cells of levels (``occupied``: level -> cells, every level the
    answer may be): the coarsest with ``target`` cells, else ``fallback`` (the finest level there is)."""
    dense = [lv for lv, k in occupied.items() if k >= target]
    return max(dense) if dense else fallback


def listed_order(born, mass, cell_prio, prio, ids, last: int) -> np.ndarray:
    """The ids born at or above level ``last``, by (level descending, count descending, cell priority,
    priority): the spatial order of SPEC 9 down to its last level."""
    if len(born) and born.min() < last:
        keep = np.flatnonzero(born >= last)
        born, mass, cell_prio, prio, ids = born[keep], mass[keep], cell_prio[keep], prio[keep], ids[keep]
    if len(born) == 0:
        return ids[:0]
    # (level descending, count descending) as one word: a level's rank below the highest in its top bits,
    # the count's complement below (counts under 2^40; a sort key a word fewer, and no two negated copies)
    high = born.max()
    if high - born.min() < (1 << 22) and mass.max() < (1 << 40):
        first = ((high - born) << 40) | ((1 << 40) - 1 - mass)
        return ids[np.lexsort((prio, cell_prio, first))]
    return ids[np.lexsort((prio, cell_prio, -mass, -born))]


def _in_top(low, high) -> bool:
    """Whether cells with these smallest and largest indices are the top level's (every index -1 or 0)."""
    return bool(np.min(low) >= -1 and np.max(high) <= 0)


def merge(spatial: np.ndarray, prism: np.ndarray, a: int, t: int) -> tuple[np.ndarray, int]:
    """The first ``t`` places of SPEC 9's merge (ids, in place order), and how many the spatial order filled:
    place i is spatial when share(i + 1) > share(i); each side takes its next id not already taken (PRISM's
    when the spatial order is used up). ``prism`` must hold PRISM's first ``t`` ids in rank order. Memory: a
    few words a place (where each id is in the other order, found by a sort of each), the merge itself in
    :func:`.jit.merge_walk` (the one loop the merge on disk also runs, here over one block of each)."""
    if t == 0:
        return np.zeros(0, np.uint64), 0
    spatial = np.ascontiguousarray(spatial[:min(t, len(spatial))], np.uint64)
    prism = np.ascontiguousarray(prism[:t], np.uint64)
    s_other, p_other = _places_in(prism, spatial), _places_in(spatial, prism)
    state = np.array([0, 0, 0, 0, len(spatial), 0, 0, a, t], np.int64)
    out = np.empty(t, np.uint64)
    n, _ = kernels.merge_walk(spatial, s_other, prism, p_other, state, out)
    if n != t:
        raise AssertionError(f"the spatial share's merge filled {n} of {t} places (PRISM's order too short)")
    return out, int(state[3])


def _places_in(order: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Where each of ``ids`` is in ``order`` (-1: not there)."""
    if len(order) == 0:
        return np.full(len(ids), -1, np.int64)
    by = np.argsort(order)
    at = np.minimum(np.searchsorted(order[by], ids), len(order) - 1)
    return np.where(order[by[at]] == ids, by[at], -1).astype(np.int64, copy=False)


# ---- the levels below a tracked level, a part of the input at a time (engines/spatial_disk.py) ----------------
#
# With the items of a part (points, or cells of one level with their counts) sorted by their Morton code,
# every cell of every coarser level is a run of consecutive items, and two neighbours share a cell from one
# level on (where the code bits that tell them apart have all been dropped). So one sort gives every level's
# occupied cells (one more than the neighbours apart there) and, level by level, each run's winner.

_SIGN = np.uint64(1 << 63)
_LOW21 = np.uint64((1 << 21) - 1)


def _spread21(v: np.ndarray) -> np.ndarray:
    """The low 21 bits of each word spread to every third bit (bit i to bit 3 i)."""
    v = v & _LOW21
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def _varying_bits(cells: np.ndarray) -> list:
    """Each axis's low bits that are not the same in every cell (the bits above the highest one its smallest
    and largest index differ in are every index's)."""
    lo, hi = _bounds(cells)
    return [int(_bit_length(np.array([(int(a) ^ int(b)) & ((1 << 64) - 1)], np.uint64))[0]) for a, b in zip(lo, hi)]


def _code_bits(cells: np.ndarray, base: int) -> int:
    """How many low bits of the cells' Morton codes at ``base`` tell any two apart (0: all one cell)."""
    axes = [2 - ((base + j) % 3) for j in range(3)]
    bits = _varying_bits(cells)
    return max((3 * bits[a] - 2 + j if bits[a] else 0) for j, a in enumerate(axes))


def morton_words(cells: np.ndarray, base: int, words: int = 4) -> list:
    """Each cell's Morton code at ``base``, its lowest ``words`` words, the most significant first: bit s of
    the code is the bit the step from level base + s to base + s + 1 drops (z, then y, then x at a cube
    level; bit s // 3 of that axis's index, the sign flipped so that the order of the codes is the cells').
    Word k holds code bits 63 k to 63 k + 62."""
    axes = [2 - ((base + j) % 3) for j in range(3)]  # the axis each step of a triple halves, least first
    u = [np.ascontiguousarray(cells[:, a]).view(np.uint64) ^ _SIGN for a in axes]
    out = []
    for k in range(words):
        s = np.uint64(21 * k)
        out.append(_spread21(u[0] >> s) | (_spread21(u[1] >> s) << np.uint64(1))
                   | (_spread21(u[2] >> s) << np.uint64(2)))
    return out[::-1]


def _bit_length(x: np.ndarray) -> np.ndarray:
    """Each uint64's bit length (0 for 0), exact: its halves through float64."""
    hi = (x >> np.uint64(32)).astype(np.float64)
    lo = (x & np.uint64(0xFFFFFFFF)).astype(np.float64)
    return np.where(hi > 0, 32 + np.frexp(hi)[1], np.frexp(lo)[1]).astype(np.int64)


def morton_order(cells: np.ndarray, base: int) -> tuple[np.ndarray, np.ndarray]:
    """The items' order by Morton code at ``base``, and for each two neighbours in it the level from which
    they share a cell (``base``: already at ``base``). Only the code's words that tell two items apart are
    made and sorted (one, where every index's varying bits fit 21 a axis)."""
    n = len(cells)
    if n < 2:
        return np.arange(n), np.zeros(0, np.int64)
    nwords = -(-_code_bits(cells, base) // 63)
    if nwords == 0:
        return np.arange(n), np.full(n - 1, base, np.int64)
    words = morton_words(cells, base, nwords)
    by = np.argsort(words[0], kind="stable") if nwords == 1 else np.lexsort(words[::-1])
    bit = np.full(n - 1, -1, np.int64)  # the highest code bit two neighbours differ in (-1: none)
    for k, w in zip(range(nwords - 1, -1, -1), words):
        w = w[by]
        x = w[1:] ^ w[:-1]
        free = bit < 0
        bit[free] = np.where(x[free] != 0, 63 * k + _bit_length(x[free]) - 1, -1)
    return by, base + bit + 1


def fitting_base(cells: np.ndarray, base: int, stop: int) -> int:
    """The finest level from ``base`` to ``stop`` at which these cells' codes differ in their lowest word
    only (one word to sort): below it, cells apart at ``base`` may be taken for one. Cells on both sides of 0
    on an axis differ in their sign bits at every level (-1 and 0 never share a cell): their codes keep more
    words at any level, which :func:`morton_order` sorts all the same."""
    return min(stop, base + max(0, _code_bits(cells, base) - 63))


def occupied_counts(joins: np.ndarray, n: int, base: int, stop: int) -> np.ndarray:
    """The occupied cells of each level from ``base`` to ``stop - 1`` of ``n`` items whose neighbours (in
    Morton order) share a cell from level ``joins`` on."""
    if n == 0 or stop <= base:
        return np.zeros(max(stop - base, 0), np.int64)
    joined = np.bincount(np.clip(joins - base, 0, stop - base), minlength=stop - base + 1)
    return n - np.cumsum(joined)[:stop - base]


def births_below(cells: np.ndarray, levels: tuple, rarity: np.ndarray, prio: np.ndarray, counts: np.ndarray,
                 order: tuple | None = None) -> tuple:
    """The items listed at levels ``lowest`` to ``stop - 1`` (``levels``: (base, stop, lowest); SPEC 9's walk
    up, below a level ``stop`` whose every cell's items are all here): each one's index, birth level and its
    cell's count there. An item is listed at level b when it is its b-cell's winner and not its (b + 1)-cell's.
    ``order``: the items' :func:`morton_order` at ``base``, where it is known."""
    base, stop, lowest = levels
    lowest = max(lowest, base)
    n = len(cells)
    empty = (np.zeros(0, np.int64),) * 3
    if n == 0 or lowest >= stop:
        return empty
    by, joins = morton_order(cells, base) if order is None else order
    item_of = np.lexsort((prio, rarity))  # the items by (rarity, priority): the winner is the smallest rank
    rank = np.empty(n, np.int64)
    rank[item_of] = np.arange(n)
    runs = np.flatnonzero(np.r_[True, joins > lowest])  # the cells of level ``lowest``: runs of the order
    win = np.minimum.reduceat(rank[by], runs)
    mass = np.add.reduceat(counts[by], runs)
    apart = joins[runs[1:] - 1]  # the level from which each two neighbouring cells share one
    out_at, out_level, out_mass = [], [], []
    for level in range(lowest, stop):
        starts = np.r_[True, apart > level + 1]  # where a cell of the level above starts
        parent = np.flatnonzero(starts)
        up_win = np.minimum.reduceat(win, parent) if len(win) else win
        of = np.cumsum(starts) - 1  # each cell's parent
        lost = win != up_win[of]
        out_at.append(item_of[win[lost]])
        out_level.append(np.full(int(lost.sum()), level, np.int64))
        out_mass.append(mass[lost])
        win, mass, apart = up_win, np.add.reduceat(mass, parent), apart[parent[1:] - 1]
    return np.concatenate(out_at), np.concatenate(out_level), np.concatenate(out_mass)
