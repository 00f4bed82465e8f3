"""The paper's baselines, streamed like the sampler: Random, Voxel grid, Normal space sampling.

Each reads its inputs in chunks through :mod:`prism_stream.formats`, keeps
actual input points (every attribute unchanged, in input order) and writes
them through the same sinks as :func:`prism_stream.sample`, atomically.

- :func:`random_sample`: exactly T points, the T smallest SPEC priorities
  (the sampler's selection with every point in one bin). One bounded heap of
  T priorities, filled without reading the file (ids alone), then one pass.
- :func:`voxel_sample`: one point per occupied voxel, the input point nearest
  the voxel center; the voxel size is given or searched to land near a
  target count (several coordinate passes, see :func:`search_voxel_size`).
- :func:`nss_sample`: normal space sampling (Rusinkiewicz and Levoy 2001):
  normals from the k nearest neighbours, binned on the sphere, points drawn
  round-robin across normal bins up to T (the sampler's exact quota rule on
  normal bins). Normals are computed in spatial tiles with an overlap.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time
from dataclasses import asdict, dataclass, field, fields

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from scipy.spatial import cKDTree

from .. import __version__
from ..core.cutoffs import Rules, find_cutoffs
from ..errors import UsageError
from ..core.histogram import Histogram
from ..core.passes import select
from ..core.quotas import Options, solve
from ..core.selection import Selector
from ..formats import AtomicFile, open_sink
from ..run.outputs import check_output_file
from .cloud import RGB8, Chunk, Cloud
from .denoise import query_rows
from .tiles import SPILL, Tiling, spill_tiles

# Random and NSS reuse the sampler's quota, cutoff and selection steps. Their
# bins are not colors, so the plan's key space only has to hold them:
# 3 * (8 - bits) key bits, i.e. 8 keys at bits=7 and 4,096 at bits=4.
_ONE_BIN_BITS = 7
_NORMAL_BIN_BITS = 4
MAX_NORMAL_BINS = 1 << (3 * (8 - _NORMAL_BIN_BITS))


@dataclass
class BaselineResult:
    """What a baseline run did."""

    method: str
    inputs: list
    output: str
    points: int
    target: int
    kept: int
    ratio_achieved: float
    seed: int | None = None
    params: dict = field(default_factory=dict)
    seconds: float = 0.0
    version: str = __version__

    def as_dict(self) -> dict:
        return asdict(self)


def _open(inputs, **kw) -> tuple[Cloud, bool]:
    if isinstance(inputs, Cloud):
        return inputs, False
    return Cloud(inputs, **kw), True


def _target(points: int, ratio, count) -> int:
    t = Options(ratio=ratio, count=count).target(points)
    return int(t)


def write_selection(cloud: Cloud, output: str, keep, provenance: dict, overwrite: bool = False) -> int:
    """Stream ``cloud`` into ``output``, keeping the points ``keep(chunk)`` marks; atomic."""
    check_output_file(output, cloud.files, overwrite)
    with open_sink(output, cloud.sources, provenance) as sink:
        for chunk in cloud.chunks():
            sink.write(chunk.raw, np.asarray(keep(chunk), dtype=bool))
    return sink.written


def write_stratified(cloud: Cloud, output: str, plan, keys_of, provenance: dict, overwrite: bool = False) -> int:
    """The sampler's own selection (plan, cutoffs, pass two) over strata that are not colors.

    ``keys_of(source, start, n)`` gives the stratum key of records [start, start + n)
    of a source (one bin for Random, a normal bin for NSS).
    """
    check_output_file(output, cloud.files, overwrite)
    rules = Rules(plan)
    selector = Selector(plan, find_cutoffs(rules, cloud.sources, cloud.chunk_size, keys_of), rules)
    with open_sink(output, cloud.sources, provenance) as sink:
        for src in cloud.sources:
            for chunk, mask in select(src.whole(), plan, selector=selector, chunk_size=cloud.chunk_size,
                                      keys_of=lambda a, n, src=src: keys_of(src, a, n)):
                sink.write(chunk, mask)
    return sink.written


def _provenance(cloud: Cloud, method: str, params: dict) -> dict:
    return {"software": f"prism-stream {__version__}", "method": method, "params": params,
            "inputs": [os.path.abspath(f) for f in cloud.files]}


def _result(method, cloud, output, counts: tuple, seed, params, t0) -> BaselineResult:
    """``counts``: (the target, the points kept)."""
    target, kept = counts
    n = cloud.points
    return BaselineResult(method, [os.path.abspath(f) for f in cloud.files], os.path.abspath(output), n, target,
                          int(kept), kept / n if n else 0.0, seed, params, round(time.perf_counter() - t0, 4))


# ---------------------------------------------------------------- Random

def random_sample(inputs, output: str, *, ratio: float | None = None, count: int | None = None, seed: int = 0,
                  overwrite: bool = False, **open_kw) -> BaselineResult:
    """Exactly T points: those with the T smallest priorities ``splitmix64(id ^ splitmix64(seed))``.

    The same priorities as the sampler's (SPEC 3), so Random is PRISM with a
    single bin: deterministic for a seed, independent of chunking.
    """
    t0 = time.perf_counter()
    cloud, owned = _open(inputs, **open_kw)
    try:
        n = cloud.points
        target = _target(n, ratio, count)
        provenance = _provenance(cloud, "random", {"target": target, "seed": int(seed)})
        if target == 0:
            kept = write_selection(cloud, output, lambda c: np.zeros(len(c), bool), provenance, overwrite)
            return _result("random", cloud, output, (target, kept), int(seed), {}, t0)
        plan = solve(Histogram(np.zeros(1, np.uint32), np.array([n], np.int64)),
                     Options(count=target, quant_bits=_ONE_BIN_BITS, seed=int(seed)))
        # one bin, key 0: ids only, no colors are read to find the cutoff
        kept = write_stratified(cloud, output, plan, lambda _, a, n: np.zeros(n, np.uint32), provenance, overwrite)
        return _result("random", cloud, output, (target, kept), int(seed), {}, t0)
    finally:
        if owned:
            cloud.close()


# ---------------------------------------------------------------- Voxel grid

class VoxelGrid:
    """A regular grid of cubic voxels of side ``size`` anchored at the cloud's minimum corner."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, size: float):
        if not (size > 0 and math.isfinite(size)):
            raise UsageError(f"--voxel-size must be a positive number, not {size}")
        self.lo = np.asarray(lo, np.float64)
        self.size = float(size)
        self.dims = (np.floor((np.asarray(hi) - self.lo) / self.size).astype(np.int64) + 1)
        if float(np.prod(self.dims.astype(np.float64))) >= 2.0 ** 62:
            raise UsageError(f"voxel size {size:g} is too small for the cloud's extent (more than 2^62 voxels)")

    def index(self, xyz: np.ndarray) -> np.ndarray:
        """Packed voxel index (int64) of each point."""
        ijk = np.floor((xyz - self.lo) / self.size).astype(np.int64)
        np.clip(ijk, 0, self.dims - 1, out=ijk)
        return (ijk[:, 0] * self.dims[1] + ijk[:, 1]) * self.dims[2] + ijk[:, 2]

    def center_distance2(self, xyz: np.ndarray, index: np.ndarray) -> np.ndarray:
        k = index % self.dims[2]
        j = (index // self.dims[2]) % self.dims[1]
        i = index // (self.dims[2] * self.dims[1])
        with np.errstate(over="ignore"):  # a voxel far larger than the cloud: every distance inf, ties by id
            centers = self.lo + (np.column_stack([i, j, k]).astype(np.float64) + 0.5) * self.size
            return ((xyz - centers) ** 2).sum(axis=1)


def _nearest_per_voxel(index, d2, gid):
    """For each voxel, the (d2, gid)-smallest entry: ties in distance go to the smaller id."""
    order = np.lexsort((gid, d2, index))
    index, d2, gid = index[order], d2[order], gid[order]
    first = np.ones(len(index), dtype=bool)
    first[1:] = index[1:] != index[:-1]
    return index[first], d2[first], gid[first]


def voxel_representatives(cloud: Cloud, grid: VoxelGrid) -> np.ndarray:
    """Sorted cloud-wide indices of the point nearest each occupied voxel's center (one pass).

    Memory: three words per occupied voxel, i.e. per output point.
    """
    best = (np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64))
    for c in cloud.chunks():
        idx = grid.index(c.xyz)
        local = _nearest_per_voxel(idx, grid.center_distance2(c.xyz, idx),
                                   c.offset + np.arange(len(c), dtype=np.int64))
        best = _nearest_per_voxel(*(np.concatenate([a, b]) for a, b in zip(best, local)))
    return np.sort(best[2])


