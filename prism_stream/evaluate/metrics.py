"""The paper's measures of a sample: Chamfer and Hausdorff distance, color entropy gain.

Chamfer distance, as the paper's equation, between the input P and the
sample Q (mean nearest-neighbour distance both ways, summed; Euclidean,
not squared)::

    CD(P, Q) = 1/|P| sum_{p in P} min_{q in Q} ||p - q||
             + 1/|Q| sum_{q in Q} min_{p in P} ||p - q||

Hausdorff distance is the larger of the two one-sided suprema. Every method
evaluated here keeps actual input points, so Q is a subset of P and the
second term (and the second supremum) is zero. :func:`sample_distances`
uses that: a KD-tree on the sample, one streamed pass over the input. It
also checks the premise on the way (every sample point must be met at
distance zero) instead of trusting it.

Color entropy gain: the Shannon entropy, in bits, of the distribution of
points over color bins (the 8-bit RGB triples unless told otherwise) of
the output, minus that of the input. Positive: the sample spreads over
colors more evenly than the input does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow.parquet as pq
from scipy.spatial import cKDTree

from ..core.bins import decided_keys
from ..errors import NoColorError, PrismError, UsageError
from ..formats.conversion import as_unsigned
from ..formats.parquet import DEFAULT_RGB
from ..formats.pcd import unpack
from ..core.histogram import Histogram
from .cloud import RGB8, Cloud, arrow_coordinates
from ..formats.arrow import to_numpy


def entropy_bits(counts) -> float:
    """Shannon entropy (bits) of the distribution given by nonnegative counts."""
    c = np.asarray(counts, dtype=np.float64)
    c = c[c > 0]
    if c.size == 0:
        return 0.0
    p = c / c.sum()
    return float(-(p * np.log2(p)).sum())


def color_entropy_gain(input_histogram: Histogram, output_histogram: Histogram) -> float:
    """H(output bins) - H(input bins), in bits."""
    return entropy_bits(output_histogram.counts) - entropy_bits(input_histogram.counts)


def chamfer_distance(p: np.ndarray, q: np.ndarray) -> float:
    """The paper's Chamfer distance between two in-memory clouds, both directions computed."""
    p, q = _points(p), _points(q)
    if not len(p) or not len(q):
        raise UsageError("Chamfer distance needs two non-empty clouds")
    return float(cKDTree(q).query(p)[0].mean() + cKDTree(p).query(q)[0].mean())


def hausdorff_distance(p: np.ndarray, q: np.ndarray) -> float:
    """max(sup_p min_q ||p - q||, sup_q min_p ||p - q||) of two in-memory clouds."""
    p, q = _points(p), _points(q)
    if not len(p) or not len(q):
        raise UsageError("Hausdorff distance needs two non-empty clouds")
    return float(max(cKDTree(q).query(p)[0].max(), cKDTree(p).query(q)[0].max()))


def _points(a) -> np.ndarray:
    return np.asarray(a, dtype=np.float64).reshape(-1, 3)


@dataclass(frozen=True)
class Distances:
    """Chamfer and Hausdorff distance of a sample to its input (in the input's units)."""

    chamfer: float
    hausdorff: float
    input_points: int
    sample_points: int


class NotASubset(PrismError):
    """The sample holds a point the input does not: the one-pass formula does not apply."""


def sample_distances(cloud: Cloud, sample_xyz: np.ndarray, chunk_size: int | None = None,
                     subset: bool = True) -> Distances:
    """CD and HD of a sample that is a subset of ``cloud``: a KD-tree on the sample, one pass over the input.

    Memory: the sample's tree; the input streams in chunks. Raises
    :class:`NotASubset` if some sample point has no identical input point.
    ``subset=False`` (new points, e.g. voxel centroids) also measures the
    sample-to-input direction: each input chunk's tree is queried with the
    whole sample, keeping each sample point's smallest distance.
    """
    if not subset:
        return _two_sided(cloud, _points(sample_xyz), chunk_size)
    q = np.unique(_points(sample_xyz), axis=0)
    if not len(q):
        raise UsageError("the sample is empty; distances are undefined", cloud.files[0] if cloud.files else None)
    tree = cKDTree(q)
    met = np.zeros(len(q), dtype=bool)
    total = 0.0
    worst = 0.0
    n = 0
    for chunk in cloud.chunks(chunk_size):
        if not len(chunk):
            continue
        d, i = tree.query(chunk.xyz, workers=-1)
        total += float(d.sum())
        worst = max(worst, float(d.max()))
        met[i[d == 0.0]] = True
        n += len(d)
    if not met.all():
        raise NotASubset(f"{int((~met).sum())} sample points are not input points", cloud.files[0])
    return Distances(chamfer=total / n, hausdorff=worst, input_points=n, sample_points=len(_points(sample_xyz)))


