"""How a local run reads its input: the three :class:`.pipeline.Reads` strategies.

- :class:`Held`: a small input of known size is read once and held in memory;
  numpy alone selects it (the numba loops never load).
- :class:`Spilled`: an input of known size is read once. Pass one
  (:func:`..core.passes.scan_candidates`) decodes every attribute, counts the
  colors and keeps in a temporary :class:`..run.spill.Spill` only the points that
  may still be selected; the cutoffs and pass two read the spill.
- :class:`Reread`: otherwise (a query's result, ``--flag``, ``--reads two``...)
  the input is read twice. Pass one (:func:`..core.passes.scan`) counts colors
  and caches each point's bin key (4 bytes a point), so the cutoff scan and
  pass two never decode colors again.

Memory holds the dense per-key tables (at most 2^24 keys), one chunk and the
heaps; it does not grow with the input (:class:`Held` aside, which is bounded
by its size limit).
"""

from __future__ import annotations

import hashlib
import os

import numpy as np

from ..core.candidates import CandidateFilter
from ..core.cutoffs import Rules, cutoffs_by_groups, find_cutoffs
from ..core.histogram import Histogram, Tally, source_scan
from ..core.kernels import ID_SHIFT
from ..core.passes import scan, scan_candidates, scan_held, select
from ..core.selection import Selector, held_mask
from ..errors import CorruptInput
from ..core.sparse import mark, marks_for, sparse_zeros, table_runs
from ..evaluate.cloud import coordinates
from ..run import staging
from ..run.memory import release_memory
from ..run.progress import Progress
from ..run.spill import Spill, SpillFull, compact_mark, spill_history
from ..run.staging import ArrayFile
from ..run.tempspace import TempForecast, forecast
from .pipeline import Reads, Run
from .ranking import held_ranks
from .spatial import IdSelector


class KeyCache(ArrayFile):
    """Every point's bin key, in input order (the two-read path's cache: 4 bytes a point)."""

    def __init__(self, folder: str):
        super().__init__(folder, "keys.u32", np.uint32)


class CachedTally(Tally):
    """One source's keys, counted into the run's shared dense histogram and appended to the key cache."""

    def __init__(self, dense: np.ndarray, marks: np.ndarray, cache: KeyCache):
        self.dense, self.marks = dense, marks  # marks: the blocks of the table a key was counted in
        self.cache = cache
        self.base = cache.size  # where this source's keys start in the cache

    def count(self, spec, r, g, b, shift):
        keys = spec.counted_keys(r, g, b, shift, self.dense, self.marks)
        self.cache.append(keys)
        return keys

    def refile(self, n):
        moved = self.cache.read(self.base, n).copy()
        np.subtract.at(self.dense, moved, 1)
        self.dense[0] += n
        mark(self.marks, [0])
        self.cache.overwrite_zero(self.base, n)

    def histogram(self):
        return None  # the run's histogram is the shared dense one


def read_facts(reads: int, why: str | None, spill: Spill | None = None) -> dict:
    """What the summary says about how the input was read."""
    d = {"reads": reads, "why": why or "the input's size is known up front"}
    if spill is not None:
        d["spill_points"] = spill.size
        d["spill_bytes"] = spill.bytes
        d.update(spill_history(spill))
    return d


def _selector(plan, rules: Rules, cutoffs) -> Selector:
    """Pass two's keep rule, once the cutoff scan's heaps are let go."""
    rules.drop_caps()
    release_memory()  # the cutoff scan's heaps
    return Selector(plan, cutoffs, rules)


def _facts(src, unit_scan) -> dict:
    return source_scan(src, unit_scan.points, unit_scan.decision, unit_scan.max_value).as_dict()