def occupied_voxels(cloud: Cloud, sizes, cap: int, nested: bool = False) -> list[int | None]:
    """Occupied-voxel count at each size, in one coordinate pass; None where it exceeds ``cap``.

    ``nested``: the sizes descend by halving from one origin, so each grid
    refines the one before and cannot hold fewer voxels; once a size passes
    the cap, the smaller ones are dropped unseen. Memory: the occupied voxel
    set of each size still under the cap.
    """
    lo, hi = cloud.bounds()
    grids = [VoxelGrid(lo, hi, s) for s in sizes]
    sets: list[np.ndarray | None] = [np.zeros(0, np.int64) for _ in sizes]
    for c in cloud.chunks():
        for i, g in enumerate(grids):
            if sets[i] is None:
                continue
            merged = np.union1d(sets[i], g.index(c.xyz))
            sets[i] = merged if len(merged) <= cap else None
            if sets[i] is None and nested:
                sets[i + 1:] = [None] * (len(sets) - i - 1)
                break
    return [None if s is None else len(s) for s in sets]


def search_voxel_size(cloud: Cloud, target: int, tolerance: float = 0.01, max_passes: int = 4,
                      ladder: int = 16) -> tuple[float, int, int]:
    """A voxel size whose occupied-voxel count is near ``target``: (size, count, coordinate passes).

    Pass one tries sizes halving from the cloud's extent; each further pass
    tries ``ladder`` sizes between the closest pair that brackets the target,
    until the count is within ``tolerance`` of it (relative) or the passes run
    out. The count is not monotone in the size, so this finds a near size,
    not the nearest. Each pass reads the coordinates once.
    """
    lo, hi = cloud.bounds()
    extent = float(np.max(hi - lo))
    if extent == 0.0 or target <= 1:
        size = max(extent, 1.0) * 2.0
        return size, 1, 0
    cap = max(2 * target, target + 1024)
    sizes = [extent * 2.0 ** -i for i in range(0, 40)]
    sizes = [s for s in sizes if np.prod(np.floor((hi - lo) / s) + 1) < 2.0 ** 62]
    trials: list[tuple[float, int | None]] = []
    passes = 0
    for _ in range(max_passes):
        passes += 1
        trials += list(zip(sizes, occupied_voxels(cloud, sizes, cap, nested=passes == 1)))
        known = [(s, n) for s, n in trials if n is not None]
        best = min(known, key=lambda t: (abs(t[1] - target), -t[0])) if known else (sizes[0], None)
        if best[1] is not None and abs(best[1] - target) <= tolerance * target:
            break
        small = [s for s, n in trials if n is None or n > target]
        large = [s for s, n in trials if n is not None and n <= target]
        if not small or not large:
            break
        s_lo = max(small)
        above = [s for s in large if s > s_lo]
        if not above:
            break
        s_hi = min(above)
        if s_hi / s_lo < 1 + 1e-9:
            break
        sizes = list(s_lo * (s_hi / s_lo) ** (np.arange(1, ladder + 1) / (ladder + 1)))
    known = [(s, n) for s, n in trials if n is not None]
    if not known:
        raise UsageError(f"no voxel size gives at most {cap} voxels", cloud.files[0])
    size, n = min(known, key=lambda t: (abs(t[1] - target), -t[0]))
    return float(size), int(n), passes


@dataclass(frozen=True)
class VoxelOptions:
    """The voxel grid's size, or the target a size is searched for (within ``tolerance``, in ``max_passes``)."""

    voxel_size: float | None = None
    ratio: float | None = None
    count: int | None = None
    tolerance: float = 0.01
    max_passes: int = 4


@dataclass(frozen=True)
class NssOptions:
    """Normal space sampling: the target (or a cap ``per_bin`` on every normal bin), the seed, and how normals
    are estimated (``k`` neighbours, ``bands`` x ``sectors`` bins, in XY tiles of ``tile_points``)."""

    ratio: float | None = None
    count: int | None = None
    seed: int = 0
    per_bin: int | None = None
    k: int = 10
    bands: int = 8
    sectors: int = 16
    tile_points: int = 2_000_000
    overlap: float = 0.05


def _split(options: dict, cls) -> tuple:
    """(an instance of the options dataclass ``cls`` from ``options``, the rest: how the inputs are read)."""
    names = {f.name for f in fields(cls)}
    return cls(**{k: v for k, v in options.items() if k in names}), {k: v for k, v in options.items()
                                                                       if k not in names}


def voxel_sample(inputs, output: str, *, overwrite: bool = False, **options) -> BaselineResult:
    """One input point per occupied voxel, the one nearest the voxel center (ties: smaller id).

    ``options``: :class:`VoxelOptions` fields, and how the inputs are read. Give ``voxel_size``, or a
    ``ratio``/``count`` to search a size whose output lands near it; the result reports the ratio reached.
    """
    grid_options, open_kw = _split(options, VoxelOptions)
    voxel_size, ratio, count = grid_options.voxel_size, grid_options.ratio, grid_options.count
    tolerance, max_passes = grid_options.tolerance, grid_options.max_passes
    t0 = time.perf_counter()
    cloud, owned = _open(inputs, **open_kw)
    try:
        lo, hi = cloud.bounds()
        params: dict = {}
        target = None
        if voxel_size is None:
            if ratio is None and count is None:
                raise UsageError("give --voxel-size, or a --ratio/--count to search it")
            target = _target(cloud.points, ratio, count)
            voxel_size, _, passes = search_voxel_size(cloud, target, tolerance, max_passes)
            params.update(search_target=target, search_passes=passes)
        elif ratio is not None or count is not None:
            raise UsageError("give either --voxel-size or a target, not both")
        grid = VoxelGrid(lo, hi, voxel_size)
        keep_ids = voxel_representatives(cloud, grid)
        params["voxel_size"] = float(voxel_size)

        def keep(c: Chunk):
            ids = c.offset + np.arange(len(c), dtype=np.int64)
            pos = np.searchsorted(keep_ids, ids)
            pos[pos == len(keep_ids)] = 0
            return keep_ids[pos] == ids if len(keep_ids) else np.zeros(len(c), bool)

        kept = write_selection(cloud, output, keep, _provenance(cloud, "voxel grid", params), overwrite)
        return _result("voxel", cloud, output, (target if target is not None else kept, kept), None, params, t0)
    finally:
        if owned:
            cloud.close()


@dataclass
class CentroidSample:
    """A centroid voxel grid's output: one new point per occupied voxel (not input points)."""

    result: BaselineResult
    xyz: np.ndarray  # (m, 3) float64, voxel centroids
    rgb: np.ndarray  # (m, 3) uint8, the mean 8-bit color of each voxel's points, rounded


def _sum_per_voxel(index, sums):
    """Collapse rows sharing a voxel index: (unique indices, summed rows)."""
    order = np.argsort(index, kind="stable")
    index, sums = index[order], sums[order]
    first = np.ones(len(index), dtype=bool)
    first[1:] = index[1:] != index[:-1]
    starts = np.flatnonzero(first)
    return index[starts], np.add.reduceat(sums, starts, axis=0) if len(starts) else sums[:0]


def voxel_centroid_sample(inputs, output: str | None = None, *, voxel_size: float, overwrite: bool = False,
                          **open_kw) -> CentroidSample:
    """The classic voxel grid filter (PCL's VoxelGrid, Open3D's voxel_down_sample): each occupied
    voxel becomes the centroid of its points, with their mean color.

    Voxels are anchored at the cloud's minimum corner. Colors are averaged on
    the 8-bit values (the sampler's color-depth decision applied) and rounded
    half up. One streamed pass after the bounds; memory: seven words per
    occupied voxel. ``output`` (optional) gets x, y, z, red, green, blue as
    Parquet. These are new points, so distances to them are computed both ways.
    """
    t0 = time.perf_counter()
    cloud, owned = _open(inputs, **open_kw)
    try:
        lo, hi = cloud.bounds()
        grid = VoxelGrid(lo, hi, voxel_size)
        index = np.zeros(0, np.int64)
        sums = np.zeros((0, 7))
        for c in cloud.chunks():
            r, g, b = (x.astype(np.float64) for x in _rgb8(cloud, c))
            rows = np.column_stack([c.xyz, r, g, b, np.ones(len(c))])
            index, sums = _sum_per_voxel(np.concatenate([index, grid.index(c.xyz)]), np.concatenate([sums, rows]))
        n = sums[:, 6:7]
        xyz = sums[:, :3] / n if len(n) else np.zeros((0, 3))
        rgb = np.floor(sums[:, 3:6] / n + 0.5).astype(np.uint8) if len(n) else np.zeros((0, 3), np.uint8)
        params = {"voxel_size": float(voxel_size), "representative": "centroid, mean color"}
        if output is not None:
            _write_centroids(output, xyz, rgb, cloud, params, overwrite)
        res = _result("voxel", cloud, output or "", (len(xyz), len(xyz)), None, params, t0)
        return CentroidSample(res, xyz, rgb)
    finally:
        if owned:
            cloud.close()


