"""The Dask engine: the same two passes, mapped over work units on a dask.distributed cluster.

Every step is one of the pure per-unit functions the local engine is built
from, so the output is the local engine's, row for row:

1. pass one: ``scan`` maps each unit to a sparse histogram; the per-file
   color-depth decision is made from each unit's largest value (a few bytes
   per unit gathered on the driver); the histograms are tree-reduced on the
   cluster and only the global one reaches the driver;
2. the solve runs once on the driver; the plan is sent to every worker;
3. cutoffs: each unit keeps, per capped bin, its smallest priorities at or
   under a bound the cutoff almost surely lies under (so the unit sends
   about q_b/n_b of its points, not all of them); the bottom sets are
   tree-reduced in slot-range partitions; a bin whose bound proves too low
   is redone without a bound, so the cutoffs are exact whatever happens;
4. pass two: each unit writes its own Parquet part (or each LAS/LAZ tile its
   own file) under a temporary name, renamed on success, so a retried task
   simply overwrites its own part; the driver then renames the staging
   folder onto the output, which appears complete or not at all.

Workers re-open sources from a :class:`UnitRef` (path, ordinal, options,
record range): nothing open is ever pickled. Inputs and the output folder
must be visible to every worker under the same paths (a shared filesystem).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import glob
import math
import os
import shutil
import tempfile
import time
import uuid
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from .bins import decided_keys
from . import kernels
from .cutoff import Cutoffs, Rules, merge_bottoms
from .engine import DEFAULT_CHUNK, Summary, provenance, summarize, warn_about
from .errors import CorruptInput, Interrupted, OutputError, OutputExists, PrismError, UsageError
from .formats import expand_inputs, extension, open_source
from .formats.base import AtomicFile, Unit, public_mode
from .formats.las import LasSink, LasSource
from .formats.parquet import output_schema
from .kernels import ID_SHIFT, MAX_RECORDS_PER_SOURCE
from .layout import output_stem
from .plan import Options, Plan, solve
from .scan import Histogram, UnitScan, merge_units, source_scan
from .scan import scan

DEFAULT_UNIT = 1 << 22
FAN_IN = 4
BOTTOMS_PER_REDUCER = 1 << 22  # (slot, priority) pairs one cutoff reducer holds at most: 48 MiB
BOUND_SIGMAS = 8.0  # how far above its expected value a bin's cutoff bound sits
U64_MAX = np.uint64((1 << 64) - 1)
PART_PREFIX = "part-"


class ClusterError(PrismError):
    """The cluster could not run the job (unreachable scheduler, workers dying over and over)."""

    exit_code = 9


# ---------------------------------------------------------------- work units


@dataclass(frozen=True)
class UnitRef:
    """A picklable work unit: records [start, stop) of the source at ``path``, re-opened where it runs."""

    path: str
    ordinal: int
    start: int
    stop: int
    options: tuple = ()  # (name, value) pairs for open_source: threads, rgb_columns

    @property
    def points(self) -> int:
        return self.stop - self.start

    @contextlib.contextmanager
    def opened(self):
        source = open_source(self.path, self.ordinal, **dict(self.options))
        try:
            yield Unit(source, self.start, self.stop)
        finally:
            source.close()


def unit_refs(source, unit_size: int, options: tuple) -> list[UnitRef]:
    """The source's work units (LAZ ranges are whole chunks: see LasSource.units), as picklable refs."""
    return [UnitRef(source.path, source.ordinal, u.start, u.stop, options) for u in source.units(unit_size)]


def _release_memory() -> None:
    """Hand freed memory back to the OS after a task.

    Dask pauses a worker whose process memory passes 80% of its limit, and
    memory that glibc or Arrow's allocator keep after a task looks exactly
    like a leak to it: a small worker would pause for good.
    """
    pa.default_memory_pool().release_unused()
    if _LIBC is not None:
        _LIBC.malloc_trim(0)


def _load_libc():
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.malloc_trim  # noqa: B018 - glibc only
        return libc
    except (OSError, AttributeError):
        return None


_LIBC = _load_libc()


