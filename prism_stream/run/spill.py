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

from ..core.sparse import sparse_zeros
from ..errors import Interrupted, TempDataChanged
from . import staging
from .staging import ArrayFile
from .tempspace import gib


def spill_refusal(sources) -> str | None:
    """Why these sources cannot be read once with a candidate spill (None: they can), whatever the engine."""
    if any(s.count is None for s in sources):
        return "the number of points is not known before reading (a query's result)"
    if not all(getattr(s, "spills", False) for s in sources):
        return "an input format cannot keep its points in a spill"
    return None


COMPACT_SHARE = 0.75  # a spill is compacted once it holds this share of the random-order bound: in random order it
# ends at 0.5-0.66 of it at 10^7 points and more (bench/RESULTS_SCALE.md), so a compaction there is rare


def compact_mark(bound: int) -> int:
    """Candidates at which a spill is first compacted, for a run whose random-order bound is ``bound``."""
    return max(1, int(bound * COMPACT_SHARE))


def spill_history(spill: "Spill") -> dict:
    """What the summary says of a spill beyond its size: the filter's candidates, those written, the most
    held at once, and the compactions that removed the ones no longer selectable."""
    return {"spill_candidates": spill.admitted, "spill_points_written": spill.written,
            "spill_points_peak": spill.peak, "spill_compactions": spill.compactions}


