"""The color histogram: what pass one counts, per unit, per source, and globally.

A :class:`Tally` is where pass one (:func:`.passes.scan`) counts one unit's
keys: densely over the key space, sparsely for a small unit, or (the local
engine's) into one shared histogram beside a key cache.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .bins import BinSpec
from .sparse import sparse_zeros


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
    def from_dense(dense: np.ndarray, block: int = 1 << 20) -> "Histogram":
        """The bins of a dense table of counts, ``block`` keys at a time: no int64 index as long as the
        bins (128 MB over 16M of them, beside the table itself). A boolean's nonzero: 4x faster than an integer
        array's."""
        keys = np.concatenate([np.flatnonzero(dense[a:a + block] != 0).astype(np.uint32) + np.uint32(a)
                               for a in range(0, len(dense), block)] or [np.zeros(0, np.uint32)])
        return Histogram(keys, dense[keys].astype(np.int64, copy=False))

    @staticmethod
    def from_keys(keys: np.ndarray) -> "Histogram":
        k, c = np.unique(np.asarray(keys, dtype=np.uint32), return_counts=True)
        return Histogram(k.astype(np.uint32), c.astype(np.int64))

    @staticmethod
    def sum(parts) -> "Histogram":
        """One histogram counting every part's points: one sort, however many parts."""
        parts = list(parts)
        if not parts:
            return Histogram.empty()
        keys = np.concatenate([p.keys for p in parts])
        counts = np.concatenate([p.counts for p in parts])
        if not len(keys):
            return Histogram.empty()
        order = np.argsort(keys, kind="stable")
        keys, counts = keys[order], counts[order]
        start = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        return Histogram(keys[start].astype(np.uint32), np.add.reduceat(counts, start).astype(np.int64))


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
        is16[s.ordinal] = is16.get(s.ordinal, False) or s.max_value > 255 or color_depth == "16"
        kind[s.ordinal] = kind.get(s.ordinal) or s.kind
    parts = []
    for s in scans:
        h = s.histogram
        if kind.get(s.ordinal) != "float" and is16[s.ordinal] and s.max_value <= 255 and color_depth != "16" and s.points:
            h = Histogram(np.zeros(1, np.uint32), np.array([s.points], np.int64))
        parts.append(h)
    total = Histogram.sum(parts)
    decisions = {o: ("float" if kind.get(o) == "float" else ("16" if is16[o] else "8")) for o in is16}
    return total, decisions


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

    def count(self, spec, r, g, b, shift):
        return spec.keys(r, g, b, shift, counts=self.dense)

    def refile(self, n):
        self.dense[:] = 0
        self.dense[0] = n

    def histogram(self):
        return Histogram.from_dense(self.dense)


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