def _reraise_flat(fn):
    """Worker-side task wrapper: PrismError pickles without its path, so send it back with the path in the
    message; then release the task's memory."""

    def run(*args, **kw):
        try:
            return fn(*args, **kw)
        except PrismError as exc:
            raise type(exc)(str(exc)) from None
        finally:
            _release_memory()

    run.__name__ = fn.__name__
    run.__qualname__ = fn.__qualname__
    run.__doc__ = fn.__doc__
    return run


# ---------------------------------------------------------------- pass one (worker side)


@_reraise_flat
def scan_unit(ref: UnitRef, spec, color_depth: str, chunk_size: int) -> UnitScan:
    with ref.opened() as unit:
        return scan(unit, spec, color_depth, chunk_size)


def unit_facts(s: UnitScan) -> tuple:
    return s.ordinal, s.points, s.max_value, s.kind


def decided_histogram(s: UnitScan, source_facts: UnitScan, color_depth: str) -> Histogram:
    """The unit's histogram once its file's depth is decided.

    ``source_facts`` is an empty scan carrying the whole file's largest value
    and kind; merged beside it, :func:`merge_units` applies the file's
    decision to this unit exactly as it would with every unit in hand.
    """
    return merge_units([s, source_facts], color_depth)[0]


@_reraise_flat
def merge_histograms(*parts: Histogram) -> Histogram:
    return Histogram.sum(parts)


# ---------------------------------------------------------------- cutoffs (worker side)

_CACHE: dict = {}


def _rules_of(plan: Plan) -> Rules:
    """The plan's dense rules, built once per worker process (64 MiB at 0 quantization bits)."""
    hit = _CACHE.get("rules")
    if hit is None or hit[0] is not plan:
        _CACHE.pop("rules", None)
        _CACHE["rules"] = hit = (plan, Rules(plan))
    return hit[1]


def _selector_of(plan: Plan, cutoffs: Cutoffs):
    from .select import Selector

    hit = _CACHE.get("selector")
    if hit is None or hit[0] is not plan or hit[1] is not cutoffs:
        _CACHE.pop("selector", None)
        _CACHE["selector"] = hit = (plan, cutoffs, Selector(plan, cutoffs, _rules_of(plan)))
    return hit[2]


def worker_plan(plan: Plan) -> Plan:
    """The plan without its dropped bins: what pass two and the cutoffs need, often far smaller to broadcast.

    Its :class:`Rules` are the full plan's (a bin absent from the plan is
    dropped either way), so the cutoffs and the selection are the same.
    """
    kept = plan.quotas > 0
    return dataclasses.replace(plan, keys=plan.keys[kept], counts=plan.counts[kept], quotas=plan.quotas[kept])


def cutoff_bounds(plan: Plan, sigmas: float = BOUND_SIGMAS) -> np.ndarray:
    """Per capped slot, a priority the bin's cutoff lies under but for a ~``sigmas``-sigma fluke.

    Priorities are uniform 64-bit words, so the number of a bin's n_b points
    under a bound t is Binomial(n_b, t / 2^64); t is set so that this count
    exceeds q_b by ``sigmas`` standard deviations (plus slack for small
    bins). Only an upper bound: :func:`cutoffs` checks it and redoes the bins
    it fails for.
    """
    rules = _rules_of(plan)
    caps = rules.caps.astype(np.float64)
    counts = plan.counts[plan.capped].astype(np.float64)
    if not np.isfinite(sigmas):
        return np.full(len(caps), U64_MAX, dtype=np.uint64)
    want = caps + sigmas * np.sqrt(caps * (1.0 - caps / np.maximum(counts, 1.0))) + sigmas * sigmas
    frac = np.minimum(want / np.maximum(counts, 1.0), 1.0)
    bounds = np.full(len(caps), U64_MAX, dtype=np.uint64)
    low = frac < 0.999
    bounds[low] = (frac[low] * 2.0**64).astype(np.uint64)
    return bounds


