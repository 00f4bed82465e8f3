"""Pass one: the global color histogram.

``scan(unit, spec)`` is the pure per-unit step the DuckDB and Dask engines
map over work units; the local engine streams whole sources through a
:class:`HistogramAccumulator` and caches each point's bin key on the way.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .bins import BinSpec, ColorDepth


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
    def from_dense(dense: np.ndarray) -> "Histogram":
        keys = np.flatnonzero(dense).astype(np.uint32)
        return Histogram(keys, dense[keys].astype(np.int64))

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

    def merge(self, other: "Histogram") -> "Histogram":
        return Histogram.sum([self, other])

    def to_dense(self, key_space: int) -> np.ndarray:
        dense = np.zeros(key_space, dtype=np.int64)
        dense[self.keys] = self.counts
        return dense


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
    """

    ordinal: int
    points: int
    max_value: int
    kind: str | None
    histogram: Histogram


def scan(unit, spec: BinSpec, color_depth: str = "auto", chunk_size: int = 1 << 20) -> UnitScan:
    """Histogram of one work unit (a file range or a row group) on its own.

    It counts into a dense array over the key space (128 MiB at 0
    quantization bits) or, when the unit's keys take less room than that (a
    small unit on a cluster worker), collects them and counts them sparsely.
    """
    depth = ColorDepth(color_depth, unit.source.path)
    sparse = unit.points * 4 < spec.key_space * 8
    dense = None if sparse else np.zeros(spec.key_space, dtype=np.int64)
    collected = []
    points = 0
    for chunk in unit.color_chunks(chunk_size):
        r, g, b, shift = depth.prepare(*chunk.rgb)
        if depth.switched_at == points and points and shift == 8:
            # this chunk proved the file 16-bit: what was counted as 8-bit is key 0 now
            if sparse:
                collected = [np.zeros(points, np.uint32)]
            else:
                dense[:] = 0
                dense[0] = points
        keys = spec.keys(r, g, b, shift, counts=dense)
        if sparse:
            collected.append(keys)
        points += len(r)
    if sparse:
        histogram = Histogram.from_keys(np.concatenate(collected)) if collected else Histogram.empty()
    else:
        histogram = Histogram.from_dense(dense)
    return UnitScan(unit.source.ordinal, points, depth.max_value, depth.kind, histogram)


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


class HistogramAccumulator:
    """Dense histogram over the whole key space, for the local streaming engine."""

    def __init__(self, spec: BinSpec):
        self.spec = spec
        self.dense = np.zeros(spec.key_space, dtype=np.int64)

    def move_to_zero(self, keys: np.ndarray) -> None:
        """Re-file points already counted under ``keys`` into key 0 (a late 16-bit switch)."""
        np.subtract.at(self.dense, keys, 1)
        self.dense[0] += len(keys)

    def histogram(self) -> Histogram:
        return Histogram.from_dense(self.dense)