def _identity(st: os.stat_result) -> tuple[int, int]:
    """(size, mtime ns) of a spill file as its writer left it: a file replaced by one of the same size, or
    written over in place, is told from it by its mtime (an inode number adds little: ext4 gives a freed one
    to the next file, and an SMB share without server inode numbers makes them up)."""
    return st.st_size, st.st_mtime_ns


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
        self.frames_path = os.path.join(folder, "spill.frames")
        self.frames = open(self.frames_path, mode)
        if not reopen:
            staging.mark(self.frames_path, self.frames.fileno())
        self.starts: dict = {}  # ordinal -> (first candidate, first frame byte)
        self.ends: dict = {}
        self.source = None
        self.reopened = reopen
        self.refiled = 0  # points moved to key 0 by a switch to 16-bit (refile)
        self.finished = False  # finish() keeps the files for reopen()
        self.budget = budget  # the most bytes the spill may take (None: as much as the disk has)
        self.records = records  # False: the index alone (a plan's dry run, which reads colors only)
        self.frame_count = 0  # chunks with candidates (a frame each, when records are kept)
        self.compact_at = None  # candidates past which the spill is compacted (None: never; :meth:`compact`)
        self.compact_base = None  # compact_at's floor (it doubles past what a compaction leaves)
        self.admitted = 0  # the filter's candidates in all
        self.written = 0  # candidates appended in all (a compaction before a chunk's append drops some of its
        # own; a later one removes some written; ``size`` is what is left)
        self.compactions = 0
        self.peak = 0  # the most candidates the spill held at once
        self.sources: dict = {}  # ordinal -> source, for a compaction's frames
        self.broken = False  # a compaction failed part way: what the files hold is no longer the candidates

    @classmethod
    def reopen(cls, folder: str) -> "Spill":
        """A finished spill, read back (by another process): its index and frames, nothing appended."""
        try:
            spill = cls(folder, reopen=True)
        except FileNotFoundError as exc:  # written by a task that finished: removed since
            raise TempDataChanged(f"{os.path.basename(exc.filename or folder)} was removed", folder) from None
        try:
            try:
                with open(os.path.join(folder, "spill.meta"), "rb") as f:
                    spill.starts, spill.ends, sizes = pickle.load(f)
                sizes = {str(k): tuple(int(x) for x in v) for k, v in sizes.items()}
            except Exception as exc:  # noqa: BLE001 - whatever garbage unpickles to, or fails as
                raise TempDataChanged(f"spill.meta cannot be read ({type(exc).__name__})", folder) from None
            for name, (size, mtime) in sizes.items():  # as the task that wrote them left them
                what = staging.change_of(os.path.join(folder, name), size, mtime)
                if what is not None:
                    raise TempDataChanged(what, folder)
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
        frames = os.path.getsize(self.frames_path) if self.reopened else self.frames.tell()
        return self.size * 12 + frames

    def begin_source(self, src) -> None:
        self._end_source()
        self.source = src
        self.sources[src.ordinal] = src
        self.starts[src.ordinal] = (self.size, self.frames.tell())
        self.log.clear()

    def _end_source(self) -> None:
        if self.source is not None:
            self.ends[self.source.ordinal] = self.size

    def log_keys(self, keys: np.ndarray) -> None:
        self.log.append(keys)

    def add(self, chunk, keys: np.ndarray, mask: np.ndarray, first_id: int, candidates=None) -> None:
        """Append a chunk's candidates (``mask``). ``candidates``: the run's filter, when every point it
        counted has its final bin: if this chunk would take the spill past its mark, the spill and the
        chunk's candidates are compacted together first (:meth:`compact`), so the spill never holds more
        than its mark and what a compaction leaves."""
        self._usable()
        at = np.flatnonzero(mask)
        ids = np.uint64(first_id) + at.astype(np.uint64)
        self.admitted += len(at)
        if candidates is not None and self._due(len(at)):
            kept = self.compact(candidates, keys[at], ids)
            at, ids = at[kept], ids[kept]
        if not len(at):
            return
        self.keys.append(keys[at])
        self.ids.append(ids)
        self.frame_count += 1
        self.written += len(at)
        self.peak = max(self.peak, self.size)
        # a plan's dry run keeps the frames' sizes alone, so a compaction cuts its index where the run's is cut
        state = self.source.spill_state(chunk, at) if self.records else None
        staging.verify(self.frames_path)
        try:
            pickle.dump((len(at), state), self.frames, protocol=pickle.HIGHEST_PROTOCOL)
            self.frames.flush()
        finally:  # what a failed write (a full disk) left is this process's own too
            staging.mark(self.frames_path, self.frames.fileno())
        if self.budget is not None and self.bytes > self.budget:
            raise SpillFull(f"the candidate spill passed the {gib(self.budget)} its disk can spare "
                            f"({self.size:,} points)")

    def flush(self) -> None:
        for f in (self.keys.file, self.ids.file, self.log.file, self.frames):
            f.flush()

    def finish(self) -> None:
        """Flush everything and record where each source lies (``spill.meta``), so :meth:`reopen` can read it."""
        self._usable()
        self._end_source()
        self.flush()
        for f in (self.keys.file, self.ids.file, self.frames):
            os.fsync(f.fileno())
        meta = os.path.join(self.folder, "spill.meta")
        sizes = {os.path.basename(path): _identity(os.fstat(f.fileno())) for path, f in (
            (self.keys.path, self.keys.file), (self.ids.path, self.ids.file), (self.frames_path, self.frames))}
        with open(meta + ".part", "wb") as f:
            pickle.dump((self.starts, self.ends, sizes), f, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(meta + ".part", meta)
        self.finished = True

    def index(self, a: int = 0, b: int | None = None, step: int = 1 << 20):
        """(keys, ids) of candidates [a, b), ``step`` at a time."""
        self._usable()
        b = self.size if b is None else b
        for x in range(a, b, step):
            n = min(step, b - x)
            yield self.keys.read(x, n), self.ids.read(x, n)

    def _usable(self) -> None:
        if self.broken:
            raise AssertionError("the spill is used after a compaction failed part way")

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

    def limit(self, points: int | None) -> None:
        """Compact the spill whenever it holds ``points`` candidates (None: never)."""
        self.compact_at = self.compact_base = points

    def _due(self, more: int) -> bool:
        """``more`` candidates would take the spill to the size at which :meth:`compact` is worth its read."""
        return self.compact_at is not None and self.size + more >= self.compact_at

    @property
    def due(self) -> bool:
        return self._due(0)

    def compact(self, candidates, keys: np.ndarray | None = None,
                ids: np.ndarray | None = None) -> np.ndarray | None:
        """Drop the spilled candidates that can no longer be selected, and write the rest again.

        A point is a candidate if it may be selected *at its arrival*; as the counts grow the bound falls,
        and a point spilled early (while its bin's cap was high, or before its bin's heap filled) may now lie
        past its bin's cap smallest. ``candidates.standing_rules()`` says how many each bin keeps whatever
        comes later; the cutoffs over the spill's index (:func:`..core.cutoffs.standing_cuts`) find them, and
        the index and frames are written again with only those, in the same order, over the old ones
        (:meth:`_rewrite`, in place). Only while every point counted has its final bin (the caller: no
        file's color depth undecided). The next compaction comes at twice what is left, or at the floor.

        ``keys``, ``ids``: a chunk's candidates not written yet, which the cutoffs see too; returns which of
        them stay (None without them)."""
        from .memory import release_memory

        if keys is not None:  # read-only, as the index's own arrays are: one compiled version of each loop
            keys, ids = keys.view(), ids.view()
            keys.flags.writeable = ids.flags.writeable = False
        kept = None if keys is None else np.ones(len(keys), dtype=np.bool_)
        release_memory()  # the decoded batches the allocators keep: the compaction's tables take their place
        aside = self._set_aside(candidates)
        try:
            kept = self._compact(candidates, keys, ids, kept)
        except BaseException:
            if aside is not None:
                with contextlib.suppress(Exception):
                    self._take_back(candidates, aside)
            raise
        if aside is not None:
            self._take_back(candidates, aside)
        return kept

    def _set_aside(self, candidates) -> list | None:
        """Write what the compaction does not read of the filter (:meth:`.CandidateFilter.aside`: its heaps) to a
        file in the spill's folder and let it go until :meth:`_take_back`: over 2^24 bins at T = 50M a compaction
        peaked at 1,058 MiB with them held. None (they stay) when the disk refuses the file."""
        path = os.path.join(self.folder, "heaps.aside")
        parts = candidates.aside()
        try:
            with open(path, "wb") as f:
                for _, array, n in parts:
                    array[:n].tofile(f)
                f.flush()
                staging.mark(path, f.fileno())
        except OSError:
            staging.discard_file(path)
            return None
        shapes = [(name, len(array), array.dtype, n) for name, array, n in parts]
        parts = array = None  # no reference left here: the arrays go when the filter lets them go
        for name, *_ in shapes:
            setattr(candidates, name, None)
        return shapes

    def _take_back(self, candidates, shapes: list) -> None:
        path = os.path.join(self.folder, "heaps.aside")
        staging.verify(path)  # another process changed it: TempDataChanged, never heaps made of garbage
        with open(path, "rb") as f:
            for name, size, dtype, n in shapes:
                array = sparse_zeros(size, dtype)  # the OS's pages only where slots are, as the filter made it
                view = memoryview(array[:n]).cast("B")
                if f.readinto(view) != view.nbytes:
                    raise TempDataChanged(f"{os.path.basename(path)} was truncated", self.folder)
                setattr(candidates, name, array)
        staging.discard_file(path)

    def _compact(self, candidates, keys, ids, kept):
        from ..core import kernels
        from ..core.cutoffs import standing_cuts

        rules = candidates.standing_rules()
        if rules is not None:
            def feed(finder):
                for k, i in self.index():
                    finder.add_ids(k, i)
                if keys is not None:
                    finder.add_ids(keys, ids)

            cut = standing_cuts(rules, feed)
            rules.caps = None  # 4 bytes a capped bin, not read again: the rewrite's buffers take their place

            def keep(k, i):
                return kernels.keep_mask_ids(kernels.read_only(k, np.uint32), kernels.read_only(i, np.uint64),
                                             rules.seed_mix, rules.rule, cut)

            self._rewrite(keep)
            if keys is not None:
                kept = keep(keys, ids)
            candidates.tighten(rules, cut)
            self.compactions += 1
        if self.compact_base is not None:
            self.compact_at = max(self.compact_base, 2 * (self.size + (0 if kept is None else int(kept.sum()))))
        return kept

    def _rewrite(self, keep) -> None:
        """The index and frames again with the candidates ``keep(keys, ids)`` says, in the same order, in place.

        Each frame is read (its index entries and its pickled records) before its survivors are written, and
        they are written at or before where it began: the survivors of a frame are some of its entries, and a
        frame of fewer records pickles to no more bytes (a LAS chunk's numpy records, an Arrow batch's
        columns). A compaction therefore never takes more disk than the spill already holds, whatever its
        size (written beside the old files it would take up to twice). A frame that did pickle larger waits
        in memory until the reads have passed the room it needs. A failure part way leaves the spill
        unusable (``broken``): the run's caller then reads again (a full disk: two reads), as after any
        failed write of the spill."""
        self.flush()
        self.broken = True
        first = min((offset for _, offset in self.starts.values()), default=0)
        reader = open(self.frames_path, "rb")
        fd = self.frames.fileno()
        pending: list[bytes] = []  # pickled frames waiting for the reads to pass the room they need
        try:
            reader.seek(first)
            starts, ends, at_key, at_frame, count, read = {}, {}, 0, first, 0, 0

            def put(room: int) -> None:  # write what waits, while it fits below ``room`` (what is read)
                nonlocal at_frame
                while pending and at_frame + len(pending[0]) <= room:
                    blob = pending.pop(0)
                    staging.verify(self.frames_path)
                    try:
                        staging.pwrite_all(fd, blob, at_frame, self.frames_path)
                    finally:
                        staging.mark(self.frames_path, fd)
                    at_frame += len(blob)

            for ordinal in self.starts:
                src = self.sources[ordinal]
                starts[ordinal] = (at_key, at_frame + sum(map(len, pending)))
                end = self.ends.get(ordinal, self.size)
                while read < end:
                    n, state = pickle.load(reader)
                    k, i = self.keys.read(read, n), self.ids.read(read, n)
                    read += n
                    at = np.flatnonzero(keep(k, i))
                    if len(at):
                        self.keys.write_at(at_key, k[at])
                        self.ids.write_at(at_key, i[at])
                        at_key += len(at)
                        if state is not None:
                            state = src.spill_state(src.restore(state), at)
                        pending.append(pickle.dumps((len(at), state), protocol=pickle.HIGHEST_PROTOCOL))
                        count += 1
                    put(reader.tell())
                if ordinal in self.ends:
                    ends[ordinal] = at_key
            put(1 << 62)  # everything is read: what still waits goes after what is written
            self.keys.truncate(at_key)
            self.ids.truncate(at_key)
            staging.verify(self.frames_path)
            try:
                self.frames.truncate(at_frame)
                self.frames.seek(0, os.SEEK_END)
            finally:
                staging.mark(self.frames_path, fd)
        finally:
            reader.close()
        self.starts, self.ends = starts, ends
        self.frame_count = count
        self.broken = False

    def frames_of(self, src):
        """(keys, ids, chunk) of every spilled frame of ``src``, in input order."""
        self._end_source()
        if src.ordinal not in self.starts:
            return
        for keys, ids, state in self._frames(src.ordinal):
            yield keys, ids, src.restore(state)

    def _frames(self, ordinal: int):
        """(keys, ids, spill state) of every frame of source ``ordinal``, in input order (the current
        source's up to what it has spilled so far)."""
        first, offset = self.starts[ordinal]
        end = self.ends.get(ordinal, self.size)
        self.frames.flush()
        with open(self.frames_path, "rb") as f:
            f.seek(offset)
            while first < end:
                n, state = pickle.load(f)
                keys, ids = next(self.index(first, first + n, n))
                yield keys, ids, state
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
                stack.callback(staging.discard_file, self.frames_path)
        if keep:  # another process reads them now (a Dask unit's spill), and may remove them: no longer ours
            for path in (self.keys.path, self.ids.path, self.frames_path):
                staging.unmark(path)

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        # a failure reading files that someone else changed is told as such (before close() forgets them)
        what = staging.changed(self.folder) if isinstance(exc, Exception) and not isinstance(
            exc, (TempDataChanged, Interrupted)) else None
        self.close()
        if what is not None:
            raise TempDataChanged(what, self.folder) from None