@_reraise_flat
def unit_bottoms(ref: UnitRef, plan: Plan, bounds: np.ndarray, chunk_size: int) -> tuple[np.ndarray, np.ndarray]:
    """The unit's smallest priorities per capped bin, at or under the bin's bound: (slot, priority).

    What :class:`CutoffFinder` keeps for a unit, restricted to the bound
    first: the unit's q_b smallest among its priorities under the bound are
    exactly its q_b smallest intersected with "under the bound", and the
    bound leaves about q_b/n_b of the points, so no per-unit heap as large
    as the sample (or as the number of capped bins) is ever allocated.
    """
    rules = _rules_of(plan)
    seed_mix = kernels.seed_mix(plan.seed)
    decision = plan.sources[ref.ordinal]["color_depth"]
    slots, prios = [], []
    with ref.opened() as unit:
        for chunk in unit.color_chunks(chunk_size):
            slot = rules.rule[decided_keys(plan.spec, chunk.rgb, decision, ref.path)]
            prio = kernels.priorities(np.uint64((ref.ordinal << ID_SHIFT) | chunk.start), len(slot), seed_mix)
            capped = slot >= 0
            slot, prio = slot[capped], prio[capped]
            under = prio <= bounds[slot]
            slots.append(slot[under])
            prios.append(prio[under])
    if not slots:
        return np.zeros(0, np.int32), np.zeros(0, np.uint64)
    return merge_bottom_sets(rules.caps, 0, len(rules.caps), (np.concatenate(slots), np.concatenate(prios)))


def _pairs(bottoms) -> int:
    return len(bottoms[0])


@_reraise_flat
def merge_bottom_sets(caps: np.ndarray, lo: int, hi: int, *parts) -> tuple[np.ndarray, np.ndarray]:
    """Bottom sets of slots [lo, hi) merged, keeping only each slot's caps[slot] smallest priorities."""
    slots = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, np.int32)
    prios = np.concatenate([p[1] for p in parts]) if parts else np.zeros(0, np.uint64)
    inside = (slots >= lo) & (slots < hi)
    slots, prios = slots[inside], prios[inside]
    order = np.lexsort((prios, slots))
    slots, prios = slots[order], prios[order]
    rank = np.arange(len(slots)) - np.searchsorted(slots, slots, side="left")
    keep = rank < caps[slots]
    return slots[keep], prios[keep]


def range_cutoffs(plan: Plan, lo: int, hi: int, bottoms) -> tuple[np.ndarray, np.ndarray]:
    """(slots of [lo, hi) the bound failed for, cutoffs of the others) from a partition's merged bottoms."""
    rules = _rules_of(plan)
    slots, prios = bottoms
    have = np.bincount(slots - lo, minlength=hi - lo)
    short = np.flatnonzero(have < rules.caps[lo:hi])
    part = copy.copy(rules)
    # merge_bottoms over this range only; short slots get a placeholder cutoff, redone by the driver
    part.caps = np.where(have < rules.caps[lo:hi], 1, rules.caps[lo:hi])
    part.capped_keys = rules.capped_keys[lo:hi]
    fill_slots = np.concatenate([slots - lo, short]).astype(np.int64)
    fill_prios = np.concatenate([prios, np.zeros(len(short), np.uint64)])
    cut = merge_bottoms(part, [(fill_slots, fill_prios)]).cut
    return short + lo, cut


# ---------------------------------------------------------------- pass two (worker side)


def part_name(ordinal: int, start: int) -> str:
    """Parts sort in input order: source ordinal, then first record."""
    return f"{PART_PREFIX}{ordinal:06d}-{start:013d}.parquet"


@_reraise_flat
def select_part(ref: UnitRef, plan: Plan, cutoffs: Cutoffs, stage: str, schema: pa.Schema, chunk_size: int,
                compression: str = "zstd") -> int:
    """Write the unit's kept points as its own Parquet part (temporary name, then rename); return the count."""
    from .select import select

    if not os.path.isdir(stage):
        raise OutputError("the staging folder is not visible from this worker (is the output on a shared "
                          "filesystem?)", stage)
    selector = _selector_of(plan, cutoffs)
    dest = os.path.join(stage, part_name(ref.ordinal, ref.start))
    written = 0
    out = AtomicFile(dest)
    writer = None
    try:
        with ref.opened() as unit:
            for chunk, mask in select(unit, plan, cutoffs, chunk_size, selector):
                if not mask.any():
                    continue
                batch = chunk.to_arrow(mask)
                if writer is None:
                    writer = pq.ParquetWriter(out.tmp, schema, compression=compression)
                writer.write_batch(pa.RecordBatch.from_arrays(batch.columns, schema=schema))
                written += batch.num_rows
        if writer is None:
            out.discard()
            with contextlib.suppress(FileNotFoundError):
                os.unlink(dest)  # a retry of a unit that keeps nothing leaves no part
            return 0
        writer.close()
        writer = None
        out.commit()
    except (OSError, pa.ArrowException) as exc:
        out.discard()
        raise OutputError(f"cannot write the part: {exc}", dest) from None
    except BaseException:
        out.discard()
        raise
    finally:
        if writer is not None:
            with contextlib.suppress(Exception):
                writer.close()
    return written