def _rgb8(cloud: Cloud, c: Chunk):
    return RGB8.channels(cloud.keys_of(c.ordinal, c.raw.rgb))


def _write_centroids(output, xyz, rgb, cloud, params, overwrite):
    check_output_file(output, cloud.files, overwrite)
    table = pa.table({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "red": rgb[:, 0], "green": rgb[:, 1],
                      "blue": rgb[:, 2]})
    table = table.replace_schema_metadata({"prism_stream": json.dumps(_provenance(cloud, "voxel centroid", params))})
    f = AtomicFile(output)
    try:
        pq.write_table(table, f.tmp)
        f.commit()
    except BaseException:
        f.discard()
        raise


# ---------------------------------------------------------------- Normal space sampling

def pca_normals(neighbours: np.ndarray) -> np.ndarray:
    """Unit normals from (m, k, 3) neighbourhoods: the eigenvector of the smallest covariance eigenvalue."""
    centered = neighbours - neighbours.mean(axis=1, keepdims=True)
    cov = np.einsum("mki,mkj->mij", centered, centered)
    _, vectors = np.linalg.eigh(cov)
    return vectors[:, :, 0]


def normal_bins(normals: np.ndarray, bands: int, sectors: int) -> np.ndarray:
    """Bin of each normal on the sphere, sign-free (n and -n share a bin).

    Normals are flipped into the upper hemisphere; bands split n_z evenly
    (equal areas, Archimedes) and sectors split the azimuth, so all
    ``bands * sectors`` bins cover the same solid angle.
    """
    n = np.asarray(normals, np.float64)
    flip = (n[:, 2] < 0) | ((n[:, 2] == 0) & ((n[:, 1] < 0) | ((n[:, 1] == 0) & (n[:, 0] < 0))))
    n = np.where(flip[:, None], -n, n)
    band = np.minimum((n[:, 2] * bands).astype(np.int64), bands - 1)
    phi = np.arctan2(n[:, 1], n[:, 0])
    sector = np.minimum(((phi + np.pi) / (2 * np.pi) * sectors).astype(np.int64), sectors - 1)
    return (band * sectors + sector).astype(np.uint32)


_TIE_SPARE = 6


NSS_K = 10  # neighbours per normal estimate, by default


def refuse_nss_k(k: int, n: int, path: str) -> None:
    """--nss-k above the cloud's points (and above the default, which a tiny cloud takes as all its points):
    every point's neighbours would be every point, N^2 distances (a usage error, as ``--denoise sor:K``'s)."""
    if 0 < n < k and k > NSS_K:
        raise UsageError(f"--nss-k {k:,} neighbours is more than the cloud's {n:,} points", path)