class Held(Reads):
    """A small input, read once and held in memory, with numpy alone: every chunk with its keys, the histogram,
    the solve, and each bin's q_b smallest priorities by one sort."""

    label = "pass 2/2 write"
    cutoff_step = None  # the selection is one sort, timed with pass two
    space_reads = 0  # the points are in memory

    def __init__(self, sources, limit: int):
        self.sources = sources
        self.limit = limit
        self.held: dict = {}

    def scan(self, run: Run) -> tuple:
        facts = []
        with Progress("pass 1/2 read (in memory)", self.total(), run.request.progress) as bar:
            for src in self.sources:
                bar.at(src.path, len(self.sources))
                unit_scan, self.held[src.ordinal] = scan_held(src.whole(), run.options.spec, run.options.color_depth,
                                                              run.request.chunk_size, bar)
                facts.append(_facts(src, unit_scan))
        self.points = [f["points"] for f in facts]
        self.keys = np.concatenate([k for src in self.sources for _, k in self.held[src.ordinal]]
                                   or [np.zeros(0, np.uint32)])
        return tuple(facts)

    def histogram(self) -> Histogram:
        return Histogram.from_keys(self.keys)

    def facts(self, run: Run, plan) -> dict:
        return read_facts(1, f"a small input (at most {self.limit:,} points) is held in memory")

    def total(self) -> int:
        return sum(s.count for s in self.sources)

    def select(self, run: Run, plan, rules) -> None:
        self.ids = np.concatenate([np.uint64((src.ordinal << ID_SHIFT) | c.start) + np.arange(len(k), dtype=np.uint64)
                                   for src in self.sources for c, k in self.held[src.ordinal]]
                                  or [np.zeros(0, np.uint64)])
        self.keep = held_mask(plan, self.keys, self.ids)
        self.starts = dict(zip((s.ordinal for s in self.sources), np.cumsum([0] + self.points)))

    def ranks(self, run: Run, plan):
        return held_ranks(plan, run, self.keys[self.keep], self.ids[self.keep])

    def kept(self):
        yield self.keys[self.keep], self.ids[self.keep]

    def every_point(self):
        at = 0
        for src in self.sources:
            for chunk, k in self.held[src.ordinal]:
                yield src.path, coordinates(chunk, src.path), k, self.ids[at:at + len(k)]
                at += len(k)

    def keep_ids(self, ids) -> None:
        if hasattr(ids, "read"):  # a large target's ids, in a temporary file (a held input is small: read whole)
            ids = ids.read(0, ids.size)
        self.keep = np.isin(self.ids, ids)

    def write(self, run: Run, plan, ranks) -> list[str]:
        del self.keys, self.ids
        return super().write(run, plan, ranks)

    def masked(self, src, bar):
        at = self.starts[src.ordinal]
        for chunk, k in self.held[src.ordinal]:
            yield chunk, self.keep[at:at + len(k)]
            at += len(k)
            bar.update(len(k))


class Spilled(Reads):
    """Pass one reads every attribute once and spills the candidates; pass two streams the spill.

    A plan (no output) runs pass one over the colors alone with a spill of the index alone, to report
    how much the run would spill."""

    label = "pass 2/2 select (spill)"

    def __init__(self, sources, temp: TempForecast, tmp: str, dry: bool):
        self.sources = sources
        self.temp = temp
        self.spill = self.files = Spill(tmp, records=False) if dry else Spill(tmp, budget=temp.budget)

    def scan(self, run: Run) -> tuple:
        options = run.options
        declared = sum(s.count for s in self.sources)
        self.candidates = CandidateFilter(options.spec, options, declared)
        self.spill.limit(compact_mark(self.temp.spill_bound))
        facts = []
        with Progress("pass 1/2 histogram + candidates", declared, run.request.progress) as bar:
            try:
                for src in self.sources:
                    bar.at(src.path, len(self.sources))
                    unit_scan = scan_candidates(src.whole(), self.candidates, options.color_depth,
                                                run.request.chunk_size, self.spill, bar)
                    facts.append(_facts(src, unit_scan))
                self.spill.flush()
            except OSError as exc:
                if exc.errno not in staging.OUT_OF_ROOM:
                    raise
                raise SpillFull() from None
        return tuple(facts)

    def histogram(self) -> Histogram:
        histogram = self.candidates.histogram()
        del self.candidates  # its heaps (a quarter GiB over millions of bins) go before the solve needs room,
        release_memory()  # and pass one's decoded batches, which Arrow's and glibc's allocators would keep
        return histogram

    def facts(self, run: Run, plan) -> dict:
        spill = self.spill
        if not run.dry:
            return {**read_facts(1, None, spill), "temp": self.temp.as_dict()}
        now = forecast(self.sources, run.options, self.temp.folder, plan=plan, chunk_size=run.request.chunk_size)
        ran = {"spill_points_run": spill.size, "spill_bytes_run": now.spill_bytes(spill.size, spill.frame_count),
               **{f"{k}_run": v for k, v in spill_history(spill).items()}}
        return {**read_facts(1, "a plan: the run's candidate filter over the colors"),
                "temp": {**now.as_dict(), **ran, "start": self.temp.as_dict()}}

    def rules(self, plan) -> Rules:
        return Rules(plan)

    def select(self, run: Run, plan, rules: Rules) -> None:
        def feed(finder):
            for keys, ids in self.spill.index():
                finder.add_ids(keys, ids)

        self.selector = _selector(plan, rules, cutoffs_by_groups(rules, feed))

    def masked(self, src, bar):
        for keys, ids, pts in self.spill.frames_of(src):
            yield pts, self.selector.mask_ids(keys, ids)
            bar.update(len(keys))

    def kept(self):
        for keys, ids in self.spill.index():
            m = self.selector.mask_ids(keys, ids)
            yield keys[m], ids[m]


def _digest():
    return hashlib.blake2b(digest_size=16)