@_reraise_flat
def select_tile(refs: list, plan: Plan, cutoffs: Cutoffs, stage: str, name: str, prov: dict, chunk_size: int) -> int:
    """Write one input tile's kept points as one LAS/LAZ file (its own header), renamed on success."""
    from .select import select

    if not os.path.isdir(stage):
        raise OutputError("the staging folder is not visible from this worker (is the output on a shared "
                          "filesystem?)", stage)
    selector = _selector_of(plan, cutoffs)
    first = refs[0]
    source = open_source(first.path, first.ordinal, **dict(first.options))
    sink = LasSink(os.path.join(stage, name), [source], prov)
    try:
        for ref in refs:
            for chunk, mask in select(Unit(source, ref.start, ref.stop), plan, cutoffs, chunk_size, selector):
                sink.write(chunk, mask)
        sink.commit()
    except BaseException:
        sink.abort()
        raise
    finally:
        source.close()
    return sink.written


# ---------------------------------------------------------------- the driver


def _output_layout(output: str) -> tuple[str, str | None]:
    """(folder, tile extension): ``out/`` or ``out.parquet`` is a Parquet dataset, ``out/*.laz`` one LAZ a tile."""
    base = os.path.basename(output.rstrip("/"))
    if base in ("*.las", "*.laz"):
        return os.path.dirname(output.rstrip("/")) or ".", base[1:]
    if "*" in output:
        raise UsageError("an output pattern must be FOLDER/*.las or FOLDER/*.laz", output)
    ext = extension(output)
    if ext in (".las", ".laz"):
        raise UsageError(f"the Dask engine writes one file per input tile: give FOLDER/*{ext}", output)
    if ext not in ("", ".parquet", ".pq"):
        raise UsageError(f"the Dask engine writes a Parquet dataset folder or FOLDER/*.laz, not {ext!r}", output)
    return output.rstrip("/") or ".", None


def _tile_names(files: list[str], ext: str) -> list[str]:
    names = [output_stem(os.path.basename(f)) + ext for f in files]
    seen = {}
    for f, n in zip(files, names):
        if n in seen:
            raise UsageError(f"two inputs would both write {n} (also {seen[n]}); rename one or write Parquet", f)
        seen[n] = f
    return names


def _same(value):
    return value


def _held(client, value, key: str):
    """``value`` on the cluster, sent to every worker, as a task rather than scattered data.

    Scattered data dies with the last worker holding it; a task that returns
    the value is rerun on another worker, so a killed worker never loses it.
    """
    future = client.submit(_same, value, key=key, pure=False)
    client.replicate([future])
    return future


def _tree_reduce(client, func, futures, *args, fan_in: int = FAN_IN, name: str):
    """Reduce futures on the cluster, ``fan_in`` at a time, level by level; one future back."""
    level = 0
    while len(futures) > 1:
        futures = [client.submit(func, *args, *futures[i:i + fan_in], key=f"{name}-{level}-{i}")
                   for i in range(0, len(futures), fan_in)]
        level += 1
    return futures[0]


STALL_SECONDS = 120.0


