"""Records sorted by a key of unsigned words, in bounded memory: sorted runs in temporary files, merged.

:class:`SortedRuns` takes records (a structured dtype) in any order and gives them back in ascending
order of their key fields (compared left to right, each an unsigned integer), a block at a time. Records
are sorted ``run`` at a time; when everything added fits one run nothing is written. Otherwise each run
goes to a file of its own, and :meth:`SortedRuns.blocks` merges the files: it reads a block of each, takes
from every block the records up to the smallest of the blocks' last keys (found by narrowing one key
field at a time), sorts what it took and hands it out, and reads a run's next block once its block is used
up. Each step hands out at least one whole block, so the merge ends after about as many steps as there
are blocks.

Memory: one run's records and its sort (about three times ``run`` records), or while merging one block
a run and what a step takes (at most one block a run), twice. Files: a run's is closed once written, and
at most :data:`FAN_IN` are open at once while merging (more runs are first merged in passes, ``FAN_IN`` at
a time into one). Disk: every record once (twice for the records of a pass, until its runs are removed),
the runs' files removed as the merge ends, or by :meth:`SortedRuns.discard` on an error. Records whose
keys are equal come out in no particular order: a key that tells every record apart makes the order exact.
"""

from __future__ import annotations

import os

import numpy as np

from .staging import ArrayFile, discard_file

RUN = 1 << 21  # records sorted in memory at a time
BLOCK = 1 << 16  # records read from a run at a time while merging
MERGE_MEMORY = 64 << 20  # the most bytes the merge's blocks hold together (fewer records a block past it)
FAN_IN = 256  # the most runs merged at once (and so open at once); more are merged in passes first


