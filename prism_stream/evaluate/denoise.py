"""Statistical outlier removal, as the authors' script runs it before sampling.

The authors' released PRISM.py calls Open3D's
``remove_statistical_outlier(nb_neighbors=100, std_ratio=2.0)`` on every
cloud before PRISM. Open3D's rule, reproduced here point for point:

- d_i = the mean distance from point i to its ``k`` nearest neighbours, the
  point itself included (its distance 0 counts, so the mean is over k).
- mu = the sum of the positive d_i over N (all points, including those with
  d_i = 0); sigma = sqrt(sum over positive d_i of (d_i - mu)^2 / (N - 1)).
- keep i when 0 < d_i < mu + std_ratio * sigma. A point whose k neighbours
  all sit on it (d_i = 0: k or more duplicates) is removed.

:func:`sor_keep` does it in memory (the cloud's coordinates and one KD-tree,
about 60 bytes a point). :func:`sor_keep_streamed` does it out of core, with
the same result bit for bit: the cloud is cut into XY tiles spilled with an
overlap (:mod:`.tiles`); each tile's KD-tree gives its own points' k nearest
distances, which are exact when the k-th distance does not reach past the
tile's overlap (on a side where the cloud ends nothing lies beyond). The few
points whose k-th neighbour may lie further (isolated points: the outliers
themselves) are redone against every tile in turn, keeping their k best
distances, so every d_i is the exact one. mu and sigma come from the d_i on
disk (8 bytes a point), and the keep mask is a file of 1 byte a point.
``tests/test_evaluation_paper.py`` checks both against a reference written from
Open3D's definition and against each other; ``bench/sor_check.py`` against
Open3D itself.
"""

from __future__ import annotations

import math
import os

import numpy as np
from scipy.spatial import cKDTree

from ..core.denoise import Denoise  # noqa: F401 - evaluate.denoise.Denoise, as before
from ..errors import UsageError
from ..run.memory import release_memory


def mean_neighbour_distances(xyz: np.ndarray, k: int, block: int = 1 << 16) -> np.ndarray:
    """d_i: mean distance to the k nearest points, the point itself included (Open3D's SearchKNN)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    n = len(xyz)
    k = min(k, n)
    out = np.empty(n)
    if n == 0:
        return out
    tree = cKDTree(xyz)
    block = query_rows(k, block)
    for a in range(0, n, block):
        d, _ = tree.query(xyz[a:a + block], k=k, workers=-1)
        out[a:a + block] = np.asarray(d).reshape(len(d), -1).mean(axis=1)
    return out


def sor_keep(xyz: np.ndarray, neighbours: int = 100, std_ratio: float = 2.0) -> np.ndarray:
    """Boolean mask of the points Open3D's ``remove_statistical_outlier`` keeps."""
    d = mean_neighbour_distances(xyz, neighbours)
    n = len(d)
    if n == 0:
        return np.zeros(0, dtype=bool)
    pos = d > 0
    mu = d[pos].sum() / n
    sigma = math.sqrt(((d[pos] - mu) ** 2).sum() / (n - 1)) if n > 1 else 0.0
    return pos & (d < mu + std_ratio * sigma)


MAX_REDO = 1 << 18  # points redone against every tile at a time (k distances each in memory)
QUERY_BYTES = 64 << 20  # a neighbour query's distances and indices (16 bytes a neighbour) at most


def query_rows(k: int, most: int) -> int:
    """Points a neighbour query takes at a time: at most ``most``, and k distances and indices each within
    QUERY_BYTES (a large K would otherwise ask for K x 65,536 x 16 bytes at once)."""
    return max(1, min(most, QUERY_BYTES // (16 * max(k, 1))))


def sor_keep_streamed(cloud, folder: str, neighbours: int = 100, std_ratio: float = 2.0,
                      tile_points: int = 2_000_000, overlap: float = 0.05, room=None) -> tuple[np.ndarray, dict]:
    """:func:`sor_keep` out of core: the keep mask (a memory map in ``folder``, input order) and what it cost.

    Memory holds one tile with its overlap and its KD-tree; the coordinates go through
    temporary tile files (33 bytes a point and overlap copy). ``room(bytes)``, when given, is told the
    temporary bytes the tiles and the distances will take (:func:`temporary_bytes`) before any is written.
    """
    from .tiles import SPILL, Tiling, spill_tiles

    n = cloud.points
    if 0 < n < neighbours:
        raise UsageError(f"--denoise sor:{neighbours},{std_ratio:g}: K = {neighbours:,} neighbours is more than "
                         f"the cloud's {n:,} points", cloud.files[0])
    info = {"method": f"sor:{neighbours},{std_ratio:g}", "tiles": 0, "spilled_points": 0, "redone_points": 0,
            "in_memory": False}
    keep = allocated(os.path.join(folder, "sor-keep.u1"), np.bool_, max(n, 1))[:n]
    if n == 0:
        info.update(mu=None, sigma=None, removed=0)
        return keep, info
    lo, hi = cloud.bounds()
    tiling = Tiling.plan(lo, hi, n, tile_points, overlap)
    info["tiles"] = tiling.count
    if room is not None:
        room(temporary_bytes(n, tiling.shape, overlap))
    paths, info["spilled_points"] = spill_tiles(cloud, tiling, folder)
    release_memory()  # the decoded batches Arrow's and glibc's allocators keep: the tiles' trees take their place
    paths = [p for p in paths if os.path.exists(p)]
    d = allocated(os.path.join(folder, "sor-d.f8"), np.float64, n)
    redo_gid, redo_xyz = [], []
    for p in paths:
        tile = np.fromfile(p, dtype=SPILL)
        core = np.flatnonzero(tile["core"])
        if not len(core):
            continue
        k = min(neighbours, len(tile))
        xyz = tile["xyz"]
        tree = cKDTree(xyz)
        ij = tiling.cell(xyz[core[:1], :2])[0]  # the tile of its core points
        tlo = tiling.lo + ij * tiling.width - tiling.margin
        thi = tiling.lo + (ij + 1) * tiling.width + tiling.margin
        # a side where the cloud ends has nothing beyond it
        tlo = np.where(ij == 0, -np.inf, tlo)
        thi = np.where(ij == np.array(tiling.shape) - 1, np.inf, thi)
        step = query_rows(k, 1 << 16)
        for a in range(0, len(core), step):
            rows = core[a:a + step]
            dist, _ = tree.query(xyz[rows], k=k, workers=-1)
            dist = np.asarray(dist).reshape(len(rows), -1)
            pts = xyz[rows, :2]
            room = np.minimum(pts - tlo, thi - pts).min(axis=1)  # how far the tile's points surely reach
            exact = dist[:, -1] <= room if k == neighbours else np.full(len(rows), tiling.count == 1)
            gid = tile["gid"][rows]
            d[gid[exact]] = dist[exact].mean(axis=1)
            if not exact.all():
                redo_gid.append(gid[~exact])
                redo_xyz.append(xyz[rows[~exact]])
    if redo_gid:
        gids, pts = np.concatenate(redo_gid), np.concatenate(redo_xyz)
        info["redone_points"] = int(len(gids))
        step = query_rows(4 * min(neighbours, n), MAX_REDO)  # the best k so far, the query's and their merge
        for a in range(0, len(gids), step):
            d[gids[a:a + step]] = _nearest_everywhere(pts[a:a + step], paths, min(neighbours, n), SPILL)
    for p in paths:
        os.unlink(p)
    block = 1 << 22
    pos_sum = 0.0
    for a in range(0, n, block):
        part = d[a:a + block]
        pos_sum += float(part[part > 0].sum())
    mu = pos_sum / n
    sq = 0.0
    for a in range(0, n, block):
        part = d[a:a + block]
        sq += float(((part[part > 0] - mu) ** 2).sum())
    sigma = math.sqrt(sq / (n - 1)) if n > 1 else 0.0
    cut = mu + std_ratio * sigma
    kept = 0
    for a in range(0, n, block):
        part = d[a:a + block]
        mask = (part > 0) & (part < cut)
        keep[a:a + block] = mask
        kept += int(mask.sum())
    keep.flush()
    del d
    os.unlink(os.path.join(folder, "sor-d.f8"))
    info.update(mu=mu, sigma=sigma, removed=n - kept)
    return keep, info


def allocated(path: str, dtype, n: int) -> np.memmap:
    """A new file of ``n`` values mapped for writing, its blocks allocated first: a disk without room for it
    says so here (ENOSPC), not later as a SIGBUS from a page of a sparse file it cannot write."""
    size = int(np.dtype(dtype).itemsize) * n
    with open(path, "wb") as f:
        if size:
            os.posix_fallocate(f.fileno(), 0, size)
    return np.memmap(path, dtype=dtype, mode="r+", shape=(n,))


def temporary_bytes(points: int, shape: tuple, overlap: float = 0.05) -> int:
    """The temporary bytes of :func:`sor_keep_streamed` over ``points`` in a grid of ``shape`` tiles: each
    point in its tile file and in the overlap of its neighbours' (33 bytes a copy; evenly spread points make
    (1 + 2 overlap) copies along each axis cut into tiles), its distance (8 bytes) and its keep flag (1)."""
    from .tiles import SPILL

    copies = (1 + 2 * overlap if shape[0] > 1 else 1.0) * (1 + 2 * overlap if shape[1] > 1 else 1.0)
    return int(math.ceil(points * (SPILL.itemsize * copies + 9)))


def _nearest_everywhere(pts: np.ndarray, paths: list, k: int, dtype) -> np.ndarray:
    """Mean distance of each point to its k nearest among every tile's own (core) points."""
    best = np.full((len(pts), k), np.inf)
    for p in paths:
        tile = np.fromfile(p, dtype=dtype)
        own = tile["xyz"][tile["core"]]
        if not len(own):
            continue
        kk = min(k, len(own))
        dist, _ = cKDTree(own).query(pts, k=kk, workers=-1)
        merged = np.concatenate([best, np.asarray(dist).reshape(len(pts), -1)], axis=1)
        best = np.sort(merged, axis=1)[:, :k]
    return best.mean(axis=1)