def _gather(client, futures, stall_seconds: float | None = None):
    """client.gather, but a cluster whose every worker stays paused fails instead of hanging.

    A Dask worker pauses at 80% of its memory limit and waits for memory to
    be freed; when every worker is paused, nothing ever runs again.
    """
    from distributed import Future, KilledWorker, wait

    stall = STALL_SECONDS if stall_seconds is None else stall_seconds
    flat = [futures] if isinstance(futures, Future) else list(futures)
    paused_since = None
    try:
        while True:
            try:
                wait(flat, timeout=2.0)
                break
            except TimeoutError:
                pass
            workers = client.scheduler_info().get("workers", {})
            statuses = [str(w.get("status", "")).lower() for w in workers.values()]
            if statuses and all("paused" in st for st in statuses):
                paused_since = paused_since or time.monotonic()
                if time.monotonic() - paused_since > stall:
                    client.cancel(flat)
                    limits = sorted({int(w.get("memory_limit") or 0) >> 20 for w in workers.values()})
                    raise ClusterError(
                        f"every worker has been paused at its memory limit ({', '.join(map(str, limits))} MiB) "
                        f"for {stall:.0f} s; give workers at least 1 GB or use --quant-bits 1 or more")
            else:
                paused_since = None
        return client.gather(futures)
    except KilledWorker as exc:
        raise ClusterError(f"a worker died running the same task too many times ({exc}); out of memory?") from None


