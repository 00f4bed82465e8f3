"""The candidate spill of the one-read path: pass one's candidates, in input order, on disk.

Pass one of the one-read path (:func:`..core.passes.scan_candidates`) appends
every point that may still be selected to a :class:`Spill`; the cutoffs and
pass two read the spill instead of the input. The local engine keeps one
spill in its temporary folder for the whole run; the Dask engine gives every
work unit its own, in the output's staging folder, which a pass-two task on
another worker reopens with :meth:`Spill.reopen`.
"""

from __future__ import annotations

import contextlib
import os
import pickle

import numpy as np

from .staging import ArrayFile
from .tempspace import gib


def spill_refusal(sources) -> str | None:
    """Why these sources cannot be read once with a candidate spill (None: they can), whatever the engine."""
    if any(s.count is None for s in sources):
        return "the number of points is not known before reading (a query's result)"
    if not all(getattr(s, "spills", False) for s in sources):
        return "an input format cannot keep its points in a spill"
    return None


class SpillFull(Exception):
    """The spill passed its budget or filled the temporary folder during pass one: the run starts over
    reading the input twice."""


class Spill:
    """Pass one's candidates, in input order, in files of ``folder``: what pass two reads instead of the input.

    - ``keys`` / ``ids``: the index, each candidate's bin key (uint32) and id (uint64);
    - ``frames``: one pickled frame per chunk with candidates, (count, the format's spill state);
    - ``log``: the keys of the current file's points while its color depth is undecided (a file after
      the first: the first one's are all the filter counted);
    - ``spill.meta`` (written by :meth:`finish`): where each source's candidates and frames start and end.
    """

    def __init__(self, folder: str, *, reopen: bool = False, budget: int | None = None, records: bool = True):
        mode = "rb" if reopen else "w+b"
        self.folder = folder
        self.keys = ArrayFile(folder, "spill.keys", np.uint32, mode)
        self.ids = ArrayFile(folder, "spill.ids", np.uint64, mode)
        self.log = None if reopen else ArrayFile(folder, "undecided.keys", np.uint32)
        self.frames = open(os.path.join(folder, "spill.frames"), mode)
        self.starts: dict = {}  # ordinal -> (first candidate, first frame byte)
        self.ends: dict = {}
        self.source = None
        self.reopened = reopen
        self.refiled = 0  # points moved to key 0 by a switch to 16-bit (refile)
        self.finished = False  # finish() keeps the files for reopen()
        self.budget = budget  # the most bytes the spill may take (None: as much as the disk has)
        self.records = records  # False: the index alone (a plan's dry run, which reads colors only)
        self.frame_count = 0  # chunks with candidates (a frame each, when records are kept)

    @classmethod
    def reopen(cls, folder: str) -> "Spill":
        """A finished spill, read back (by another process): its index and frames, nothing appended."""
        spill = cls(folder, reopen=True)
        try:
            with open(os.path.join(folder, "spill.meta"), "rb") as f:
                spill.starts, spill.ends = pickle.load(f)
            if spill.keys.size != spill.ids.size or spill.keys.size != max(spill.ends.values(), default=0):
                raise OSError(f"spill in {folder} is incomplete")
        except BaseException:
            spill.close()
            raise
        return spill

    @property
    def size(self) -> int:
        """Candidates spilled."""
        return self.keys.size

    @property
    def bytes(self) -> int:
        frames = os.path.getsize(self.frames.name) if self.reopened else self.frames.tell()
        return self.size * 12 + frames

    def begin_source(self, src) -> None:
        self._end_source()
        self.source = src
        self.starts[src.ordinal] = (self.size, self.frames.tell())
        self.log.clear()

    def _end_source(self) -> None:
        if self.source is not None:
            self.ends[self.source.ordinal] = self.size

    def log_keys(self, keys: np.ndarray) -> None:
        self.log.append(keys)

    def add(self, chunk, keys: np.ndarray, mask: np.ndarray, first_id: int) -> None:
        at = np.flatnonzero(mask)
        if not len(at):
            return
        self.keys.append(keys[at])
        self.ids.append(np.uint64(first_id) + at.astype(np.uint64))
        self.frame_count += 1
        if not self.records:
            return
        state = self.source.spill_state(chunk, at)
        pickle.dump((len(at), state), self.frames, protocol=pickle.HIGHEST_PROTOCOL)
        if self.budget is not None and self.bytes > self.budget:
            raise SpillFull(f"the candidate spill passed the {gib(self.budget)} its disk can spare "
                            f"({self.size:,} points)")

    def flush(self) -> None:
        for f in (self.keys.file, self.ids.file, self.log.file, self.frames):
            f.flush()

    def finish(self) -> None:
        """Flush everything and record where each source lies (``spill.meta``), so :meth:`reopen` can read it."""
        self._end_source()
        self.flush()
        for f in (self.keys.file, self.ids.file, self.frames):
            os.fsync(f.fileno())
        meta = os.path.join(self.folder, "spill.meta")
        with open(meta + ".part", "wb") as f:
            pickle.dump((self.starts, self.ends), f, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(meta + ".part", meta)
        self.finished = True

    def index(self, a: int = 0, b: int | None = None, step: int = 1 << 20):
        """(keys, ids) of candidates [a, b), ``step`` at a time."""
        b = self.size if b is None else b
        for x in range(a, b, step):
            n = min(step, b - x)
            yield self.keys.read(x, n), self.ids.read(x, n)

    def refile(self, candidates, moved: int) -> None:
        """The current file proved 16-bit after ``moved`` points: they all go to key 0 (SPEC 1).

        ``candidates`` is the run's :class:`..core.candidates.CandidateFilter`: its counts lose the
        points' old keys and its heaps are made again from the index."""
        self.refiled += moved
        if candidates.first_source:  # its points are all the filter counted: no log was kept
            if moved != candidates.offered:
                raise AssertionError(f"{moved} points to refile, {candidates.offered} offered")
            candidates.drop_offered()
        else:
            if moved != self.log.size:
                raise AssertionError(f"{moved} points to refile, {self.log.size} logged")
            for x in range(0, moved, 1 << 20):
                candidates.uncount(self.log.read(x, min(1 << 20, moved - x)))
        first = self.starts[self.source.ordinal][0]
        self.keys.overwrite_zero(first, self.size - first)
        candidates.rebuild(moved, self.index())
        self.log.clear()

    def frames_of(self, src):
        """(keys, ids, chunk) of every spilled frame of ``src``, in input order."""
        self._end_source()
        first, offset = self.starts.get(src.ordinal, (0, None))
        if offset is None:
            return
        end = self.ends[src.ordinal]
        self.frames.flush()
        with open(self.frames.name, "rb") as f:
            f.seek(offset)
            while first < end:
                n, state = pickle.load(f)
                keys, ids = next(self.index(first, first + n, n))
                yield keys, ids, src.restore(state)
                first += n

    def close(self) -> None:
        """Close the files; they are deleted too unless the spill was finished (or is a reopened one)."""
        keep = self.reopened or self.finished
        with contextlib.ExitStack() as stack:  # every file closed even if one close fails (a full disk)
            for f in (self.keys, self.ids):
                stack.callback(f.close if keep else f.discard)
            if self.log is not None:
                stack.callback(self.log.discard)
            stack.callback(self.frames.close)
            if not keep:
                stack.callback(_unlink, self.frames.name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _unlink(path: str) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass
