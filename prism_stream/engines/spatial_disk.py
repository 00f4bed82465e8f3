"""The spatial share's scan when its cells do not fit in memory (``--space A`` with a large target, SPEC 9).

The in-memory scan (:class:`..core.space.SpatialScan`) holds up to ``2 T + 1`` cells, so that the level it
tracks is never coarser than SPEC 9's last level. With a large T that is more than a run may hold.
:class:`DiskScan` tracks at most ``cap`` cells instead and writes every point (its coordinates, bin key and
id: :data:`RECORD`) to a file beside it. When the level it ends on already has T occupied cells, that is
the whole order, as in memory. Otherwise SPEC 9's last level lies below it, and the points are sorted out
by their cells there:

- the points are routed to a few files by a hash of their cell at that level, so that every cell (and so
  every smaller cell in it) lies in one file;
- a file of at most ``leaf`` points is loaded whole and its points sorted by Morton code: every level's
  occupied cells below the parent's level follow from that one sort (:func:`..core.space.occupied_counts`);
- a larger one is routed again by another hash of the same cells; where that leaves most of its points
  in one file (a few cells hold them), that file is scanned on its own instead (the in-memory scan again,
  at most ``cap`` cells, never below the input's last possible level): its cells' winners give the levels
  between its level and the parent's, and its points are routed again by their cells at its level.

The occupied cells of every level, summed over the files, give SPEC 9's last level; a second visit of the
small files lists the points born at or above it (each file's share, :func:`..core.space.births_below`),
beside those the large files' cells and the top scan listed. The order is the same as the in-memory scan's,
bit for bit, for any cap, file size and fan-out (tests/test_space_disk.py).

Disk: the points' file (36 bytes a point) and, while it is routed, its copy, the births the files scanned on
their own write (at most one a point) and a byte a point of the small files' order (the order's sorted
runs come once the routing is done, beside the small files, the births and the order: 36 + 32 + 1 + 32
bytes a point at most): :func:`..core.space.
disk_bytes` bounds it; the run's forecast counts it before pass one (a file's), and the spatial read checks
the room again before it writes (a query's size is known only after pass one).
Memory: the scan's cells (``cap``), or one file's scan of its own (the same bound; nothing of it is held
while its files are visited), one small file's sort (about 200 bytes a point of ``leaf``), the top scan's
births (40 bytes a cell of ``cap``), a run of the points born at or above the last level (there are fewer
than 2 T: they are sorted :data:`SORT_RUN` at a time into runs on disk and merged, :mod:`..run.extsort`);
the order's first T ids go to a file.
"""

from __future__ import annotations

import math
import os
import shutil
import time
import uuid
from dataclasses import dataclass

import numpy as np

from ..core import space
from ..core.kernels import priorities_of_np, seed_mix, splitmix64_np
from ..run.memory import release_memory
from ..run.progress import say
from ..run import extsort
from ..run.extsort import SortedRuns
from ..run.staging import ArrayFile, discard_file, unmark, unmark_under

RECORD = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("key", "<u4"), ("id", "<u8")])  # 36 bytes
BIRTH = np.dtype([("level", "<i8"), ("mass", "<i8"), ("cell_prio", "<u8"), ("id", "<u8")])
SORTED = np.dtype([("first", "<u8"), ("cell_prio", "<u8"), ("prio", "<u8"), ("id", "<u8")])  # a listed birth
SORT_KEYS = ("first", "cell_prio", "prio")  # (level descending, count descending) as one word, then the rest
SORT_RUN = 1 << 21  # listed births sorted in memory at a time (64 MiB); past it, in runs on disk, merged
SORT_BLOCK = 1 << 16  # listed births read from each run at a time while merging
LEAF = 1 << 20  # the most points a file is loaded and sorted whole with
FAN = 256  # the most files one file's points are routed to
SPREAD_SHARE = 0.75  # a file routed again by another hash that keeps more of its points in one: a few cells
READ = 1 << 20  # records read at a time
assert RECORD.itemsize == space.POINT_BYTES  # what the forecast counts
assert BIRTH.itemsize == SORTED.itemsize == space.BIRTH_BYTES
assert extsort.FAN_IN * SORT_RUN == space.MERGED_AT_ONCE  # what the forecast counts