class SortedRuns:
    """Records of ``dtype`` sorted by the fields ``keys`` (unsigned words, the first the most significant),
    in files named ``name``.1, .2, ... of ``folder``. ``open_file(folder, name, dtype)`` makes a file (an
    :class:`..staging.ArrayFile`, by default). A run's file is closed once written, and opened again only
    while it is merged: at most ``fan_in`` at a time (beside the one a pass writes), runs past that merged in
    passes into longer runs."""

    def __init__(self, folder: str, name: str, dtype, keys: tuple, run: int | None = None,
                 block: int | None = None, open_file=None):
        self.folder, self.name = folder, name
        self.dtype = np.dtype(dtype)
        self.keys = tuple(keys)
        for k in self.keys:
            if self.dtype[k].kind != "u":
                raise TypeError(f"sort key {k!r} is not an unsigned integer field")
        self.run = max(int(RUN if run is None else run), 1)
        self.block = max(int(BLOCK if block is None else block), 1)
        self.fan_in = max(int(FAN_IN), 2)
        self.open_file = open_file or ArrayFile
        self.pending: list = []
        self.held = 0  # records in ``pending``
        self.files: list = []  # the runs' (name, records), in the order written
        self.serial = 0
        self.size = 0  # records added
        self.runs = 0  # runs written to files (the first sort's, not the passes')
        self.reading: list = []  # the runs a merge has open

    def _sorted(self, rec: np.ndarray) -> np.ndarray:
        return rec[np.lexsort(tuple(rec[k] for k in reversed(self.keys)))]

    def add(self, rec: np.ndarray) -> None:
        """Records, in any order."""
        if len(rec) == 0:
            return
        if rec.dtype != self.dtype:
            raise TypeError(f"records of {rec.dtype}, not {self.dtype}")
        self.size += len(rec)
        while len(rec):
            take = min(len(rec), self.run - self.held)
            self.pending.append(np.array(rec[:take]))  # a copy: the caller's array may be a view of a larger one
            self.held += take
            rec = rec[take:]
            if self.held == self.run:
                self._spill()

    def _gather(self) -> np.ndarray:
        rec = np.concatenate(self.pending) if len(self.pending) > 1 else self.pending[0]
        self.pending, self.held = [], 0
        return rec

    def _written(self, blocks) -> tuple:
        """A new run's file from sorted ``blocks``: its (name, records)."""
        self.serial += 1
        name = f"{self.name}.{self.serial}"
        self.files.append((name, 0))
        try:
            f = self.open_file(self.folder, name, self.dtype)
            try:
                for b in blocks:
                    f.append(b)
                size = f.size
            finally:
                f.close()
        finally:
            if hasattr(blocks, "close"):  # a pass's merge: its runs closed now, even on an error
                blocks.close()
        self.files[-1] = (name, size)
        return name, size

    def _spill(self) -> None:
        self._written([self._sorted(self._gather())])
        self.runs += 1

    def blocks(self):
        """Every record added, in key order, a sorted block at a time; the runs' files are removed once it
        ends (or is closed). Adding after this starts is an error."""
        try:
            if not self.files:
                if self.held:
                    yield self._sorted(self._gather())
                return
            if self.held:
                self._spill()
            # passes: runs merged into one, removed once read, until fan_in are left; the first pass takes
            # just enough that each later one takes fan_in (the fewest records written again)
            take = (len(self.files) - 2) % (self.fan_in - 1) + 2
            while len(self.files) > self.fan_in:
                group = sorted(self.files, key=lambda f: f[1])[:take]  # the smallest runs
                self._written(self._merged(group))
                for name, _ in group:
                    discard_file(os.path.join(self.folder, name))
                self.files = [f for f in self.files if f not in group]  # (the new run last)
                take = self.fan_in
            yield from self._merged(list(self.files))
        finally:
            self.discard()

    def _merged(self, runs: list):
        files = self.reading = []
        try:
            for name, _ in runs:
                files.append(ArrayFile(self.folder, name, self.dtype, "rb"))
            yield from self._merge(files)
        finally:
            for f in files:
                f.close()

    def _merge(self, files: list):
        per = max(1, min(self.block, MERGE_MEMORY // (self.dtype.itemsize * len(files))))
        at = [0] * len(files)
        heads: list = [None] * len(files)

        def refill(i):
            f = files[i]
            n = min(per, f.size - at[i])
            heads[i] = f.read(at[i], n) if n > 0 else None
            at[i] += max(n, 0)

        for i in range(len(files)):
            refill(i)
        while True:
            live = [i for i in range(len(files)) if heads[i] is not None]
            if not live:
                return
            bound = min(tuple(int(heads[i][k][-1]) for k in self.keys) for i in live)
            taken = []
            for i in live:
                n = _upto(heads[i], self.keys, bound)
                if n:
                    taken.append(heads[i][:n])
                    heads[i] = heads[i][n:]
                if len(heads[i]) == 0:
                    refill(i)
            out = np.concatenate(taken) if len(taken) > 1 else taken[0]
            yield self._sorted(out) if len(taken) > 1 else out

    def runs_written(self) -> list[tuple[str, int]]:
        """Every record added as sorted runs in files (the last one written now), handed over: their (path,
        records), for another sort to merge (:meth:`adopt`); this one holds nothing after."""
        if self.held:
            self._spill()
        files, self.files = self.files, []
        return [(os.path.join(self.folder, name), size) for name, size in files]

    def adopt(self, runs: list[tuple[str, int]]) -> None:
        """Sorted runs another sort wrote (:meth:`runs_written`: (path, records) each), merged with this
        one's records and removed with its runs."""
        for path, size in runs:
            self.files.append((path, size))  # an absolute path: os.path.join keeps it whole
            self.size += size

    def discard(self) -> None:
        """Close the runs a merge has open, remove every run's file and let go of what is held."""
        for f in self.reading:
            f.close()
        files, self.files = self.files, []
        for name, _ in files:
            discard_file(os.path.join(self.folder, name))
        self.pending, self.held = [], 0


def _upto(block: np.ndarray, keys: tuple, bound: tuple) -> int:
    """How many records at the start of ``block`` (sorted by ``keys``) have keys at most ``bound``."""
    lo, hi = 0, len(block)
    for k, b in zip(keys, bound):
        col = block[k][lo:hi]
        v = col.dtype.type(b)
        lo, hi = lo + int(np.searchsorted(col, v, "left")), lo + int(np.searchsorted(col, v, "right"))
        if lo == hi:
            return lo
    return hi