def connect(address: str):
    """A Client for ``tcp://host:port`` (an existing scheduler) or ``local:N`` (a LocalCluster of N processes).

    A context manager; a LocalCluster is shut down on exit.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise UsageError("--dask needs Dask: pip install 'prism-stream[dask]'") from None

    if address.startswith("local:") or address == "local":
        n = address.partition(":")[2] or str(os.cpu_count() or 1)
        if not n.isdigit() or int(n) < 1:
            raise UsageError(f"--dask local:N needs a positive number of workers, not {n!r}")
        cluster = LocalCluster(n_workers=int(n), threads_per_worker=1, processes=True, dashboard_address=":0")
        return _Owned(Client(cluster), cluster)
    try:
        return _Owned(Client(address, timeout="20s"), None)
    except (OSError, TimeoutError) as exc:
        raise ClusterError(f"cannot reach the Dask scheduler: {exc}", address) from None


class _Owned:
    def __init__(self, client, cluster):
        self.client, self.cluster = client, cluster

    def __enter__(self):
        return self.client

    def __exit__(self, *exc):
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def sample_at(address: str, inputs, output=None, **kw) -> Summary:
    """:func:`sample` on the cluster at ``address`` (``tcp://...`` or ``local:N``)."""
    with connect(address) as client:
        return sample(client, inputs, output, **kw)


def on_cluster(address: str):
    """``prism_stream.sample``'s call shape, run on the cluster at ``address`` (what the CLI's --dask calls)."""

    def run(inputs, output=None, **kw):
        return sample_at(address, inputs, output, **kw)

    return run


def sample(
    client,
    inputs,
    output: str | None = None,
    *,
    ratio: float | None = None,
    count: int | None = None,
    k: int | None = None,
    mode: str = "exact",
    color_space: str = "rgb",
    quant_bits: int = 0,
    quant_step: float | None = None,
    color_depth: str = "auto",
    seed: int = 0,
    chunk_size: int = DEFAULT_CHUNK,
    unit_size: int = DEFAULT_UNIT,
    threads: int = 1,
    rgb_columns=None,
    overwrite: bool = False,
    progress: bool = False,
    temp_dir: str | None = None,
    bound_sigmas: float = BOUND_SIGMAS,
    bottoms_per_reducer: int = BOTTOMS_PER_REDUCER,
    flag: str | None = None,
    output_format: str | None = None,
    per_file: bool = False,
) -> Summary:
    """Sample ``inputs`` into ``output`` with PRISM on a Dask cluster; the rows are the local engine's.

    Parameters
    ----------
    client : dask.distributed.Client
        The cluster to run on. Inputs and output must be visible to every
        worker under the same paths.
    inputs : str or list of str
        Files, globs or Parquet directories, as for :func:`prism_stream.sample`.
    output : str or None
        ``FOLDER`` or ``FOLDER.parquet``: a Parquet dataset folder, one part
        per work unit that keeps points (``part-<source>-<first record>.parquet``,
        in input order). ``FOLDER/*.laz`` (or ``*.las``): one file per input
        tile, named after it. None: pass one and the solve only.
    unit_size : int
        Points per work unit (LAZ: rounded to whole chunks; Parquet: one row
        group a unit). The output does not depend on it.
    bound_sigmas, bottoms_per_reducer
        Tuning of the cutoff reduce (see :func:`cutoff_bounds`); the output
        does not depend on them.

    The other options are :func:`prism_stream.sample`'s; ``progress`` and
    ``temp_dir`` are accepted for symmetry (nothing is cached on disk);
    ``flag``, ``output_format`` and ``per_file`` are the local engine's only.
    """
    for name, value in (("--flag", flag), ("--format", output_format), ("--per-file", per_file or None)):
        if value is not None:
            raise UsageError(f"{name} is not available with --dask (it writes a Parquet dataset or FOLDER/*.laz)")
    threads = 1 if threads is None else threads
    options = Options(ratio=ratio, count=count, k=k, mode=mode, color_space=color_space, bits=int(quant_bits),
                      quant_step=quant_step,
                      color_depth=color_depth, seed=int(seed))
    for name, value in (("--chunk-size", chunk_size), ("--threads", threads), ("unit_size", unit_size)):
        if value < 1:
            raise UsageError(f"{name} must be positive, not {value}")
    files = expand_inputs(inputs)
    folder = tiles = None
    if output is not None:
        folder, tiles = _output_layout(os.fspath(output))
        real = os.path.realpath(folder)
        if any(os.path.realpath(f) == real or os.path.realpath(f).startswith(real + os.sep) for f in files):
            raise UsageError("the output folder would overwrite or hold an input", folder)
        if os.path.lexists(folder) and not overwrite:
            raise OutputExists("already exists (use --overwrite to replace it)", folder)
        if not os.path.isdir(os.path.dirname(os.path.abspath(folder))):
            raise OutputError("output folder's parent does not exist", folder)
    spec = options.spec
    seconds: dict = {}
    run = uuid.uuid4().hex[:10]
    stats: dict = {"workers": len(client.scheduler_info().get("workers", {}))}
    open_options = tuple(sorted({"threads": int(threads), "rgb_columns": rgb_columns}.items()))
    t0 = time.perf_counter()
    sources = [open_source(f, i, threads=threads, rgb_columns=rgb_columns) for i, f in enumerate(files)]
    stage = None
    try:
        for s in sources:
            if s.count >= MAX_RECORDS_PER_SOURCE:
                raise CorruptInput(f"{s.count} points is more than one source may hold (2^{ID_SHIFT})", s.path)
        refs = [r for s in sources for r in unit_refs(s, unit_size, open_options)]
        stats["units"] = len(refs)

        # pass one: unit histograms, the depth decisions, a tree merge on the cluster
        scans = client.map(scan_unit, refs, spec=spec, color_depth=options.color_depth, chunk_size=chunk_size,
                           key=[f"prism-scan-{run}-{i}" for i in range(len(refs))])
        facts = _gather(client, client.map(unit_facts, scans, key=[f"prism-facts-{run}-{i}" for i in range(len(refs))]))
        stubs = [UnitScan(o, p, m, kind, Histogram.empty()) for o, p, m, kind in facts]
        _, decisions = merge_units(stubs, options.color_depth)
        seen = {}
        for o, p, _, _ in facts:
            seen[o] = seen.get(o, 0) + p
        source_facts = {}
        for s in sources:
            if seen.get(s.ordinal, 0) != s.count:
                raise CorruptInput(f"header declares {s.count} points but {seen.get(s.ordinal, 0)} could be read",
                                   s.path)
            mine = [f for f in facts if f[0] == s.ordinal]
            source_facts[s.ordinal] = UnitScan(s.ordinal, 0, max(f[2] for f in mine),
                                               next((f[3] for f in mine if f[3]), None), Histogram.empty())
        decided = [client.submit(decided_histogram, f, source_facts[r.ordinal], options.color_depth,
                                 key=f"prism-decide-{run}-{i}") for i, (f, r) in enumerate(zip(scans, refs))]
        del scans
        histogram = _gather(client, _tree_reduce(client, merge_histograms, decided, name=f"prism-hmerge-{run}"))
        del decided
        stats["histogram_bytes"] = int(histogram.keys.nbytes + histogram.counts.nbytes)
        source_scans = [source_scan(s, s.count, decisions[s.ordinal], source_facts[s.ordinal].max_value).as_dict()
                        for s in sources]
        seconds["scan"] = time.perf_counter() - t0

        t1 = time.perf_counter()
        plan = solve(histogram, options, tuple(source_scans))
        del histogram
        seconds["solve"] = time.perf_counter() - t1
        caught = warn_about(plan)
        if output is None:
            seconds["total"] = time.perf_counter() - t0
            return _with_stats(summarize(plan, [os.path.abspath(f) for f in files], None, seconds, caught), stats)

        # the plan, to every worker (rebuilt from JSON if a worker holding it dies)
        t2 = time.perf_counter()
        plan_json = worker_plan(plan).to_json()
        stats["plan_full_json_bytes"] = len(plan.to_json())
        stats["plan_json_bytes"] = len(plan_json)
        plan_f = client.submit(Plan.from_json, plan_json, key=f"prism-plan-{run}")
        client.replicate([plan_f])  # rebuilt from its JSON if every worker holding it dies
        cutoffs = _cutoffs(client, plan, plan_f, refs, chunk_size, bound_sigmas, bottoms_per_reducer, run, stats)
        stats["cutoffs_bytes"] = int(cutoffs.keys.nbytes + cutoffs.cut.nbytes)
        cutoffs_f = _held(client, cutoffs, f"prism-cutoffs-{run}")
        seconds["cutoffs"] = time.perf_counter() - t2

        # pass two: parts or tiles in a staging folder beside the output
        t3 = time.perf_counter()
        prov = provenance(plan, files)
        parent = os.path.dirname(os.path.abspath(folder))
        stage = tempfile.mkdtemp(prefix="." + os.path.basename(os.path.abspath(folder)) + ".", suffix=".prism-tmp",
                                 dir=parent)
        os.chmod(stage, public_mode(0o777))  # mkdtemp makes it private; the output folder should not be
        if tiles is None:
            schema = output_schema(sources, prov)  # the local Parquet sink's, provenance included
            jobs = client.map(select_part, refs, plan=plan_f, cutoffs=cutoffs_f, stage=stage, schema=schema,
                              chunk_size=chunk_size, key=[f"prism-select-{run}-{i}" for i in range(len(refs))])
        else:
            for s in sources:
                if not isinstance(s, LasSource):
                    raise UsageError("LAS/LAZ output needs LAS/LAZ inputs; write Parquet instead", s.path)
            names = _tile_names(files, tiles)
            by_tile = [[r for r in refs if r.ordinal == s.ordinal] for s in sources]
            jobs = [client.submit(select_tile, group, plan_f, cutoffs_f, stage, name, prov, chunk_size,
                                  key=f"prism-select-{run}-{i}")
                    for i, (group, name) in enumerate(zip(by_tile, names))]
        written = sum(_gather(client, jobs))
        del jobs, plan_f, cutoffs_f
        if written != plan.kept:
            raise AssertionError(f"wrote {written} points, the plan keeps {plan.kept}")
        seconds["select"] = time.perf_counter() - t3
        t4 = time.perf_counter()
        _commit(stage, folder, tiles, schema if tiles is None else None)
        stage = None
        seconds["commit"] = time.perf_counter() - t4
    except KeyboardInterrupt:
        raise Interrupted("interrupted; no output was written", output) from None
    finally:
        for s in sources:
            s.close()
        if stage is not None:
            shutil.rmtree(stage, ignore_errors=True)
    seconds["total"] = time.perf_counter() - t0
    return _with_stats(summarize(plan, [os.path.abspath(f) for f in files], folder, seconds, caught), stats)


def _with_stats(summary: Summary, stats: dict) -> Summary:
    """The cluster's share of the summary, under ``plan["dask"]``: units, sizes of what moved, bins redone."""
    summary.plan["dask"] = stats
    return summary


def _cutoffs(client, plan: Plan, plan_f, refs, chunk_size, sigmas, per_reducer, run, stats) -> Cutoffs:
    """Each capped bin's cutoff: bounded unit bottoms, reduced in slot-range partitions; bins the bound failed redone."""
    rules = _rules_of(plan)
    caps = rules.caps
    if not len(caps):
        return merge_bottoms(rules, [])
    cut = np.zeros(len(caps), dtype=np.uint64)
    todo = np.arange(len(caps))
    bounds = cutoff_bounds(plan, sigmas)
    for attempt in range(2):
        bounds_f = _held(client, bounds, f"prism-bounds-{run}-{attempt}")
        bottoms = client.map(unit_bottoms, refs, plan=plan_f, bounds=bounds_f, chunk_size=chunk_size,
                             key=[f"prism-bottoms-{run}-{attempt}-{i}" for i in range(len(refs))])
        sizes = client.map(_pairs, bottoms, key=[f"prism-bsize-{run}-{attempt}-{i}" for i in range(len(refs))])
        stats.setdefault("bottoms_pairs", []).append(int(sum(_gather(client, sizes))))
        del sizes
        caps_f = _held(client, caps, f"prism-caps-{run}-{attempt}")
        weight = np.cumsum(caps)
        parts = max(1, math.ceil(int(weight[-1]) / max(1, per_reducer)))
        stats["cutoff_partitions"] = parts
        edges = [0] + [int(np.searchsorted(weight, weight[-1] * p / parts, side="left")) + 1
                       for p in range(1, parts)] + [len(caps)]
        edges = sorted(set(min(e, len(caps)) for e in edges))
        results = []
        for p, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
            if not np.any((todo >= lo) & (todo < hi)):
                continue
            leaves = [client.submit(merge_bottom_sets, caps_f, lo, hi, *bottoms[i:i + FAN_IN],
                                    key=f"prism-bmerge-{run}-{attempt}-{p}-leaf-{i}")
                      for i in range(0, len(bottoms), FAN_IN)]
            root = _tree_reduce(client, merge_bottom_sets, leaves, caps_f, lo, hi, name=f"prism-bmerge-{run}-{attempt}-{p}")
            results.append((lo, hi, client.submit(range_cutoffs, plan_f, lo, hi, root, key=f"prism-cut-{run}-{attempt}-{p}")))
        short = []
        for (lo, hi, fut), (missing, values) in zip(results, _gather(client, [r[2] for r in results])):
            ok = np.ones(hi - lo, dtype=bool)
            ok[missing - lo] = False
            wanted = np.isin(np.arange(lo, hi), todo)
            cut[lo:hi][ok & wanted] = values[ok & wanted]
            short.append(np.intersect1d(missing, todo))
        del bottoms, results
        todo = np.concatenate(short) if short else np.zeros(0, np.int64)
        stats["bins_redone"] = stats.get("bins_redone", 0) + len(todo)
        if not len(todo):
            return Cutoffs(rules.capped_keys.copy(), cut)
        # the bound was too low for these bins (a fluke, or a tiny bound_sigmas): redo them with no bound
        bounds = np.zeros(len(caps), dtype=np.uint64)
        bounds[todo] = U64_MAX
    raise AssertionError("cutoff merge saw fewer points than the histogram counted")


def _commit(stage: str, folder: str, tiles, schema) -> None:
    """Drop what killed tasks left behind, then rename the staging folder onto the output."""
    for name in os.listdir(stage):
        if name.startswith(".") and name.endswith(".prism-tmp"):
            os.unlink(os.path.join(stage, name))
    if tiles is None and not any(n.startswith(PART_PREFIX) for n in os.listdir(stage)):
        pq.ParquetWriter(os.path.join(stage, part_name(0, 0)), schema, compression="zstd").close()
    old = None
    if os.path.lexists(folder):
        old = folder.rstrip("/") + f".prism-old-{uuid.uuid4().hex[:8]}"
        os.rename(folder, old)
    try:
        os.rename(stage, folder)
    except OSError as exc:
        if old is not None:
            os.rename(old, folder)
        raise OutputError(f"cannot commit the output: {exc.strerror or exc}", folder) from None
    if old is not None:
        shutil.rmtree(old, ignore_errors=True) if os.path.isdir(old) else os.unlink(old)


def read_dataset(folder: str) -> pa.Table:
    """The rows of a Parquet dataset folder this engine wrote, in input order."""
    parts = sorted(glob.glob(os.path.join(folder, PART_PREFIX + "*.parquet")))
    return pa.concat_tables([pq.read_table(p) for p in parts])