@dataclass(frozen=True)
class Frame:
    """What the points of a scan on disk are sorted out by once its top scan is walked (the same for every
    part of the work, on any machine): the target, seed, cap, file size and fan-out, the last possible
    level, the top level and the level the top scan tracked."""

    target: int
    seed: int
    cap: int
    leaf: int
    fan: int
    floor: int
    top: int
    tracked: int


class DiskScan:
    """A spatial scan that tracks at most ``cap`` cells and keeps every point in a file of ``folder`` (see the
    module). ``rarity_of``: the run's :class:`..spatial.Rarity`; ``mix``: its :func:`..core.kernels.seed_mix`."""

    def __init__(self, target: int, folder: str, rarity_of, mix, cap: int, leaf: int | None = None,
                 fan: int | None = None):
        self._setup(target, folder, rarity_of, mix, cap, leaf, fan)
        self.points = ArrayFile(folder, "space.points", RECORD)

    @classmethod
    def part(cls, target: int, path: str, rarity_of, mix, cap: int) -> "DiskScan":
        """The scan of a part of an input (a Dask engine's group of units, on a worker): its points go to
        ``path`` (:func:`write_part`, under a name of this attempt's own until it is whole)."""
        self = cls.__new__(cls)
        folder = os.path.dirname(path)
        self._setup(target, folder, rarity_of, mix, cap, None, None)
        self.points = ArrayFile(folder, f".{os.path.basename(path)}-{uuid.uuid4().hex[:8]}", RECORD)
        self.part_path = path
        return self

    @classmethod
    def of_parts(cls, scan: space.SpatialScan, paths: list[str], folder: str, rarity_of, mix, cap: int):
        """The scan of a whole input from its parts' (:meth:`part`, in input order): their scans folded into
        ``scan`` (at most ``cap`` cells) and their points' files, read from where they are and removed once
        routed. What :meth:`order` then writes goes to ``folder``."""
        self = cls.__new__(cls)
        self._setup(scan.target, folder, rarity_of, mix, cap, None, None)
        self.mem, self.points = scan, Parts(paths)
        self.written = self.points.size
        return self

    @classmethod
    def of_frame(cls, frame: Frame, folder: str, rarity_of, fresh: bool = True) -> "DiskScan":
        """A scan of one of a cluster's routed files, in ``folder`` (:func:`expand_part`, :func:`list_part`)."""
        self = cls.__new__(cls)
        self._setup(frame.target, folder, rarity_of, seed_mix(frame.seed), frame.cap, frame.leaf, frame.fan)
        self.framed(frame, fresh)
        self.output = Appended  # a worker runs a task a thread: up to FAN files each, not held open
        return self

    def _setup(self, target: int, folder: str, rarity_of, mix, cap: int, leaf: int | None, fan: int | None):
        self.target = int(target)
        self.folder = folder
        self.rarity_of = rarity_of
        self.mix = mix
        self.cap = cap
        self.leaf = max(int(LEAF if leaf is None else leaf), 1)
        self.fan = max(int(FAN if fan is None else fan), 2)
        self.mem = space.SpatialScan(target, cap=cap, coarse=True)  # its order goes below its level anyway
        self.serial = 0
        self.written = 0  # points written to the points' file (what the summary reports)
        self.routed = 0  # points written to routed files
        self.recounted = 0  # small files counted again from the last possible level
        self.rescanned = 0  # large files scanned on their own
        self.sorted = 0  # births listed in the order
        self.sort_runs = 0  # runs of them sorted on disk (past SORT_RUN)
        self.sort_run, self.sort_block = SORT_RUN, SORT_BLOCK  # (the tests make them small)
        self.keep_inputs = False  # a cluster task's: the files it was given stay (a task run again reads them)
        self.output = ArrayFile  # what a routing writes to (a cluster task's: files it does not hold open)

    def add(self, xyz: np.ndarray, keys: np.ndarray, ids: np.ndarray) -> None:
        """One chunk: coordinates (n, 3) float64, bin keys and ids."""
        if len(ids) == 0:
            return
        ids = np.ascontiguousarray(ids, np.uint64)
        self.mem.add(xyz, self.rarity_of.of(keys), priorities_of_np(ids, self.mix), ids)
        rec = np.empty(len(ids), RECORD)
        rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        rec["key"], rec["id"] = keys, ids
        self.points.append(rec)
        self.written += len(rec)

    def order(self, seed: int, limit: int | None = None, into: ArrayFile | None = None) -> np.ndarray | None:
        """SPEC 9's spatial order (ids): every point born at or above the last level, in order; its first
        ``limit`` only, when given (what the merge takes). With ``into``, the ids are appended to that file
        instead (returns None)."""
        walked = self.walked(seed)
        if walked is None:
            return np.zeros(0, np.uint64)
        births, occupied, frame, alone = walked
        if alone:  # the last level is at or above the tracked one: the top scan's order is the whole order
            return self.alone(births, occupied, frame, limit, into)
        self.framed(frame)
        listed = self.listing()
        done = False
        try:
            for child in self._route(self.points, frame.tracked, 0):
                self._expand(child, frame.tracked, 1)
            last = self._last(occupied)
            if any(base > last for _, _, base, _ in self.leaves):  # counted from too coarse a level: again,
                self.recount(last)  # from the last possible one, for those (an input whose points are apart
                last = self._last(occupied)  # only below about 2^-21 of a file's extent)
            # every point born at or above the last level, sorted on disk past SORT_RUN of them (up to 2 T)
            self._list(listed, last, *births)  # every top birth is at or above ``tracked`` > last
            del births
            self.list_own(listed, last)
            out = self.taken(listed, limit, into)
            done = True
        finally:
            listed.discard()
            self.births.discard()
            for leaf in self.leaves:
                _remove(self.folder, leaf[0])
                _remove(self.folder, leaf[0] + ".joins")
            if not done:  # an error part way: every file the routing made that is still there
                for n in range(1, self.serial + 1):
                    _remove(self.folder, f"space.{n}")
                self.points.discard()
        release_memory()
        return out

    # ---- the steps of :meth:`order` (a Dask driver runs the files' on its workers: ..dask.driver) --------------

    def walked(self, seed: int):
        """The top scan walked and let go: (its births (levels, counts, cell priorities, priorities, ids),
        the occupied cells of its levels, the :class:`Frame`, whether its order is the whole order), or None
        when there are no points (their file removed)."""
        mem = self.mem.settled()
        if mem.state is None or mem.points == 0:
            self.points.discard()
            return None
        born, mass, cell_prio, occupied, top = mem.walk(seed)
        floor = top - space.LEVELS_BELOW_TOP
        _, _, prio, ids, _ = mem.state
        tracked, alone = mem.level, mem.origin or mem.level <= floor or occupied[mem.level] >= self.target
        self.mem = mem = None  # the top scan's cells go; its births stay
        frame = Frame(self.target, int(seed), self.cap, self.leaf, self.fan, floor, top, tracked)
        return (born, mass, cell_prio, prio, ids), occupied, frame, alone

    def alone(self, births, occupied: dict, frame: Frame, limit: int | None, into: ArrayFile | None):
        """The order when the top scan's is the whole order (the points' file removed)."""
        self.points.discard()
        born, mass, cell_prio, prio, ids = births
        out = space.listed_order(born, mass, cell_prio, prio, ids,
                                 space.last_level(occupied, self.target, max(frame.tracked, frame.floor)))
        out = out if limit is None else out[:limit].copy()
        if into is None:
            return out
        into.append(out)
        return None

    def framed(self, frame: Frame, fresh: bool = True) -> None:
        """Ready to sort points out by ``frame``: the counts of the levels below the tracked one, no files
        visited yet, the births' file (made, or with ``fresh`` False the one a first visit wrote, read)."""
        release_memory()  # the top scan's arrays, before the files' sorts make theirs
        self.floor, self.cell_mix, self.top = frame.floor, space.cell_mix(frame.seed), frame.top
        self.counts = np.zeros(frame.tracked - frame.floor, np.int64)  # occupied cells of floor .. tracked - 1
        self.leaves: list = []
        self.births = ArrayFile(self.folder, "space.births", BIRTH, "w+b" if fresh else "rb")

    def listing(self, name: str = "space.sorted") -> SortedRuns:
        """The sort of the listed births (in this scan's folder)."""
        return SortedRuns(self.folder, name, SORTED, SORT_KEYS, run=self.sort_run, block=self.sort_block,
                          open_file=scan_file)

    def recount(self, last: int) -> None:
        """The small files counted from too coarse a level for ``last``, counted again from the last possible one."""
        for leaf in self.leaves:
            if leaf[2] > last:
                self._recount(leaf)

    def list_own(self, listed: SortedRuns, last: int) -> None:
        """The births of the files visited (those the large files' scans wrote, then the small files'), at or
        above ``last``, into ``listed``; each file removed once read (unless :attr:`keep_inputs`)."""
        for part in self._listed_births(last):
            self._list(listed, last, *part)
        self._let_go(self.births)
        for leaf in self.leaves:
            self._list(listed, last, *self._leaf_births(leaf, last))

    def taken(self, listed: SortedRuns, limit: int | None, into: ArrayFile | None):
        """The first ``limit`` ids of the sorted births (all without a limit), or appended to ``into``."""
        self.sorted = listed.size
        out = _first_ids(listed.blocks(), listed.size if limit is None else min(limit, listed.size), into)
        self.sort_runs = listed.runs
        return out

    def _let_go(self, file) -> None:
        """A file read for the last time: removed, or (a cluster task's input, which a task run again reads)
        closed."""
        if self.keep_inputs:
            file.close()
        else:
            file.discard()

    def _list(self, listed: SortedRuns, last: int, born, mass, cell_prio, prio, ids) -> None:
        """Births (their levels, counts, cell priorities, priorities and ids) into the sort of the order: those
        at or above ``last``, by (level descending, count descending, cell priority, priority) as
        :func:`..core.space.listed_order` sorts them, the level and count as one word."""
        keep = np.flatnonzero(np.asarray(born) >= last)
        if len(keep) == 0:
            return
        born, mass = np.asarray(born)[keep], np.asarray(mass)[keep]
        if int(mass.max()) >= 1 << 40 or self.top - last >= 1 << 22:
            raise AssertionError("the spatial order's key holds counts under 2^40 and 2^22 levels")
        rec = np.empty(len(keep), SORTED)
        rec["first"] = (((self.top - born) << 40) | ((1 << 40) - 1 - mass)).astype(np.uint64)
        rec["cell_prio"], rec["prio"], rec["id"] = np.asarray(cell_prio)[keep], np.asarray(prio)[keep], \
            np.asarray(ids)[keep]
        listed.add(rec)

    # ---- the files -------------------------------------------------------------------------------------------

    def _name(self) -> str:
        self.serial += 1
        return f"space.{self.serial}"

    def _records(self, file: ArrayFile):
        for a in range(0, file.size, READ):
            yield file.read(a, min(READ, file.size - a))

    def _route(self, file: ArrayFile, level: int, depth: int) -> list:
        """``file``'s points into files by a hash of their cell at ``level`` (removed once read): every cell's
        points in one file. Returns the new files' (name, size), the empty ones left out."""
        fan = fan_of(file.size, self.fan, self.leaf)
        names = [self._name() for _ in range(fan)]
        outs = [self.output(self.folder, name, RECORD) for name in names]
        try:
            self.routed += route_records(self._records(file), level, depth, outs)
            sizes = [o.size for o in outs]
        finally:
            for o in outs:
                o.close()
            file.discard()
        kept = []
        for name, size in zip(names, sizes):
            if size:
                kept.append((name, size))
            else:
                _remove(self.folder, name)
        return kept

    def _open(self, name: str) -> ArrayFile:
        return ArrayFile(self.folder, name, RECORD, "r+b")

    def _points_of(self, file: ArrayFile) -> tuple:
        """A file's points: cells at the last possible level, rarities, priorities and ids."""
        rec = file.read(0, file.size)
        ids = np.ascontiguousarray(rec["id"])
        return (space.cells_at(_xyz(rec), self.floor), self.rarity_of.of(rec["key"]),
                priorities_of_np(ids, self.mix), ids)

    # ---- the first visit: every level's occupied cells ------------------------------------------------------

    def _expand(self, child: tuple, stop: int, depth: int, spread: bool = True) -> None:
        """The occupied cells, below level ``stop``, of a file's points (each of whose ``stop`` cells has all
        its points in it). A large file is routed again by another hash of the same cells (``spread``); one
        whose points that left mostly in one file (a few cells hold them) is scanned on its own instead, and
        its births below ``stop`` (to its own level) are written down."""
        name, size = child
        file = name if isinstance(name, Parts) else self._open(name)  # (a cluster task's: pieces of others')
        if size > self.leaf and spread:
            for grandchild in self._route(file, stop, depth):
                self._expand(grandchild, stop, depth + 1, grandchild[1] <= SPREAD_SHARE * size)
            return
        if size <= self.leaf:
            rec = file.read(0, size)
            cells = space.cells_at(_xyz(rec), self.floor)
            # sorted from ``base`` (the code's low word alone, unless the cells straddle 0 on an axis): exact
            # from ``base`` up, and below it at least the cells of ``base``
            base = space.fitting_base(cells, self.floor, stop)
            by, joins = space.morton_order(space.shifted(cells, self.floor, base), base)
            del cells
            exact = space.occupied_counts(joins, size, base, max(stop, base + 1))
            self.counts[base - self.floor:stop - self.floor] += exact[:stop - base]
            self.counts[:base - self.floor] += exact[0]
            if isinstance(file, Parts):  # pieces another task wrote (kept): the sorted points to a file of its own
                file.discard()
                name = self._name()
                file = ArrayFile(self.folder, name, RECORD)
            file.write_at(0, rec[by])  # in Morton order at ``base``, its neighbours' joins beside it (a byte
            file.close()  # each: a join is at most base + 252): a second visit from ``base`` sorts nothing
            with ArrayFile(self.folder, name + ".joins", np.uint8) as kept:
                kept.append(joins - base)
            self.leaves.append([name, stop, base, int(exact[0])])
            return
        level = self._rescan(file, stop)
        if level == self.floor:  # its cells are the last possible level's: nothing lies below
            file.discard()
            return
        for grandchild in self._route(file, level, depth):  # nothing of the scan held while they are visited
            self._expand(grandchild, level, depth + 1)

    def _rescan(self, file: ArrayFile, stop: int) -> int:
        """A large file scanned on its own: the occupied cells of its levels from the scan's level to
        ``stop`` and its cells' births there written down. Returns the scan's level."""
        self.rescanned += 1
        sub = space.SpatialScan(self.target, cap=self.cap, lowest=self.floor)
        for rec in self._records(file):
            ids = np.ascontiguousarray(rec["id"])
            sub.add(_xyz(rec), self.rarity_of.of(rec["key"]), priorities_of_np(ids, self.mix), ids)
        sub.settled()
        level = self.floor if sub.origin else sub.level  # every point at (0, 0, 0): its cell at any level
        cells, rarity, prio, ids, counts = sub.state
        del sub
        by, joins = space.morton_order(cells, level)
        self.counts[level - self.floor:stop - self.floor] += space.occupied_counts(joins, len(cells), level, stop)
        at, born, mass = space.births_below(cells, (level, stop, level), rarity, prio, counts, (by, joins))
        self._write_births(at, born, mass, cells, level, ids)
        return level

    def _last(self, occupied: dict) -> int:
        """SPEC 9's last level, from the top scan's levels and the files' summed counts below them."""
        every = {**occupied, **{self.floor + j: int(k) for j, k in enumerate(self.counts)}}
        return space.last_level(every, self.target, self.floor)

    def _recount(self, leaf: list) -> None:
        """A small file's occupied cells below its first count's level, exactly (every code word sorted)."""
        name, stop, base, at_base = leaf
        file = self._open(name)
        cells, _, _, _ = self._points_of(file)
        file.close()
        _, joins = space.morton_order(cells, self.floor)
        self.counts[:base - self.floor] += space.occupied_counts(joins, len(cells), self.floor, base) - at_base
        leaf[2] = self.floor
        self.recounted += 1

    def _write_births(self, at, born, mass, cells, level: int, ids) -> None:
        out = np.empty(len(at), BIRTH)
        out["level"], out["mass"], out["id"] = born, mass, ids[at]
        out["cell_prio"] = self._cell_prios(at, born, cells, level)
        self.births.append(out)

    def _cell_prios(self, at, born, cells, level: int) -> np.ndarray:
        cp = np.empty(len(at), np.uint64)
        for b in np.unique(born):
            where = np.flatnonzero(born == b)
            cp[where] = space.cell_priorities(self.cell_mix, int(b), space.shifted(cells[at[where]], level, int(b)))
        return cp

    # ---- the second visit: what is born at or above the last level -----------------------------------------

    def _listed_births(self, last: int):
        for a in range(0, self.births.size, READ):
            rec = self.births.read(a, min(READ, self.births.size - a))
            rec = rec[rec["level"] >= last]
            ids = np.ascontiguousarray(rec["id"])
            yield (rec["level"], rec["mass"], np.ascontiguousarray(rec["cell_prio"]),
                   priorities_of_np(ids, self.mix), ids)

    def _leaf_births(self, leaf: list, last: int) -> tuple:
        name, stop, base, _ = leaf
        if stop <= last:
            none = np.zeros(0, np.int64)
            return none, none, np.zeros(0, np.uint64), np.zeros(0, np.uint64), np.zeros(0, np.uint64)
        file = self._open(name)
        cells, rarity, prio, ids = self._points_of(file)
        self._let_go(file)
        order = None
        if base > self.floor:  # the first visit's order (a file counted again sorts again)
            joins = ArrayFile(self.folder, name + ".joins", np.uint8, "r+b")
            order = (np.arange(len(ids)), joins.read(0, joins.size).astype(np.int64) + base)
            self._let_go(joins)
        cells = space.shifted(cells, self.floor, base)  # base <= last: exact from there up
        at, born, mass = space.births_below(cells, (base, stop, last), rarity, prio, np.ones(len(ids), np.int64),
                                            order)
        return born, mass, self._cell_prios(at, born, cells, base), prio[at], ids[at]