def _two_sided(cloud: Cloud, q: np.ndarray, chunk_size: int | None) -> Distances:
    if not len(q):
        raise UsageError("the sample is empty; distances are undefined", cloud.files[0] if cloud.files else None)
    tree = cKDTree(q)
    back = np.full(len(q), np.inf)
    total, worst, n = 0.0, 0.0, 0
    for chunk in cloud.chunks(chunk_size):
        if not len(chunk):
            continue
        d, _ = tree.query(chunk.xyz, workers=-1)
        total += float(d.sum())
        worst = max(worst, float(d.max()))
        n += len(d)
        np.minimum(back, cKDTree(chunk.xyz).query(q, workers=-1)[0], out=back)
    return Distances(chamfer=total / n + float(back.mean()), hausdorff=max(worst, float(back.max())),
                     input_points=n, sample_points=len(q))


@dataclass
class Sample:
    """An output read back: its coordinates and its 8-bit RGB histogram."""

    path: str
    xyz: np.ndarray
    histogram: Histogram
    keys: np.ndarray | None = None  # each point's 8-bit RGB key (RGB8), in file order

    @property
    def points(self) -> int:
        return int(self.xyz.shape[0])


def read_sample(path: str, cloud: Cloud, batch_size: int = 1 << 20) -> Sample:
    """Read a Parquet output of ``cloud`` back: coordinates, and colors binned as the input's were.

    The colors are binned with the input's color-depth decision (a sample of
    a 16-bit file is 16-bit even if its values happen to stay under 256).
    """
    cloud.histogram()
    decisions = {cloud.decisions.get(s.ordinal, "8") for s in cloud.sources}
    if len(decisions) > 1:
        raise UsageError("the inputs mix color depths (" + ", ".join(sorted(decisions)) + "); evaluate them "
                         "one at a time", cloud.files[0])
    decision = decisions.pop() if decisions else "8"
    f = pq.ParquetFile(path)
    names = _color_names(f.schema_arrow, cloud, path)
    xyz, keys = [], []
    for batch in f.iter_batches(batch_size=batch_size):
        xyz.append(arrow_coordinates(batch, path))
        keys.append(decided_keys(RGB8, _channels(batch, names), decision, path))
    xyz = np.concatenate(xyz) if xyz else np.zeros((0, 3))
    keys = np.concatenate(keys) if keys else np.zeros(0, np.uint32)
    return Sample(path, xyz, Histogram.from_keys(keys), keys)


def _channels(batch, names) -> tuple:
    """The three color channels of a batch: three columns, or one packed 0x??RRGGBB word (PCD)."""
    cols = [as_unsigned(to_numpy(batch.column(batch.schema.get_field_index(n))))
            for n in names]
    return unpack(cols[0]) if len(cols) == 1 else tuple(cols)


def _color_names(schema, cloud: Cloud, path: str):
    """The sample's color columns: those its source read colors from, else the usual names."""
    src = cloud.sources[0]
    tried = [getattr(src, "color_fields", None), getattr(src, "rgb_names", None), cloud.rgb_columns, DEFAULT_RGB,
             ("diffuse_red", "diffuse_green", "diffuse_blue")]
    lower = {n.lower(): n for n in schema.names}
    for wanted in tried:
        if wanted and all(w.lower() in lower for w in wanted):
            return tuple(lower[w.lower()] for w in wanted)
    raise NoColorError("the sample has no color columns to bin", path)


PREVIEW = 150_000  # points kept for a top-down render


def preview(xyz: np.ndarray, keys: np.ndarray | None, limit: int = PREVIEW):
    """Up to ``limit`` evenly strided points of a sample and their 8-bit colors, for a render."""
    step = max(1, -(-len(xyz) // limit))
    rgb = np.column_stack(RGB8.channels(keys[::step])).astype(np.uint8) if keys is not None else None
    return xyz[::step], rgb


def input_preview(cloud: Cloud, limit: int = PREVIEW):
    """Up to ``limit`` evenly strided input points and their 8-bit colors, from one streamed pass."""
    step = max(1, -(-cloud.points // limit))
    xyz, keys = [], []
    for c in cloud.chunks():
        pick = np.arange((-c.offset) % step, len(c), step)
        xyz.append(c.xyz[pick])
        keys.append(cloud.keys_of(c.ordinal, tuple(np.asarray(ch)[pick] for ch in c.raw.rgb)))
    return preview(np.concatenate(xyz), np.concatenate(keys), limit) if xyz else (np.zeros((0, 3)), None)