def estimate_normal_bins(cloud: Cloud, folder: str, *, k: int = NSS_K, bands: int = 8, sectors: int = 16,
                         tile_points: int = 2_000_000, overlap: float = 0.05) -> tuple[np.memmap | None, dict]:
    """Every point's normal bin, in input order, in a file in ``folder`` (uint16, 2 bytes a point).

    One pass spills each point (33 bytes) to the tile files it belongs to,
    core or overlap; then each tile is loaded alone, its KD-tree built and
    the normals of its core points computed from their k nearest neighbours
    within the tile and its overlap.
    """
    if bands * sectors > MAX_NORMAL_BINS or bands < 1 or sectors < 1:
        raise UsageError(f"normal bins must number 1..{MAX_NORMAL_BINS}, not {bands} x {sectors}")
    if k < 3:
        raise UsageError(f"normals need k >= 3 neighbours, not {k}")
    n = cloud.points
    refuse_nss_k(k, n, cloud.files[0])
    lo, hi = cloud.bounds()
    tiling = Tiling.plan(lo, hi, n, tile_points, overlap)
    info = {"k": k, "normal_bins": bands * sectors, "bands": bands, "sectors": sectors, "tiles": tiling.count,
            "overlap": overlap, "spilled_points": 0}
    if n == 0:
        return None, info
    paths, info["spilled_points"] = spill_tiles(cloud, tiling, folder)
    cache = np.memmap(os.path.join(folder, "normal-bins.u16"), dtype=np.uint16, mode="w+", shape=(n,))
    block = 1 << 17
    for p in paths:
        if not os.path.exists(p):
            continue
        tile = np.fromfile(p, dtype=SPILL)
        os.unlink(p)
        core = np.flatnonzero(tile["core"])
        kk = min(k, len(tile))
        if kk < 3:
            cache[tile["gid"][core]] = 0
            continue
        tree = cKDTree(tile["xyz"])
        # equidistant neighbours (quantized or duplicate coordinates) are common: a few spare
        # neighbours, ordered by (distance, id), keep the k chosen independent of tile and order
        spare = min(kk + _TIE_SPARE, len(tile))
        step = query_rows(spare, block)  # a large k: the distances of as many rows as 64 MiB hold, not k x 2^17
        for a in range(0, len(core), step):
            rows = core[a:a + step]
            d, nn = tree.query(tile["xyz"][rows], k=spare, workers=-1)
            order = np.lexsort((tile["gid"][nn], d), axis=-1)[:, :kk]
            nn = np.take_along_axis(nn, order, axis=1)
            cache[tile["gid"][rows]] = normal_bins(pca_normals(tile["xyz"][nn]), bands, sectors)
    cache.flush()
    return cache, info


def nss_sample(inputs, output: str, *, temp_dir: str | None = None, overwrite: bool = False,
               **options) -> BaselineResult:
    """Normal space sampling: exactly T points spread round-robin over normal bins.

    ``options``: :class:`NssOptions` fields, and how the inputs are read.
    Round-robin is the sampler's exact rule on normal bins: every bin gives K
    points (all it has if fewer), and E more bins, in seeded bin order, give
    one more; inside a bin, points are taken in seeded priority order.
    ``per_bin`` instead caps every normal bin at that many points (NSS at its
    own size, as the paper ran it), whatever the total.
    """
    nss, open_kw = _split(options, NssOptions)
    ratio, count, seed, per_bin = nss.ratio, nss.count, nss.seed, nss.per_bin
    k, bands, sectors, tile_points, overlap = nss.k, nss.bands, nss.sectors, nss.tile_points, nss.overlap
    t0 = time.perf_counter()
    cloud, owned = _open(inputs, **open_kw)
    try:
        n = cloud.points
        if per_bin is not None:
            if ratio is not None or count is not None:
                raise UsageError("give NSS either a per-bin cap or a target, not both")
            if int(per_bin) < 1:
                raise UsageError(f"--nss-per-bin must be at least 1, not {per_bin}")
            target = None
        else:
            target = _target(n, ratio, count)
        with tempfile.TemporaryDirectory(prefix="prism-stream-nss-", dir=temp_dir) as tmp:
            cache, params = estimate_normal_bins(cloud, tmp, k=k, bands=bands, sectors=sectors,
                                                 tile_points=tile_points, overlap=overlap)
            counts = np.bincount(np.asarray(cache), minlength=bands * sectors) if n else np.zeros(0, np.int64)
            keys = np.flatnonzero(counts).astype(np.uint32)
            hist = Histogram(keys, counts[keys].astype(np.int64))
            if target == 0:
                kept = write_selection(cloud, output, lambda c: np.zeros(len(c), bool),
                                       _provenance(cloud, "normal space sampling", params), overwrite)
                return _result("nss", cloud, output, (target, kept), int(seed), params, t0)
            quota = Options(k=int(per_bin)) if per_bin is not None else Options(count=target)
            plan = solve(hist, Options(count=quota.count, k=quota.k, quant_bits=_NORMAL_BIN_BITS, seed=int(seed)))
            params.update(k_rounds=plan.k, extra=plan.extra, occupied_normal_bins=plan.bins)
            if per_bin is not None:
                params["per_bin"] = int(per_bin)

            def normal_keys(src, a, n):
                base = int(cloud.offsets[src.ordinal]) + a
                return np.asarray(cache[base:base + n], dtype=np.uint32)

            kept = write_stratified(cloud, output, plan, normal_keys,
                                    _provenance(cloud, "normal space sampling", params), overwrite)
            del cache
        return _result("nss", cloud, output, (target if target is not None else kept, kept), int(seed), params, t0)
    finally:
        if owned:
            cloud.close()
