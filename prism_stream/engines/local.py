"""The local engine: the core's passes over whole sources on this machine.

Where the input's size is known up front it is read once: pass one
(:func:`..core.passes.scan_candidates`) decodes every attribute, counts the
colors and keeps in a temporary :class:`Spill` only the points that may still
be selected; the cutoffs and pass two read the spill. Otherwise (a query's
result, ``--flag``, ``--reads two``...) it is read twice: pass one
(:func:`..core.passes.scan`) counts colors and caches each point's bin key
(4 bytes a point), so the cutoff scan and pass two never decode colors
again. Memory holds the dense per-key tables (at most 2^24 keys), one chunk
and the heaps; it does not grow with the input.

The SQL engine runs :func:`execute` too, over a query's result.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import time

import numpy as np

from ..core.candidates import CandidateFilter
from ..core.cutoffs import Rules, cutoffs_by_groups, find_cutoffs
from ..core.histogram import Histogram, SourceScan, Tally, source_scan
from ..core.passes import scan, scan_candidates, scan_held, select
from ..core import ranks as ranking
from ..core import kernels
from ..core.kernels import ID_SHIFT
from ..core.warm import warm_up
from ..core.quotas import solve
from ..core.selection import Selector, held_mask
from ..errors import UsageError
from ..formats import check_sink, extension, open_sink
from ..formats.parquet import check_selection_apart, own_selection
from ..formats.reorder import reorder_by
from ..run import remote, staging
from ..run.inputs import open_sources
from ..run.memory import release_memory
from ..run.outputs import Layout
from ..run.progress import Progress, notice_compiling, say
from ..run.request import Request
from ..run.spill import Spill, SpillFull, compact_mark, spill_history, spill_refusal
from ..run.staging import ArrayFile
from ..run.tempspace import TempForecast, forecast
from ..run.summary import Summary, peak_rss_bytes, provenance, summarize, warn_about

MEMORY_POINTS = 1 << 20  # inputs of at most this many points are held in memory (no numba loop loads)


class KeyCache(ArrayFile):
    """Every point's bin key, in input order (the two-read path's cache: 4 bytes a point)."""

    def __init__(self, folder: str):
        super().__init__(folder, "keys.u32", np.uint32)


class CachedTally(Tally):
    """One source's keys, counted into the run's shared dense histogram and appended to the key cache."""

    def __init__(self, dense: np.ndarray, cache: KeyCache):
        self.dense = dense
        self.cache = cache
        self.base = cache.size  # where this source's keys start in the cache

    def count(self, spec, r, g, b, shift):
        keys = spec.keys(r, g, b, shift, counts=self.dense)
        self.cache.append(keys)
        return keys

    def refile(self, n):
        moved = self.cache.read(self.base, n).copy()
        np.subtract.at(self.dense, moved, 1)
        self.dense[0] += n
        self.cache.overwrite_zero(self.base, n)

    def histogram(self):
        return None  # the run's histogram is the shared dense one


def one_read_refusal(sources, request: Request) -> str | None:
    """Why a run of these options reads its input twice (None: once, with a candidate spill)."""
    if request.reads == "two":
        return "--reads two"
    if request.flag is not None:
        return "--flag writes every point"
    return spill_refusal(sources)


def sample(inputs, output: str | None = None, request: Request | None = None, **options) -> Summary:
    """Sample ``inputs`` into ``output`` with PRISM; return the run's summary.

    Parameters
    ----------
    inputs : str or list of str
        Files, globs or folders; together they are one cloud.
    output : str or None
        ``.parquet``, ``.las``, ``.laz`` or ``.ply``; a folder for directory
        mode (one output per input); None runs pass one and the solve only
        (a plan), writing nothing.
    request : Request, optional
        Every option at once; ``**options`` are :class:`Request` fields
        (``ratio=0.01``, ``seed=3``, ``quant_bits=2``, ...) and override it.

    Directory mode: when ``output`` is a directory (it exists, or ends with
    a path separator), each input file gets its own output, mirroring the
    input tree; a directory input then means every readable file under it.
    """
    request = Request.of(request, **options)
    layout = Layout.of(inputs, output, request.output_format, request.overwrite)
    _refuse_by_name(layout, request)
    if request.per_file:
        if not layout.directory:
            raise UsageError("--per-file needs directory mode (an output folder)")
        with _opened(layout, request) as sources:  # every file's refusals before the first file is sampled
            refuse_outputs(layout, sources, request)
        return _per_file(layout, request)
    t0 = time.perf_counter()
    sources = open_sources(layout.files, **request.open_options(), copies_to=request.temp_dir)
    try:
        refuse_outputs(layout, sources, request)
        if not held_in_memory(sources, request):
            notice_compiling(request.progress)  # before the loading thread imports numba: never two at once
            warm_up()  # the numba loops load while the first chunk is decoded
        with staging.work_dir(request.temp_dir) as tmp:
            return execute(sources, layout, request, tmp, [remote.absolute(f) for f in layout.files], t0=t0)
    finally:
        for s in sources:
            s.close()


def say_plan(plan) -> None:
    """The solve, under --verbose."""
    k = f", K = {plan.k}" if plan.k is not None else ""
    target = f"{plan.target:,}" if plan.target is not None else "-"
    say(f"solve: N = {plan.points:,}, {plan.bins:,} bins, T = {target}{k}; keeps {plan.kept:,}")


def _refuse_by_name(layout: Layout, request: Request) -> None:
    if request.order == "rank":
        for path in layout.outputs():
            if extension(path) == ".copc.laz":
                raise UsageError("--order rank cannot apply to COPC output: COPC orders its points by octree "
                                 "node (write .laz, .las, .parquet or .ply for a progressive file"
                                 + ("; in directory mode, --format laz" if layout.directory else "") + ")", path)


def refuse_outputs(layout: Layout, sources, request: Request) -> None:
    """What a writer would refuse of each output, from the options and the inputs' headers: before a point
    is decoded, naming the output as the user gave it."""
    if layout.directory:
        check_selection_apart(request.selection, sources)
    for path, members in layout.planned(sources):
        check_sink(path, members, flag=request.flag, geometry=request.geometry, columns=request.columns,
                   selection=_selection(layout, request, members), grid=request.las_grid)


def _selection(layout: Layout, request: Request, members) -> tuple | None:
    """--keep/--drop for one output: as given, or in directory mode the names its input has."""
    return own_selection(request.selection, members[0]) if layout.directory else request.selection


@contextlib.contextmanager
def _opened(layout: Layout, request: Request):
    sources = open_sources(layout.files, **request.open_options(), copies_to=request.temp_dir)
    try:
        yield sources
    finally:
        for s in sources:
            s.close()


def check_run(inputs, output: str, request: Request) -> Layout:
    """Refuse what a run of ``request`` from ``inputs`` into ``output`` would refuse before pass one, writing
    nothing (``--plan`` given the run's OUTPUT); return its layout."""
    layout = Layout.of(inputs, output, request.output_format, request.overwrite)
    _refuse_by_name(layout, request)
    if request.per_file and not layout.directory:
        raise UsageError("--per-file needs directory mode (an output folder)")
    with _opened(layout, request) as sources:
        refuse_outputs(layout, sources, request)
    return layout


def rank(inputs, output: str, request: Request | None = None, column: str = "prism_rank", **options) -> Summary:
    """Write the points of ``inputs`` with their PRISM rank in ``column``: the points of rank < T are the exact
    sample for T (:mod:`..core.ranks`).

    Every point by default; ``ratio=R`` or ``count=T`` keeps only the points
    of rank < T (the sample for that target, ranked); ``order="rank"`` writes
    them in rank order (a progressive file). Exact mode only.
    """
    return sample(inputs, output, request, rank=column, **options)


def plan(inputs, request: Request | None = None, **options) -> Summary:
    """Pass one and the solve only: what a run would keep, writing nothing."""
    return sample(inputs, None, request, **options)


def execute(sources, layout: Layout, request: Request, tmp: str, inputs: list, *, t0: float,
            no_points: str = "the input has no points; the output is empty", **more_provenance) -> Summary:
    """Both passes over ``sources`` into the layout's outputs, the key cache in ``tmp``.

    ``inputs`` are what the summary names as the inputs; ``layout.output``
    None stops after the solve. A source whose count is unknown (a query's
    result) learns it in pass one.
    """
    seconds: dict = {}
    if held_in_memory(sources, request):
        return _in_memory(sources, layout, request, inputs, t0, seconds, no_points, more_provenance)
    notice_compiling(request.progress)
    refusal = one_read_refusal(sources, request)  # a plan says how a run would read
    temp = temp_forecast(sources, layout, request, tmp)  # None only where refusal says why (a query's result)
    if layout.output is None:
        if refusal is None:  # the run's own candidate filter over the colors: the spill it reports is the run's
            with Spill(tmp, records=False) as spill:
                return _one_read(sources, layout, request, spill, tmp, inputs, t0, seconds, no_points,
                                 more_provenance, temp)
    elif temp is not None:
        if refusal is None and not temp.one_read_fits:
            refusal = temp.too_big_for_one_read()
        if refusal is not None:
            temp.refuse_two_reads()  # before pass one: the key cache would not fit either
    if refusal is None:
        try:
            with Spill(tmp, budget=temp.budget) as spill:
                return _one_read(sources, layout, request, spill, tmp, inputs, t0, seconds, no_points,
                                 more_provenance, temp)
        except SpillFull as full:
            refusal = str(full) or "the spill ran out of temporary space"
            temp = temp_forecast(sources, layout, request, tmp)  # the spill's room is free again
            temp.refuse_two_reads()
            t0 = time.perf_counter()
    return _two_reads(sources, layout, request, tmp, inputs, t0, seconds, no_points, more_provenance, refusal,
                      temp)


def temp_forecast(sources, layout: Layout, request: Request, tmp: str) -> TempForecast | None:
    """The run's temporary disk, from the headers (None when a source's size is unknown: a query's result)."""
    if any(s.count is None for s in sources):
        return None
    return forecast(sources, request.options, os.path.dirname(tmp), layout.output, chunk_size=request.chunk_size,
                    rank=request.rank is not None)


def memory_points() -> int:
    """Inputs of at most this many points are held in memory (``PRISM_STREAM_MEMORY_POINTS``; 0: never)."""
    value = os.environ.get("PRISM_STREAM_MEMORY_POINTS", "")
    try:
        return max(0, int(value)) if value.strip() else MEMORY_POINTS
    except ValueError:
        raise UsageError(f"PRISM_STREAM_MEMORY_POINTS must be a number of points, not {value!r}") from None


def held_in_memory(sources, request: Request) -> bool:
    """Whether this run holds its input in memory: a small input of known size, ``--reads auto``."""
    if request.reads != "auto":
        return False
    if any(s.count is None for s in sources) or not all(getattr(s, "spills", False) for s in sources):
        return False
    limit = memory_points()
    return limit > 0 and sum(s.count for s in sources) <= limit


def _in_memory(sources, layout, request, inputs, t0, seconds, no_points, more_provenance) -> Summary:
    """A small input, read once and held in memory, with numpy alone (the numba loops never load): every
    chunk with its keys, the histogram, the solve, and each bin's q_b smallest priorities by one sort."""
    options = request.options
    total = sum(s.count for s in sources)
    with layout.transaction():
        scans: list[SourceScan] = []
        held: dict = {}
        with Progress("pass 1/2 read (in memory)", total, request.progress) as bar:
            for src in sources:
                bar.at(src.path, len(sources))
                unit_scan, held[src.ordinal] = scan_held(src.whole(), options.spec, options.color_depth,
                                                         request.chunk_size, bar)
                scans.append(source_scan(src, unit_scan.points, unit_scan.decision, unit_scan.max_value))
        keys = np.concatenate([k for src in sources for _, k in held[src.ordinal]] or [np.zeros(0, np.uint32)])
        seconds["scan"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        plan = solve(Histogram.from_keys(keys), options, tuple(s.as_dict() for s in scans))
        say_plan(plan)
        seconds["solve"] = time.perf_counter() - t1
        caught = warn_about(plan, no_points)
        why = {"reads": 1, "why": f"a small input (at most {memory_points():,} points) is held in memory"}
        if layout.output is None:
            seconds["total"] = time.perf_counter() - t0
            return summarize(plan, inputs, None, seconds, caught, **why)
        t3 = time.perf_counter()
        ids = np.concatenate([np.uint64((src.ordinal << ID_SHIFT) | c.start) + np.arange(len(k), dtype=np.uint64)
                              for src in sources for c, k in held[src.ordinal]] or [np.zeros(0, np.uint64)])
        keep = held_mask(plan, keys, ids)
        ranks = held_ranks(plan, request, keys[keep], ids[keep], seconds) if request.rank is not None else None
        del keys, ids
        starts = dict(zip((s.ordinal for s in sources), np.cumsum([0] + [s.points for s in scans])))

        def masked(src, bar):
            at = starts[src.ordinal]
            for chunk, k in held[src.ordinal]:
                yield chunk, keep[at:at + len(k)]
                at += len(k)
                bar.update(len(k))

        caught += write_outputs(plan, layout, sources, request, more_provenance, "pass 2/2 write", total, masked,
                                ranks)
        seconds["select"] = time.perf_counter() - t3
    seconds["total"] = time.perf_counter() - t0
    return summarize(plan, inputs, layout.output, seconds, caught, layout.published, **why,
                     **_rank_facts(request, ranks))


def _reads(path: str, reason: str | None, spill: Spill | None = None) -> dict:
    """What the summary says about how the input was read."""
    d = {"reads": 1 if path == "one" else 2, "why": reason or "the input's size is known up front"}
    if spill is not None:
        d["spill_points"] = spill.size
        d["spill_bytes"] = spill.bytes
        d.update(spill_history(spill))
    return d


def _one_read(sources, layout, request, spill, tmp, inputs, t0, seconds, no_points, more_provenance,
              temp: TempForecast) -> Summary:
    """Pass one reads every attribute once and spills the candidates; pass two streams the spill.

    A plan (no output) runs pass one over the colors alone with a spill of the index alone, to report
    how much the run would spill."""
    options = request.options
    dry = layout.output is None
    spec = options.spec
    chunk = request.chunk_size
    declared = sum(s.count for s in sources)
    candidates = CandidateFilter(spec, options, declared)
    spill.limit(compact_mark(temp.spill_bound))
    with layout.transaction():
        scans: list[SourceScan] = []
        with Progress("pass 1/2 histogram + candidates", declared, request.progress) as bar:
            try:
                for src in sources:
                    bar.at(src.path, len(sources))
                    unit_scan = scan_candidates(src.whole(), candidates, options.color_depth, chunk, spill, bar,
                                                colors_only=dry)
                    scans.append(source_scan(src, unit_scan.points, unit_scan.decision, unit_scan.max_value))
                spill.flush()
            except OSError as exc:
                if exc.errno not in staging.OUT_OF_ROOM:
                    raise
                raise SpillFull() from None
        seconds["scan"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        dense = candidates.counts()
        del candidates  # its heaps (a quarter GiB over millions of bins) go before the solve needs room,
        release_memory()  # and pass one's decoded batches, which Arrow's and glibc's allocators would keep
        histogram = Histogram.from_dense(dense)
        del dense
        plan = solve(histogram, options, tuple(s.as_dict() for s in scans))
        del histogram
        say_plan(plan)
        seconds["solve"] = time.perf_counter() - t1
        caught = warn_about(plan, no_points)
        if dry:
            seconds["total"] = time.perf_counter() - t0
            forecast_now = forecast(sources, options, temp.folder, plan=plan, chunk_size=chunk)
            run = {"spill_points_run": spill.size, "spill_bytes_run": forecast_now.spill_bytes(spill.size,
                                                                                             spill.frame_count),
                   **{f"{k}_run": v for k, v in spill_history(spill).items()}}
            return summarize(plan, inputs, None, seconds, caught, **_reads("one", "a plan: the run's candidate filter "
                                                                          "over the colors"),
                             temp={**forecast_now.as_dict(), **run, "start": temp.as_dict()})

        t2 = time.perf_counter()
        rules = Rules(plan)

        def feed(finder):
            for keys, ids in spill.index():
                finder.add_ids(keys, ids)

        cutoffs = cutoffs_by_groups(rules, feed)
        rules.drop_caps()
        release_memory()  # the cutoff scan's heaps
        seconds["cutoffs"] = time.perf_counter() - t2

        t3 = time.perf_counter()
        selector = Selector(plan, cutoffs, rules)

        def spilled(src, bar):
            for keys, ids, pts in spill.frames_of(src):
                yield pts, selector.mask_ids(keys, ids)
                bar.update(len(keys))

        def kept():
            for keys, ids in spill.index():
                m = selector.mask_ids(keys, ids)
                yield keys[m], ids[m]

        ranks = rank_points(plan, request, tmp, kept, seconds)
        caught += write_outputs(plan, layout, sources, request, more_provenance, "pass 2/2 select (spill)",
                                spill.size, spilled, ranks)
        seconds["select"] = time.perf_counter() - t3
    seconds["total"] = time.perf_counter() - t0
    return summarize(plan, inputs, layout.output, seconds, caught, layout.published, **_reads("one", None, spill),
                     **_rank_facts(request, ranks), temp=temp.as_dict())


def _two_reads(sources, layout, request, tmp, inputs, t0, seconds, no_points, more_provenance, refusal,
               temp: TempForecast | None) -> Summary:
    """Pass one counts colors into a key cache; the cutoff scan and pass two read the keys back."""
    options = request.options
    spec = options.spec
    chunk = request.chunk_size
    reads = _reads("two", refusal)
    if temp is not None:
        reads["temp"] = temp.as_dict()
    with layout.transaction(), KeyCache(tmp) as cache:
        dense = np.zeros(spec.key_space, dtype=np.int64)
        scans: list[SourceScan] = []
        offsets = []
        declared = None if any(s.count is None for s in sources) else sum(s.count for s in sources)
        with Progress("pass 1/2 histogram", declared, request.progress) as bar:
            for src in sources:
                bar.at(src.path, len(sources))
                if layout.output is None:
                    cache.clear()  # a plan needs the current file's keys alone (to refile them)
                offsets.append(cache.size)
                unit_scan = scan(src.whole(), spec, options.color_depth, chunk, CachedTally(dense, cache), bar)
                if src.count is None:
                    src.count = unit_scan.points
                scans.append(source_scan(src, unit_scan.points, unit_scan.decision, unit_scan.max_value))
        seconds["scan"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        plan = solve(Histogram.from_dense(dense), options, tuple(s.as_dict() for s in scans))
        say_plan(plan)
        del dense
        release_memory()  # pass one's decoded batches (see _one_read)
        seconds["solve"] = time.perf_counter() - t1
        caught = warn_about(plan, no_points)
        if layout.output is None:
            if temp is not None:  # what a run would spill, now that the histogram is known
                reads["temp"] = forecast(sources, options, os.path.dirname(tmp), plan=plan, chunk_size=chunk).as_dict()
            return summarize(plan, inputs, None, seconds, caught, **reads)

        t2 = time.perf_counter()
        rules = Rules(plan)
        with Progress("cutoffs", cache.size, request.progress and len(rules.caps) > 0) as bar:
            cutoffs = find_cutoffs(rules, sources, chunk, lambda src, a, n: cache.read(offsets[src.ordinal] + a, n),
                                   bar)
        rules.drop_caps()
        release_memory()  # the cutoff scan's heaps
        seconds["cutoffs"] = time.perf_counter() - t2

        t3 = time.perf_counter()
        selector = Selector(plan, cutoffs, rules)

        def reread(src, bar):
            base = offsets[src.ordinal]
            return select(src.whole(), plan, selector=selector, chunk_size=chunk, bar=bar,
                          keys_of=lambda a, n: cache.read(base + a, n))

        def kept():
            for src in sources:
                for a in range(0, src.count, chunk):
                    keys = cache.read(offsets[src.ordinal] + a, min(chunk, src.count - a))
                    at = np.flatnonzero(selector.mask(keys, src.ordinal, a))
                    yield keys[at], np.uint64((src.ordinal << ID_SHIFT) | a) + at.astype(np.uint64)

        ranks = rank_points(plan, request, tmp, kept, seconds)
        caught += write_outputs(plan, layout, sources, request, more_provenance, "pass 2/2 select", cache.size,
                                reread, ranks)
        seconds["select"] = time.perf_counter() - t3
    seconds["total"] = time.perf_counter() - t0
    return summarize(plan, inputs, layout.output, seconds, caught, layout.published, **reads,
                     **_rank_facts(request, ranks))


class Ranks:
    """The kept points' ranks in input order (a temporary file), read as pass two writes them."""

    def __init__(self, column: str, order: str, values: ArrayFile, method: str):
        self.column = column
        self.order = order
        self.values = values
        self.method = method
        self.at = 0

    def next(self, n: int) -> np.ndarray:
        out = self.values.read(self.at, n)
        self.at += n
        return out

    def facts(self) -> dict:
        return {"column": self.column, "order": self.order, "points": self.values.size, "method": self.method}


class _Held:
    """Ranks held in memory, read as an :class:`ArrayFile` is."""

    def __init__(self, values: np.ndarray):
        self.values = values
        self.size = len(values)

    def read(self, at: int, n: int) -> np.ndarray:
        return self.values[at:at + n]


def held_ranks(plan, request: Request, keys: np.ndarray, ids: np.ndarray, seconds: dict) -> Ranks:
    """The ranks of a sample held in memory (its points' bin keys and ids, in input order), with numpy alone:
    the same two sorts :func:`rank_points` makes on its files."""
    t = time.perf_counter()
    order = ranking.BinOrder(plan)
    place = order.place[np.searchsorted(plan.keys, keys)]
    priority = kernels.priorities_of_np(np.ascontiguousarray(ids, dtype=np.uint64), order.seed_mix)
    values = ranking.rank_sample(place, priority, plan.bins)
    seconds["rank"] = time.perf_counter() - t
    return Ranks(request.rank, request.order, _Held(values), "numpy")


def rank_points(plan, request: Request, tmp: str, kept, seconds: dict) -> Ranks | None:
    """The rank of every point ``kept()`` yields (as (bin keys, ids), in input order), when the run ranks.

    Up to :data:`..core.ranks.IN_MEMORY` points are ranked with numpy; more with
    DuckDB, which spills its sort to ``tmp``. Either way the ranks land in a
    temporary file that pass two reads in step with the points it writes.
    """
    if request.rank is None:
        return None
    t = time.perf_counter()
    order = ranking.BinOrder(plan)
    place = ArrayFile(tmp, "rank.place", np.uint32)
    priority = ArrayFile(tmp, "rank.priority", np.uint64)
    out = ArrayFile(tmp, "rank.values", np.int64)
    with Progress("ranks", plan.kept, request.progress) as bar:
        for keys, ids in kept():
            p, q = order.of(keys, ids)
            place.append(p)
            priority.append(q)
            bar.update(len(keys))
    n = place.size
    if n <= ranking.IN_MEMORY:
        method = "numpy"
        out.append(ranking.rank_sample(place.read(0, n), priority.read(0, n), plan.bins))
    else:
        method = "duckdb"
        step = 1 << 20

        def batches():
            for a in range(0, n, step):
                yield place.read(a, min(step, n - a)), priority.read(a, min(step, n - a))

        for values in ranking.rank_sample_duckdb(batches, tmp, threads=request.workers):
            out.append(values)
    place.discard()
    priority.discard()
    if out.size != plan.kept:
        raise AssertionError(f"ranked {out.size} points, the plan keeps {plan.kept}")
    seconds["rank"] = time.perf_counter() - t
    return Ranks(request.rank, request.order, out, method)


def _rank_facts(request: Request, ranks: Ranks | None) -> dict:
    return {} if ranks is None else {"rank": ranks.facts()}


def write_outputs(plan, layout: Layout, sources, request: Request, more_provenance: dict, label: str, total: int,
                  masked, ranks: Ranks | None = None) -> list[str]:
    """Pass two's writing, for either path: each output's sink fed with ``masked(source, bar)``'s
    (chunk, keep mask) pairs of its sources, and their ranks when the run ranks (then reordered by rank
    with ``--order rank``); checked against the plan and published. Returns what the sinks noted
    (attributes a format changed or left out, already warned)."""
    if ranks is not None:
        more_provenance = {**more_provenance, "rank": {"column": ranks.column, "order": ranks.order}}
    prov = provenance(plan, layout.files, **more_provenance)
    layout.begin()
    kept = 0
    notes: list[str] = []
    with Progress(label, total, request.progress) as bar:
        for target, members in layout.targets(sources):
            with open_sink(target, members, prov, flag=request.flag, geometry=request.geometry,
                           rank=request.rank, columns=request.columns, grid=request.las_grid,
                           selection=_selection(layout, request, members)) as sink:
                for src in members:
                    bar.at(src.path, len(sources))
                    for pts, mask in masked(src, bar):
                        n = int(np.count_nonzero(mask))
                        if ranks is None:
                            sink.write(pts, mask)
                        else:
                            sink.write(pts, mask, ranks=ranks.next(n))
                        kept += n
            notes += sink.notes
            if ranks is not None and ranks.order == "rank":
                with Progress("rank order", sink.written, request.progress) as order_bar:
                    reorder_by(target, ranks.column, sink.written, order_bar.update)
    if kept != plan.kept:
        raise AssertionError(f"selected {kept} points, the plan keeps {plan.kept}")
    layout.publish()
    return notes


def _per_file(layout: Layout, request: Request) -> Summary:
    """Directory mode with an independent solve per file; all outputs published together."""
    t0 = time.perf_counter()
    runs = []
    one = dataclasses.replace(request, overwrite=True, per_file=False, output_format=None)
    with layout.transaction():
        layout.begin()
        for i, f in enumerate(layout.files):
            runs.append(sample(f, layout.stage(i), one))
        layout.publish()
    options = request.options
    points = sum(r.points for r in runs)
    kept = sum(r.kept for r in runs)
    for r, final in zip(runs, layout.published):
        r.output = final
        r.outputs = [final]
    return Summary(
        inputs=[remote.absolute(f) for f in layout.files], output=remote.absolute(layout.output), points=points,
        bins=None, target=(sum(r.target for r in runs) if options.k is None else None), kept=kept,
        ratio_achieved=(kept / points) if points else 0.0, rule=options.rule, k=None, extra=None,
        seed=int(options.seed), options=options.as_dict(), sources=[s for r in runs for s in r.sources],
        seconds={**{step: round(sum(r.seconds.get(step, 0.0) for r in runs), 4)
                    for step in sorted({step for r in runs for step in r.seconds} - {"total"})},
                 "total": round(time.perf_counter() - t0, 4)},  # each step summed over the files' runs
        peak_rss_bytes=peak_rss_bytes(),
        plan={"per_file": [r.as_dict() for r in runs]}, warnings=[w for r in runs for w in r.warnings],
        outputs=list(layout.published),
    )
