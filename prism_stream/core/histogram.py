"""The color histogram: what pass one counts, per unit, per source, and globally.

A :class:`Tally` is where pass one (:func:`.passes.scan`) counts one unit's
keys: densely over the key space, sparsely for a small unit, or (the local
engine's) into one shared histogram beside a key cache.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import keyblocks
from .bins import BinSpec
from .folding import Folding
from .sparse import mark, marks_for, sparse_zeros, table_runs


@dataclass(frozen=True)
class Histogram:
    """Sparse histogram: sorted bin keys and their point counts."""

    keys: np.ndarray  # uint32, sorted, unique
    counts: np.ndarray  # int64, > 0

    @property
    def total(self) -> int:
        return int(self.counts.sum())

    @property
    def bins(self) -> int:
        return int(self.keys.shape[0])

    @staticmethod
    def empty() -> "Histogram":
        return Histogram(np.zeros(0, np.uint32), np.zeros(0, np.int64))

    @staticmethod
    def from_dense(dense: np.ndarray, block: int = 1 << 20, runs=None) -> "Histogram":
        """The bins of a dense table of counts, ``block`` keys at a time: no int64 index as long as the
        bins (128 MB over 16M of them, beside the table itself). A boolean's nonzero: 4x faster than an integer
        array's. ``runs``: the (a, b) ranges of keys outside which the table holds 0 (the others are not read:
        pages the OS never mapped stay so)."""
        if runs is None:
            runs = [(a, min(a + block, len(dense))) for a in range(0, len(dense), block)]
        keys = np.concatenate([np.flatnonzero(dense[a:b] != 0).astype(np.uint32) + np.uint32(a)
                               for a, b in runs] or [np.zeros(0, np.uint32)])
        return Histogram(keys, dense[keys].astype(np.int64, copy=False))

    @staticmethod
    def from_keys(keys: np.ndarray) -> "Histogram":
        k, c = np.unique(np.asarray(keys, dtype=np.uint32), return_counts=True)
        return Histogram(k.astype(np.uint32), c.astype(np.int64))

    @staticmethod
    def sum(parts) -> "Histogram":
        """One histogram counting every part's points, a range of keys at a time (:func:`.keyblocks.merged`:
        the temporaries of a million bins of each part, not of all of them): in each range the smaller
        parts sorted together, then merged into the largest (:meth:`add`)."""
        keys, counts = keyblocks.merged(Histogram._sum_of_columns, [(p.keys, p.counts) for p in parts])
        return Histogram(keys, counts)

    @staticmethod
    def _sum_of_columns(parts: list) -> tuple[np.ndarray, np.ndarray]:
        h = Histogram._sum([Histogram(k, c) for k, c in parts])
        return h.keys, h.counts

    @staticmethod
    def _sum(parts) -> "Histogram":
        parts = sorted((p for p in parts if p.bins), key=lambda p: p.bins)
        if not parts:
            return Histogram.empty()
        largest = parts.pop()
        if not parts:
            return Histogram(largest.keys.astype(np.uint32), largest.counts.astype(np.int64))
        return largest.add(parts[0] if len(parts) == 1 else Histogram._sorted_sum(parts))

    @staticmethod
    def _sorted_sum(parts) -> "Histogram":
        keys = np.concatenate([p.keys for p in parts])
        counts = np.concatenate([p.counts for p in parts])
        order = np.argsort(keys, kind="stable")
        keys, counts = keys[order], counts[order]
        start = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        return Histogram(keys[start].astype(np.uint32), np.add.reduceat(counts, start).astype(np.int64))

    def add(self, other: "Histogram") -> "Histogram":
        """This histogram plus ``other``: the smaller one's keys looked up in the larger one's (a binary
        search each) and the new ones inserted, O(n + m log n) for sizes n >= m, with no sort of the larger
        (a 16.7M-bin total plus five 1M-point units: 0.5 s, against 4.5 s sorting them all together)."""
        a, b = (self, other) if self.bins >= other.bins else (other, self)
        counts = a.counts.astype(np.int64)  # a copy (int64 already: astype copies)
        if not b.bins:
            return Histogram(a.keys.astype(np.uint32), counts)
        at = np.searchsorted(a.keys, b.keys)
        found = np.zeros(b.bins, dtype=bool)
        inside = np.flatnonzero(at < a.bins)
        found[inside] = a.keys[at[inside]] == b.keys[inside]
        counts[at[found]] += b.counts[found].astype(np.int64)  # b's keys are distinct: so are their places in a
        new = ~found
        # np.insert puts values given for one place in their given (ascending) order, before a's key there
        return Histogram(np.insert(a.keys.astype(np.uint32), at[new], b.keys[new].astype(np.uint32)),
                         np.insert(counts, at[new], b.counts[new].astype(np.int64)))


@dataclass(frozen=True)
class DenseHistogram:
    """Counts as a table indexed by key (``table[key]``: the key's points), for sums of many bins: a table of
    4-byte counts over 2^24 keys takes 64 MiB, the same bins sparse (a 4-byte key and an 8-byte count each)
    up to 192 MiB. What :func:`fold` returns once a table is the smaller."""

    table: np.ndarray  # uint32 (while the total fits) or int64; its length a power of two
    bins: int  # keys with a count
    total: int  # points (the parts' total: not summed over the table again)

    def sparse(self) -> Histogram:
        return Histogram.from_dense(self.table)


SPARSE_BYTES = 12  # a sparse histogram's bytes a bin (a uint32 key, an int64 count)


def fold(parts) -> Histogram | DenseHistogram:
    """The sum of ``parts`` (:class:`Histogram` or :class:`DenseHistogram`), as a table over the keys they reach
    when that takes fewer bytes than the sum's bins sparse, else as a :class:`Histogram`: the same counts either
    way (:func:`as_histogram`). A table is made only when it could be the smaller (the parts' bins counted as if
    none were shared: a fold of few bins never allocates one), and kept only if it is (its bins counted: parts
    of one cloud share most of theirs). Over 2^24 keys a fold of millions of colors is 64 MiB, not up to
    200 MB."""
    parts = [p for p in parts if p.bins]
    if not parts:
        return Histogram.empty()
    top = max(len(p.table) if isinstance(p, DenseHistogram) else int(p.keys[-1]) + 1 for p in parts)
    space = 1 << max(top - 1, 0).bit_length()
    total = sum(p.total for p in parts)
    dtype = np.dtype(np.uint32) if total < 1 << 32 else np.dtype(np.int64)  # no bin can pass the total
    if space * dtype.itemsize > SPARSE_BYTES * min(space, sum(p.bins for p in parts)):
        return Histogram.sum([as_histogram(p) for p in parts])
    table = np.zeros(space, dtype)
    for p in parts:
        if isinstance(p, DenseHistogram):
            table[:len(p.table)] += p.table.astype(dtype, copy=False)
        else:
            table[p.keys] += p.counts.astype(dtype)  # a part's keys are distinct: no index twice
    bins = int(np.count_nonzero(table))
    if SPARSE_BYTES * bins < table.nbytes:
        return Histogram.from_dense(table)
    return DenseHistogram(table, bins, total)


def as_histogram(h) -> Histogram:
    """``h`` as a sparse :class:`Histogram` (what :func:`fold` returned)."""
    return h.sparse() if isinstance(h, DenseHistogram) else h


@dataclass
class SourceScan:
    """What pass one learned about one source file."""

    ordinal: int
    path: str
    points: int = 0
    depth: str = "8"  # "8", "16" or "float"
    max_value: int = 0
    extra: dict = field(default_factory=dict)  # format facts worth reporting (NaN points skipped...)

    def as_dict(self) -> dict:
        d = {"ordinal": self.ordinal, "path": self.path, "points": self.points, "color_depth": self.depth}
        if self.extra:
            d.update(self.extra)
        return d


REPORTED_FACTS = ("nan_points_skipped",)  # format facts a source's summary entry repeats


def source_scan(src, points: int, depth: str, max_value: int) -> SourceScan:
    """The SourceScan of ``src``: what pass one decided, and the format facts worth reporting."""
    facts = src.describe()
    extra = {"format": facts["format"], **{k: facts[k] for k in REPORTED_FACTS if k in facts}}
    return SourceScan(src.ordinal, src.path, points, depth, max_value, extra)


@dataclass(frozen=True)
class UnitScan:
    """The result of scanning one work unit; merged per source, then globally.

    ``max_value`` is the unit's largest integer channel value. A unit that saw
    only values <= 255 scanned itself as 8-bit; if another unit of the same
    file proves the file 16-bit, :func:`merge_units` moves its points to key 0.
    ``histogram`` is None when the unit was counted into a shared tally;
    ``decision`` is the unit's own color-depth decision (the file's, for a
    whole-file unit); ``final`` says no other unit can change it (a value
    above 255 seen, float colors, a fixed ``--color-depth``, or 8-bit channel
    types), so the unit's keys are final.
    """

    ordinal: int
    points: int
    max_value: int
    kind: str | None
    histogram: Histogram | None
    decision: str = "8"
    final: bool = False


def merge_units(scans: list[UnitScan], color_depth: str = "auto") -> tuple[Histogram, dict[int, str]]:
    """Global histogram of unit scans, with each source's color-depth decision applied."""
    is16 = {}
    kind = {}
    for s in scans:
        is16[s.ordinal] = is16.get(s.ordinal, False) or proves_16_bit(s.max_value, color_depth)
        kind[s.ordinal] = kind.get(s.ordinal) or s.kind
    parts = []
    for s in scans:
        h = s.histogram
        if waits_for_its_file(s.points, s.max_value, kind.get(s.ordinal), color_depth) and is16[s.ordinal]:
            h = key_zero(s.points)
        parts.append(h)
    total = Histogram.sum(parts)
    decisions = {o: ("float" if kind.get(o) == "float" else ("16" if is16[o] else "8")) for o in is16}
    return total, decisions