class Parts:
    """Points' files written elsewhere (a Dask engine's groups: :func:`write_part`), read as one file of
    :data:`RECORD` (``size``, ``read``; one of them open at a time, however many there are) and removed
    together (``discard``)."""

    def __init__(self, paths: list[str], keep: bool = False):
        self.paths = list(paths)
        self.keep = keep  # ``discard`` closes them only (a cluster task's inputs, which a task run again reads)
        self.starts = np.cumsum([0] + [os.stat(p).st_size // RECORD.itemsize for p in self.paths])
        self.size = int(self.starts[-1])
        self.open, self.at = None, -1  # the file read last, and which

    def _file(self, i: int) -> ArrayFile:
        if i != self.at:
            if self.open is not None:
                self.open.close()
            self.open, self.at = ArrayFile(*os.path.split(self.paths[i]), RECORD, "rb"), i
        return self.open

    def read(self, offset: int, n: int) -> np.ndarray:
        end = offset + n
        i = int(np.searchsorted(self.starts, offset, "right")) - 1
        parts = []
        while n > 0 and i < len(self.paths):
            a = offset - int(self.starts[i])
            take = min(n, int(self.starts[i + 1]) - offset)
            if take > 0:
                parts.append(self._file(i).read(a, take))
                offset, n = offset + take, n - take
            i += 1
        if offset != end:
            raise AssertionError(f"read past the parts' {self.size} points")
        return parts[0] if len(parts) == 1 else np.concatenate(parts) if parts else np.zeros(0, RECORD)

    def discard(self) -> None:
        if self.open is not None:
            self.open.close()
        if not self.keep:
            for path in self.paths:
                _remove(*os.path.split(path))
        self.paths, self.starts, self.size, self.open, self.at = [], np.zeros(1, np.int64), 0, None, -1


class Appended:
    """A file of one dtype appended to without being held open, for a routing's outputs on a cluster's worker:
    up to :data:`FAN` of them a task and a task a worker thread would pass the usual 1,024 open files. What
    a routing asks of an :class:`..staging.ArrayFile` (``append``, ``size``, ``path``, ``close``,
    ``discard``)."""

    def __init__(self, folder: str, name: str, dtype):
        self.path, self.dtype, self.size = os.path.join(folder, name), np.dtype(dtype), 0
        with open(self.path, "wb"):
            pass

    def append(self, values: np.ndarray) -> None:
        with open(self.path, "ab") as f:
            f.write(np.ascontiguousarray(values, dtype=self.dtype).tobytes())
        self.size += len(values)

    def close(self) -> None:
        pass

    def discard(self) -> None:
        discard_file(self.path)


def fan_of(size: int, fan: int, leaf: int) -> int:
    """How many files ``size`` points are routed to: enough that each holds about half of ``leaf``, at most ``fan``."""
    return int(min(fan, max(2, math.ceil(2 * size / leaf))))


def route_records(records, level: int, depth: int, outs: list) -> int:
    """Blocks of points into the files ``outs`` by a hash of their cells at ``level`` (``depth`` seeds it):
    every cell's points in one file, in the order they come. Returns the points routed."""
    fan, n = len(outs), 0
    for rec in records:
        cells = space.cells_at(_xyz(rec), level)
        h = splitmix64_np(np.full(len(rec), depth, np.uint64))
        for axis in range(3):
            h = splitmix64_np(h ^ cells[:, axis].view(np.uint64))
        part = (h % np.uint64(fan)).astype(np.int64)
        by = np.argsort(part, kind="stable")
        edges = np.searchsorted(part[by], np.arange(fan + 1))
        for g in range(fan):
            if edges[g + 1] > edges[g]:
                outs[g].append(rec[by[edges[g]:edges[g + 1]]])
        n += len(rec)
    return n


# ---- the files' work as tasks (a Dask driver's, :func:`order_in_parts`) ---------------------------------------

def order_in_parts(disk: DiskScan, seed: int, limit: int | None, into: ArrayFile, run_tasks) -> None:
    """:meth:`DiskScan.order` of a scan whose points are in its parts' files (:meth:`DiskScan.of_parts`), the
    files' work done as tasks: ``run_tasks(fn, jobs)`` runs ``fn(*args)`` for each ``args`` of ``jobs`` (on a
    cluster's workers, which see the parts' folder) and returns the results in order. Each part's points are
    routed as the first route routes the whole input's (:func:`route_part`), each routed file is visited from
    its parts' pieces (:func:`expand_part`, counted again if need be: :func:`recount_part`), each lists its
    births into sorted runs (:func:`list_part`) and the driver merges those with the top scan's into the
    order's first ``limit`` ids, appended to ``into``: the same order, bit for bit. A step's inputs are removed
    once every task of it has finished (a task run again finds them); every file is in the parts' folder."""
    walked = disk.walked(seed)
    if walked is None:
        return
    births, occupied, frame, alone = walked
    if alone:
        disk.alone(births, occupied, frame, limit, into)
        return
    disk.framed(frame)
    parts, rarity_of = disk.points, disk.rarity_of
    work = os.path.dirname(parts.paths[0])
    listed, visited = disk.listing(), []
    since = [time.perf_counter()]

    def run(fn, jobs: list, what: str) -> list:
        out = run_tasks(fn, jobs)
        now = time.perf_counter()
        say(f"spatial share on disk: {what} ({len(jobs):,} tasks), {now - since[0]:.1f} s")
        since[0] = now
        return out

    try:
        fan = fan_of(parts.size, frame.fan, frame.leaf)
        routed = run(route_part, [(p, frame, fan) for p in parts.paths], f"{parts.size:,} points routed to {fan} files")
        parts.discard()
        pieces = [[files[j] for files, _ in routed if files[j] is not None] for j in range(fan)]
        disk.routed = sum(n for _, n in routed)
        jobs = [(frame, rarity_of, p, os.path.join(work, f"routed-{j:03d}")) for j, p in enumerate(pieces) if p]
        visited = run(expand_part, jobs, "the routed files visited")
        for p in pieces:
            for path in p:
                _remove(*os.path.split(path))
        for v in visited:
            disk.counts += v["counts"]
            disk.routed += v["routed"]
        last = disk._last(occupied)
        leaves = [v["leaves"] for v in visited]
        if any(leaf[2] > last for some in leaves for leaf in some):
            again = run(recount_part, [(frame, rarity_of, some, v["folder"], last) for some, v in zip(leaves, visited)],
                        "small files counted again")
            for i, (counts, some) in enumerate(again):
                disk.counts += counts
                leaves[i] = some
            last = disk._last(occupied)
        runs = run(list_part, [(frame, rarity_of, some, v["folder"], last) for some, v in zip(leaves, visited)],
                   f"births at or above level {last} listed")
        for some, v in zip(leaves, visited):  # the visits' files, before the merge: their runs alone are left
            for name in ["space.births"] + [n for leaf in some for n in (leaf[0], leaf[0] + ".joins")]:
                _remove(v["folder"], name)
        disk._list(listed, last, *births)
        del births
        for r in runs:
            listed.adopt(r)
        disk.taken(listed, limit, into)
        say(f"spatial share on disk: the order's {into.size:,} ids merged from {listed.size:,} births, "
            f"{time.perf_counter() - since[0]:.1f} s")
    finally:
        listed.discard()
        disk.births.discard()
        disk.points.discard()
        for v in visited:
            shutil.rmtree(v["folder"], ignore_errors=True)
    release_memory()


def route_part(path: str, frame: Frame, fan: int) -> tuple[list, int]:
    """A part's points (its file: ``path``) routed as the whole input's are first routed, by their cells at
    the tracked level, to ``fan`` files beside it, ``path.NNN`` each once whole (under a name of this
    attempt's own until then); the part's file stays. Returns each file's path (None: no points) and the
    points routed."""
    folder, base = os.path.split(path)
    tag = uuid.uuid4().hex[:8]
    outs = [Appended(folder, f".{base}.{j:03d}-{tag}", RECORD) for j in range(fan)]
    source = Parts([path], keep=True)
    done = False
    try:
        n = route_records((source.read(a, min(READ, source.size - a)) for a in range(0, source.size, READ)),
                          frame.tracked, 0, outs)
        done = True
    finally:
        source.discard()
        for o in outs:
            o.close() if done else o.discard()
    got = []
    for j, o in enumerate(outs):
        if o.size:
            os.replace(o.path, f"{path}.{j:03d}")
            got.append(f"{path}.{j:03d}")
        else:
            o.discard()
            got.append(None)
    return got, n


def expand_part(frame: Frame, rarity_of, pieces: list[str], prefix: str) -> dict:
    """The first visit (:meth:`DiskScan._expand`) of the routed file the parts' ``pieces`` make up (in input
    order), in a folder made here, ``prefix`` and this attempt's own tag: its levels' occupied cells, its
    small files sorted and its large files' births, left there for :func:`list_part`. The pieces stay."""
    folder = f"{prefix}-{uuid.uuid4().hex[:8]}"
    os.mkdir(folder)
    scan = DiskScan.of_frame(frame, folder, rarity_of)
    source = Parts(pieces, keep=True)
    try:
        scan._expand((source, source.size), frame.tracked, 1)
    finally:
        source.discard()
        scan.births.close()
        unmark_under(folder)  # its files are the driver's to remove now (this process may run other runs' tasks)
    return {"folder": folder, "counts": scan.counts, "leaves": scan.leaves, "routed": scan.routed}


def recount_part(frame: Frame, rarity_of, leaves: list, folder: str, last: int) -> tuple:
    """:meth:`DiskScan.recount` of a visited file's small files: (the counts to add, the leaves)."""
    scan = DiskScan.of_frame(frame, folder, rarity_of, fresh=False)
    scan.leaves = [list(leaf) for leaf in leaves]
    try:
        scan.recount(last)
    finally:
        scan.births.close()
    return scan.counts, scan.leaves


def list_part(frame: Frame, rarity_of, leaves: list, folder: str, last: int) -> list:
    """A visited file's births at or above ``last`` (:meth:`DiskScan.list_own`), as sorted runs in ``folder``
    (named for this attempt): their (path, records), for the driver's merge (:meth:`.extsort.SortedRuns.adopt`).
    The visit's files stay."""
    scan = DiskScan.of_frame(frame, folder, rarity_of, fresh=False)
    scan.leaves, scan.keep_inputs = leaves, True
    listed = scan.listing(f"space.sorted-{uuid.uuid4().hex[:8]}")
    try:
        scan.list_own(listed, last)
        return listed.runs_written()
    except BaseException:
        listed.discard()
        raise
    finally:
        unmark_under(folder)  # the runs are the driver's to merge and remove


def write_part(scan: DiskScan) -> None:
    """A part's points' file (:meth:`DiskScan.part`) renamed to its path once whole: a task that runs again
    rewrites it under another name and renames that over it."""
    scan.points.close()
    os.replace(scan.points.path, scan.part_path)
    unmark(scan.points.path)


def _first_ids(blocks, n: int, into: ArrayFile | None = None) -> np.ndarray | None:
    """The ids of the first ``n`` records of sorted ``blocks`` (the generator closed once they are taken), or
    with ``into``, appended to that file."""
    out = np.empty(0 if into is not None else n, np.uint64)
    at = 0
    try:
        for block in blocks:
            if at >= n:
                break
            take = min(len(block), n - at)
            if into is not None:
                into.append(block["id"][:take])
            else:
                out[at:at + take] = block["id"][:take]
            at += take
    finally:
        blocks.close()
    return None if into is not None else out[:at]


def scan_file(folder: str, name: str, dtype) -> ArrayFile:
    """A temporary file of the spatial share's steps (this one's sorts, and :mod:`.spatial_merge`'s)."""
    return ArrayFile(folder, name, dtype)  # looked up at the call: the tests measure these files' bytes too


def _xyz(rec: np.ndarray) -> np.ndarray:
    return np.stack([rec["x"], rec["y"], rec["z"]], axis=1)


def _remove(folder: str, name: str) -> None:
    discard_file(os.path.join(folder, name))
