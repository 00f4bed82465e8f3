"""The spatial share of a local run (``--space A``, SPEC 9): one more read, then the merge with PRISM's order.

After the cutoffs, PRISM's sample for T is known. :func:`respace` reads the
input once more (held in memory: no read) for every point's place, rarity
and priority (:class:`..core.space.SpatialScan`; past :data:`BUDGET`, with
the points on disk: :class:`.spatial_disk.DiskScan`), ranks PRISM's sample
(:func:`prism_order`) and merges the two orders into the T ids the run
keeps; pass two then writes exactly those (:class:`IdSelector`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ..core import space
from ..core.kernels import ID_SHIFT, bin_seed_mix, priorities_of_np, seed_mix
from ..errors import CorruptInput, OutputError
from ..run import staging
from ..run.memory import release_memory
from ..run.progress import Progress
from . import spatial_disk, spatial_merge
from .ranking import Held
from .spatial_disk import DiskScan

BUDGET = space.MEMORY_BUDGET  # what the spatial scan may hold in memory (core/space.state_bytes); past it, on disk
RELEASE_EVERY = 1 << 20  # points of the spatial read between two hand-backs of freed memory to the OS
CAP = space.SPREAD * space.largest_target(BUDGET) + 1  # the cells a scan on disk tracks in memory, at most
PAST_CAP = 1 << 16  # and for a target past CAP (bench/RESULTS_SPACE.md, "A smaller top scan")


def disk_cap(target: int) -> int:
    """The cells a scan on disk tracks for ``target``: as many as the budget holds while its level may still
    have T cells (then its order is the whole order and nothing is routed), else few: the points are routed
    and sorted out below its level whatever it tracks, and a small scan costs less (and its folds, on Dask)."""
    return CAP if target <= CAP else min(CAP, PAST_CAP)


def check_coordinates(options, sources) -> None:
    """Refuse, before pass one, a spatial share over a source whose columns hold no coordinates."""
    if options.space is None:
        return
    from ..evaluate.cloud import check_coordinates as check

    check(sources)


class Rarity:
    """Each point's rarity (SPEC 9): the points of the whole input in its coarse color, the bin key with
    max(q, 4) bits dropped a channel (at most 4,096 coarse colors), from the plan's histogram."""

    def __init__(self, plan):
        bits = int(plan.options.quant_bits)
        self.w = 8 - bits
        self.drop = max(bits, 4) - bits
        self.coarse_w = self.w - self.drop
        table = np.zeros(1 << (3 * self.coarse_w), np.int64)
        step = 1 << 20  # a million bins at a time: no temporary over 2^24 bins
        for a in range(0, len(plan.keys), step):
            np.add.at(table, self.coarse(plan.keys[a:a + step]), plan.counts[a:a + step])
        self.table = table.astype(np.uint64)

    def coarse(self, keys: np.ndarray) -> np.ndarray:
        keys = keys.astype(np.int64)
        w, d, cw = self.w, self.drop, self.coarse_w
        mask = (1 << w) - 1
        return ((keys >> (2 * w)) >> d << (2 * cw)) | (((keys >> w) & mask) >> d << cw) | ((keys & mask) >> d)

    def of(self, keys: np.ndarray) -> np.ndarray:
        return self.table[self.coarse(keys)]


@dataclass
class Spaced:
    """The run's sample: its ids ascending (input order) and each one's place in SPEC 9's order (its rank),
    arrays or (a target past the scan's memory budget) temporary files of them."""

    ids: "np.ndarray | staging.ArrayFile"
    places: "np.ndarray | staging.ArrayFile"
    spatial: int  # how many places the spatial order filled
    on_disk: int = 0  # the points the spatial scan wrote to the temporary folder (0: its cells fit in memory)
    routed: int = 0  # the points it wrote again, routed by their cells (0: the order needed no level below)

    @property
    def count(self) -> int:
        return self.ids.size if isinstance(self.ids, staging.ArrayFile) else len(self.ids)

    def rank_values(self):
        """The places as pass two's ranks read them (``read(at, n)`` and ``size``): the file, or the array."""
        return self.places if isinstance(self.places, staging.ArrayFile) else Held(self.places)

    def facts(self, options) -> dict:
        return {"share": options.space, "spatial_points": self.spatial, "prism_points": self.count - self.spatial,
                "points_on_disk": self.on_disk, "points_routed": self.routed}