def proves_16_bit(max_value: int, color_depth: str) -> bool:
    """Whether a unit with this largest integer channel value decides its file 16-bit."""
    return max_value > 255 or color_depth == "16"


def waits_for_its_file(points: int, max_value: int, kind: str | None, color_depth: str) -> bool:
    """Whether a unit's counts depend on its file's color-depth decision: integer values all <= 255 under
    ``auto`` or ``8``, which are 8-bit colors, unless another unit of the file proves it 16-bit (then they
    are dark 16-bit values: every point of the unit goes to key 0). ``kind``: the file's ("int", "float"),
    which is the unit's own for a unit with points."""
    return bool(points) and kind != "float" and color_depth != "16" and max_value <= 255


def key_zero(points: int) -> Histogram:
    """A unit's histogram once its file is proved 16-bit and the unit saw no value above 255."""
    return Histogram(np.zeros(1, np.uint32), np.array([points], np.int64))


class RunningHistogram:
    """The run's histogram summed as units finish, each unit's counts once its file's color depth is decided
    (:func:`merge_units`' rule, applied unit by unit): an engine whose units' histograms live elsewhere
    (a Dask cluster's workers) holds a few of them at a time, whatever the number of units.

    ``submit(func, *args)`` runs ``func(*args)`` where the histograms live and returns a handle to the
    result (a future; any handle ``submit`` accepts as an argument); ``merge(*histograms)`` sums them
    (:meth:`Histogram.sum`). A unit's histogram is summed at once when :func:`waits_for_its_file` says its
    counts cannot change, else kept (and summed with its file's other waiting units) until its file ends or
    proves 16-bit, and then summed, or dropped for its point count at key 0. Sums are folded ``fan_in`` at a
    time, level by level (:class:`.Folding`).
    """

    def __init__(self, submit, merge, units_of: dict, color_depth: str, fan_in: int = 4):
        self.submit, self.merge, self.color_depth, self.fan_in = submit, merge, color_depth, fan_in
        self.left = dict(units_of)  # ordinal -> units of the file not done yet
        self.parts = self._folding()  # decided histograms
        self.waiting: dict = {}  # ordinal -> [its waiting units' histograms (a Folding), their points]
        self.sixteen: set = set()  # files proved 16-bit
        self.key_zero = 0  # points of waiting units whose file proved 16-bit

    def _folding(self) -> Folding:
        # a closure over submit and merge, not over self: self holds its Foldings, so a fold referring back
        # to self made a cycle, and the handles (a cluster's futures) lived on until Python's cycle collector
        # ran. Held futures are wanted: a worker lost in pass two had the scheduler run pass one's units
        # again, which left their spill folders in the output
        submit, merge = self.submit, self.merge
        return Folding(lambda *handles: submit(merge, *handles), self.fan_in)

    def unit_done(self, ordinal: int, points: int, max_value: int, kind: str | None, histogram) -> None:
        """A unit finished: its facts and a handle to its histogram (under its own keys)."""
        if waits_for_its_file(points, max_value, kind, self.color_depth):
            if ordinal in self.sixteen:
                self.key_zero += points
            else:
                held = self.waiting.setdefault(ordinal, [self._folding(), 0])
                held[0].add(histogram)
                held[1] += points
        else:
            self.parts.add(histogram)
            if proves_16_bit(max_value, self.color_depth) and ordinal not in self.sixteen:
                self.sixteen.add(ordinal)
                if ordinal in self.waiting:
                    self.key_zero += self.waiting.pop(ordinal)[1]
        self.left[ordinal] -= 1
        if not self.left[ordinal] and ordinal in self.waiting:  # the file ended and none proved it 16-bit: 8-bit
            for h in self.waiting.pop(ordinal)[0].held():
                self.parts.add(h)

    def held(self) -> int:
        """Histograms held (not yet folded into another)."""
        return len(self.parts) + sum(len(w[0]) for w in self.waiting.values())

    def total(self):
        """A handle to the run's histogram, once every unit is done."""
        left = {o: n for o, n in self.left.items() if n}
        if left or self.waiting:
            raise AssertionError(f"units of files {sorted(left)} are not done")
        extra = [key_zero(self.key_zero)] if self.key_zero else []
        if not len(self.parts) and not extra:
            return self.submit(self.merge)
        return self.parts.result(*extra)