def _same_places(src, chunks, want: bytes):
    """Pass two's chunks, checked at the end to hold the coordinates the spatial read hashed (``want``): a
    re-run query whose rows of equal colors came in another order passes the bin-key check, but the spatial
    share's ids would then name other points. The output is still staged when this fails."""
    digest = _digest()
    for chunk, mask in chunks:
        digest.update(np.ascontiguousarray(coordinates(chunk, src.path)).tobytes())
        yield chunk, mask
    if digest.digest() != want:
        raise CorruptInput(f"{src.changed}: its coordinates came in another order than in the spatial read",
                           src.path)


class _NoMask:
    """A selector that selects nothing: the spatial read wants the points, not PRISM's mask."""

    @staticmethod
    def mask(keys, ordinal, start):
        return None


NO_MASK = _NoMask()


class Reread(Reads):
    """Pass one counts colors into a key cache; the cutoff scan and pass two read the keys back."""

    def __init__(self, sources, tmp: str, refusal: str | None, temp: TempForecast | None):
        self.sources = sources
        self.tmp = tmp
        self.refusal = refusal
        self.temp = temp
        self.cache = self.files = KeyCache(tmp)
        self.places: dict = {}  # --space over a re-run query: a digest of each source's coordinates, in order

    def scan(self, run: Run) -> tuple:
        options = run.options
        self.dense = sparse_zeros(options.spec.key_space, np.int64)
        self.marks = marks_for(options.spec.key_space)
        facts = []
        self.offsets = []
        declared = None if any(s.count is None for s in self.sources) else sum(s.count for s in self.sources)
        with Progress("pass 1/2 histogram", declared, run.request.progress) as bar:
            for src in self.sources:
                bar.at(src.path, len(self.sources))
                if run.dry:
                    self.cache.clear()  # a plan needs the current file's keys alone (to refile them)
                self.offsets.append(self.cache.size)
                unit_scan = scan(src.whole(), options.spec, options.color_depth, run.request.chunk_size,
                                 CachedTally(self.dense, self.marks, self.cache), bar)
                if src.count is None:
                    src.count = unit_scan.points
                facts.append(_facts(src, unit_scan))
        return tuple(facts)

    def histogram(self) -> Histogram:
        dense, self.dense = self.dense, None
        histogram = Histogram.from_dense(dense, runs=table_runs(self.marks, len(dense)))
        del dense
        release_memory()  # pass one's decoded batches (see Spilled.histogram)
        return histogram

    def facts(self, run: Run, plan) -> dict:
        out = read_facts(2, self.refusal)
        if self.temp is not None:
            out["temp"] = self.temp.as_dict()
            if run.dry:  # what a run would spill, now that the histogram is known
                out["temp"] = forecast(self.sources, run.options, os.path.dirname(self.tmp), plan=plan,
                                       chunk_size=run.request.chunk_size).as_dict()
        return out

    def rules(self, plan) -> Rules:
        return Rules(plan)

    def select(self, run: Run, plan, rules: Rules) -> None:
        self.plan = plan
        self.chunk = run.request.chunk_size
        with Progress("cutoffs", self.cache.size, run.request.progress and len(rules.caps) > 0) as bar:
            cutoffs = find_cutoffs(rules, self.sources, self.chunk,
                                   lambda src, a, n: self.cache.read(self.offsets[src.ordinal] + a, n), bar)
        self.selector = _selector(plan, rules, cutoffs)

    def masked(self, src, bar):
        base = self.offsets[src.ordinal]
        chunks = select(src.whole(), self.plan, selector=self.selector, chunk_size=self.chunk, bar=bar,
                        keys_of=lambda a, n: self.cache.read(base + a, n))
        want = self.places.get(src.ordinal)
        return chunks if want is None else _same_places(src, chunks, want)

    def every_point(self):
        for src in self.sources:
            base = self.offsets[src.ordinal]
            read: list = []  # the chunk's cached keys, read once: select checks them, the scan bins by them

            def keys_of(a, n, base=base):
                read[:] = [self.cache.read(base + a, n)]
                return read[0]

            digest = _digest() if src.reread_may_differ else None
            for chunk, _ in select(src.whole(), self.plan, selector=NO_MASK, chunk_size=self.chunk,
                                   keys_of=keys_of):
                n = len(chunk)
                ids = np.uint64((src.ordinal << ID_SHIFT) | chunk.start) + np.arange(n, dtype=np.uint64)
                xyz = coordinates(chunk, src.path)
                if digest is not None:
                    digest.update(np.ascontiguousarray(xyz).tobytes())
                yield src.path, xyz, read[0], ids
            if digest is not None:
                self.places[src.ordinal] = digest.digest()

    def keep_ids(self, ids) -> None:
        self.selector = IdSelector(ids)

    def kept(self):
        for src in self.sources:
            for a in range(0, src.count, self.chunk):
                keys = self.cache.read(self.offsets[src.ordinal] + a, min(self.chunk, src.count - a))
                at = np.flatnonzero(self.selector.mask(keys, src.ordinal, a))
                yield keys[at], np.uint64((src.ordinal << ID_SHIFT) | a) + at.astype(np.uint64)