def prism_order(plan, kept) -> np.ndarray:
    """PRISM's sample for T (``kept()``: (bin keys, ids) pairs), its ids in rank order (SPEC 9, section 4's
    rule read as an order: by the place j of a point in its bin, then by its bin's priority among the sample's
    bins; :func:`..core.ranks.rank_sample` as an order). From the sample alone: no per-bin array of the plan;
    each temporary let go once used (a few words a point)."""
    keys, ids = [], []
    for k, i in kept():
        keys.append(k)
        ids.append(i)
    keys = np.concatenate(keys) if keys else np.zeros(0, np.uint32)
    ids = np.concatenate(ids) if ids else np.zeros(0, np.uint64)
    n = len(ids)
    if n == 0:
        return ids
    bins, inverse = np.unique(keys, return_inverse=True)
    del keys
    place_of = np.empty(len(bins), np.int64)  # each bin's place among the sample's bins by bin priority
    place_of[np.argsort(priorities_of_np(bins.astype(np.uint64), bin_seed_mix(plan.seed)))] = np.arange(len(bins))
    place = place_of[inverse.ravel()]
    del inverse
    by_bin = np.lexsort((priorities_of_np(np.ascontiguousarray(ids, np.uint64), seed_mix(plan.seed)), place))
    b = place[by_bin]  # the bins' places, each bin's points by priority
    del place
    starts = np.flatnonzero(np.r_[True, b[1:] != b[:-1]])
    layer = np.arange(n, dtype=np.int64) - np.repeat(starts, np.diff(np.append(starts, n)))  # j - 1
    if int(layer.max()) < (1 << 62) // len(bins):
        layer *= len(bins)
        layer += b
        del b
        by = by_bin[np.argsort(layer, kind="stable")]
    else:
        by = by_bin[np.lexsort((b, layer))]
    del layer, by_bin
    return ids[by]


def check_room(work: str, points: int, target: int) -> None:
    """Before the spatial read writes a point: refuse in one line, naming the temporary folder (``work``'s,
    the run's own folder in it), when it has no room for the scan on disk (a local run's forecast counted it
    before pass one; a query's size is known only now, and the free space may have changed since)."""
    _room(os.path.dirname(os.path.abspath(work)), work, space.disk_bytes(points, target), points)


def check_cluster_room(options, points: int, temp: str, output: str) -> None:
    """Before a Dask run's pass one: refuse in one line a spatial share past the memory budget whose files
    would not fit where they go: the points' and the scan's in the staging folder beside the output
    ``output``, the merges' in the driver's temporary folder ``temp`` (:func:`..core.space.cluster_disk_bytes`;
    on one disk, :func:`..core.space.disk_bytes`)."""
    t = None if options.space is None else options.target(points)
    if t is None or not space.on_disk(t) or not os.path.isdir(temp):  # (a missing folder: said as the run makes
        return  # its work folder there)
    beside = os.path.dirname(os.path.abspath(output))
    if same_disk(beside, temp):
        _room(temp, temp, space.disk_bytes(points, t), points, where="an output folder and --temp-dir")
        return
    staged, merged = space.cluster_disk_bytes(points, t)
    _room(beside, beside, staged, points, "space beside the output", "an output folder")
    _room(temp, temp, merged, points)


def same_disk(a: str, b: str) -> bool:
    return os.stat(a).st_dev == os.stat(b).st_dev


def _room(named: str, folder: str, need: int, points: int, what: str = "temporary space",
          where: str = "--temp-dir") -> None:
    free = staging.free_bytes(folder)
    if need > free - staging.RESERVE:
        raise OutputError(f"not enough {what}: the spatial share's scan of {points:,} points writes up "
                          f"to {staging.gib(need)} and {staging.gib(free)} is free (less "
                          f"{staging.gib(staging.RESERVE)} kept free); give {where} on a larger disk", named)


def check_finite(xyz: np.ndarray, path: str) -> None:
    if not np.all(np.isfinite(xyz)):
        raise CorruptInput("non-finite coordinates; --space needs every point placed", path)


def scan_chunk(scan: space.SpatialScan, path: str, xyz: np.ndarray, keys: np.ndarray, ids: np.ndarray,
               rarity_of: Rarity, mix) -> None:
    """One chunk of the spatial read into ``scan``: its coordinates, bin keys and ids (``mix``: the run's
    :func:`..core.kernels.seed_mix`). A scan on disk (:class:`.spatial_disk.DiskScan`) takes the keys and
    makes the rarities and priorities itself, with the run's own."""
    check_finite(xyz, path)
    if isinstance(scan, DiskScan):
        scan.add(xyz, keys, ids)
        return
    scan.add(xyz, rarity_of.of(keys), priorities_of_np(np.ascontiguousarray(ids, np.uint64), mix), ids)