class Tally:
    """Where pass one counts the keys of one unit."""

    def count(self, spec: BinSpec, r, g, b, shift: int) -> np.ndarray:
        """Count the chunk's keys; return them."""
        raise NotImplementedError

    def refile(self, n: int) -> None:
        """The first ``n`` points counted are key 0 after all (the file proved 16-bit late)."""
        raise NotImplementedError

    def histogram(self) -> Histogram | None:
        raise NotImplementedError


class DenseTally(Tally):
    """One unit's counts over the whole key space (128 MiB at 0 quantization bits)."""

    def __init__(self, spec: BinSpec):
        self.dense = sparse_zeros(spec.key_space, np.int64)
        self.marks = marks_for(spec.key_space)  # the blocks a key was counted in (the scans read these alone)

    def count(self, spec, r, g, b, shift):
        return spec.counted_keys(r, g, b, shift, self.dense, self.marks)

    def refile(self, n):
        for a, b in table_runs(self.marks, len(self.dense)):
            self.dense[a:b] = 0
        self.dense[0] = n
        mark(self.marks, [0])

    def histogram(self):
        return Histogram.from_dense(self.dense, runs=table_runs(self.marks, len(self.dense)))


class SparseTally(Tally):
    """One small unit's keys, collected and counted at the end (a cluster worker's unit)."""

    def __init__(self, spec: BinSpec):
        self.collected: list[np.ndarray] = []

    def count(self, spec, r, g, b, shift):
        keys = spec.keys(r, g, b, shift)
        self.collected.append(keys)
        return keys

    def refile(self, n):
        self.collected = [np.zeros(n, np.uint32)]

    def histogram(self):
        return Histogram.from_keys(np.concatenate(self.collected)) if self.collected else Histogram.empty()


def tally_for(unit_points: int, spec: BinSpec) -> Tally:
    """The tally that takes less memory for a unit of this many points."""
    return SparseTally(spec) if unit_points * 4 < spec.key_space * 8 else DenseTally(spec)