def respace(plan, run, kept, points, total: int, rarity_of: Rarity) -> Spaced:
    """SPEC 9's sample: ``points()`` yields (path, xyz, bin keys, ids) chunks of every point (input order);
    ``rarity_of`` was made from the plan's histogram before it let its per-bin arrays go. A target whose
    cells would not fit in :data:`BUDGET` is scanned with the points on disk (:mod:`.spatial_disk`)."""
    mix = seed_mix(plan.seed)
    t = int(plan.target)
    on_disk = space.on_disk(t)
    if on_disk:
        check_room(run.tmp, int(plan.points), t)
    scan = DiskScan(t, run.tmp, rarity_of, mix, disk_cap(t)) if on_disk else space.SpatialScan(t)
    since = 0
    with Progress("spatial share", total, run.request.progress) as bar:
        for path, xyz, keys, ids in points():
            scan_chunk(scan, path, xyz, keys, ids, rarity_of, mix)
            bar.update(len(ids))
            since += len(ids)
            if since >= RELEASE_EVERY:  # the scan's merges free and allocate arrays of changing sizes, which
                release_memory()  # glibc keeps in its heap: at 100M points 819 MiB held against 405 (a few ms)
                since = 0
    if on_disk:  # a large target: its order's first T ids in the temporary folder, and the rest of the
        order = spatial_disk.ArrayFile(run.tmp, "space.order", np.uint64)  # step there too (spatial_merge)
        try:
            scan.order(plan.seed, t, order)
        except BaseException:
            order.discard()
            raise
    else:
        order = scan.order(plan.seed)[:t].copy()  # the merge takes at most T of it
    written, routed = (scan.written, scan.routed) if on_disk else (0, 0)
    del scan
    out = spaced(plan, order, kept)
    out.on_disk, out.routed = written, routed
    return out


def spaced(plan, spatial, kept) -> Spaced:
    """The run's sample from the spatial order (ids; its scan already let go) and PRISM's sample (``kept()``:
    (bin keys, ids) pairs). A spatial order in a temporary file (a large target's) is merged there, PRISM's
    order made beside it (:mod:`.spatial_merge`; the file is removed)."""
    t = int(plan.target)
    release_memory()  # the scan's buffers and the read's decoded batches, before pass two reads again
    if isinstance(spatial, staging.ArrayFile):
        folder = os.path.dirname(spatial.path)
        sizes = spatial_merge.Sizes(spatial_disk.SORT_RUN, spatial_disk.SORT_BLOCK)
        try:
            prism = spatial_merge.prism_order_file(plan.seed, kept, folder, sizes, spatial_disk.scan_file)
        except BaseException:
            spatial.discard()
            raise
        ids, places, filled = spatial_merge.merge_files(spatial, prism, plan.options.share, t, folder, sizes,
                                                        spatial_disk.scan_file)
        release_memory()  # the sorts' runs, before pass two
        return Spaced(ids, places, filled)
    prism = prism_order(plan, kept)
    release_memory()  # the order's temporaries, before the merge makes its own
    chosen, filled = space.merge(spatial, prism, plan.options.share, t)
    if len(chosen) != t:
        raise AssertionError(f"the spatial share chose {len(chosen)} points for a target of {t}")
    by = np.argsort(chosen, kind="stable")  # input order; by[i] is the place of the i-th kept point
    out = Spaced(chosen[by], by.astype(np.int64), filled)
    del chosen, by
    release_memory()  # the merge's temporaries, before pass two
    return out


class IdSelector:
    """Pass two's keep rule for a run whose kept ids are listed (ascending): of a whole run, or of the work
    units a cluster's task writes (a run with a spatial share reads its input again, never a spill). The ids
    are an array, or a temporary file of them, read a block at a time (the first id of every block held)."""

    BLOCK = 1 << 20  # ids of a file read at a time

    def __init__(self, ids):
        self.ids = ids
        self.file = ids if isinstance(ids, staging.ArrayFile) else None
        if self.file is not None:
            step = self.BLOCK
            self.firsts = np.array([int(self.file.read(a, 1)[0]) for a in range(0, self.file.size, step)],
                                   np.uint64)
            self.block_at, self.block = -1, np.zeros(0, np.uint64)

    def _block(self, k: int) -> np.ndarray:
        if k != self.block_at:
            a = k * self.BLOCK
            self.block_at, self.block = k, self.file.read(a, min(self.BLOCK, self.file.size - a))
        return self.block

    def _between(self, lo: int, hi: int) -> np.ndarray:
        """The listed ids in [lo, hi)."""
        if self.file is None:
            a, b = np.searchsorted(self.ids, [np.uint64(lo), np.uint64(hi)])
            return self.ids[a:b]
        k = max(int(np.searchsorted(self.firsts, np.uint64(lo), "right")) - 1, 0)
        parts = []
        while k < len(self.firsts) and int(self.firsts[k]) < hi:
            block = self._block(k)
            a, b = np.searchsorted(block, [np.uint64(lo), np.uint64(hi)])
            parts.append(block[a:b])
            k += 1
        return np.concatenate(parts) if len(parts) > 1 else (parts[0] if parts else np.zeros(0, np.uint64))

    def mask(self, keys: np.ndarray, ordinal: int, start: int) -> np.ndarray:
        first = (ordinal << ID_SHIFT) | start
        out = np.zeros(len(keys), bool)
        out[(self._between(first, first + len(keys)) - np.uint64(first)).astype(np.int64)] = True
        return out
