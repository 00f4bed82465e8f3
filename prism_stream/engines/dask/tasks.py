"""What runs on the workers: the core's steps on one work unit, re-opened from a picklable reference.

Every task's result is a function of its arguments alone (a unit reference,
the plan, the cutoffs), so a task lost with its worker is simply run again
elsewhere; a pass-one attempt writes its spill to a folder of its own, so a
retry never reads what a killed attempt left.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import shutil
import uuid
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from ...core import keyblocks
from ...core.candidates import CandidateFilter
from ...core.cutoffs import Cutoffs, Rules, bounded_bottoms, merge_bottom_sets, read_cutoffs, spill_bottoms
from ...core.histogram import Histogram, UnitScan, as_histogram, fold
from ...core import space
from ...core.kernels import ID_SHIFT, seed_mix
from ...core.passes import scan, scan_candidates, select, unit_keys
from ...core.quotas import Plan
from ...core.selection import Selector
from ...errors import OutputError
from ...formats import WriteOptions, open_sink, open_source
from ...formats.base import Unit
from ...formats.parquet import ParquetSink
from ...run import remote, staging
from ...run.memory import release_memory
from ...run.spill import Spill, SpillFull
from ...run.tempspace import spill_bound, target_bound
from ...evaluate.cloud import coordinates
from ..spatial import IdSelector, Rarity, scan_chunk
from .. import spatial_disk
from ..spatial_disk import DiskScan, write_part
from .cluster import task

PART_PREFIX = "part-"


# ---------------------------------------------------------------- work units


@dataclass(frozen=True)
class UnitRef:
    """A picklable work unit: records [start, stop) of the source at ``path`` (a path or a URL), re-opened
    where it runs."""

    path: str
    ordinal: int
    start: int
    stop: int
    options: tuple = ()  # (name, value) pairs for open_source: threads, rgb_columns
    columns: tuple | None = None  # the columns to decode (--keep/--drop; None: every one): Source.read_only

    @property
    def points(self) -> int:
        return self.stop - self.start

    def source(self):
        """The unit's source, opened here, decoding the driver's choice of its columns."""
        source = open_source(self.path, self.ordinal, **dict(self.options))
        if self.columns is not None:
            source.read_only(self.columns)
        return source

    @contextlib.contextmanager
    def opened(self):
        source = self.source()
        try:
            yield Unit(source, self.start, self.stop)
        finally:
            source.close()


def unit_refs(source, unit_size: int, options: tuple) -> list[UnitRef]:
    """The source's work units (LAZ ranges are whole chunks: see LasSource.units), as picklable refs.

    A remote source's refs carry the URL and the store's options (its endpoint, never credentials:
    each worker has its own), so a worker reads the object itself rather than a path the driver sees.
    """
    if remote.is_remote(source.path):
        options = (*options, ("storage_options", remote.storage_options(source.path)))
    columns = getattr(source, "read_columns", None)  # the driver's read_only: the workers decode the same
    columns = tuple(columns) if columns is not None else None
    return [UnitRef(source.path, source.ordinal, u.start, u.stop, options, columns) for u in source.units(unit_size)]


# ---------------------------------------------------------------- pass one (worker side)


@task
def scan_unit(ref: UnitRef, spec, color_depth: str, chunk_size: int) -> UnitScan:
    with ref.opened() as unit:
        return scan(unit, spec, color_depth, chunk_size)


@dataclass(frozen=True)
class UnitSpill:
    """Where pass one left a unit's candidate spill (None: the disk, a quota or a file-size limit ran
    out, the unit is read again), with the unit's own color-depth decision, which its spilled keys follow."""

    folder: str | None
    decision: str
    points: int = 0
    bytes: int = 0
    final: bool = False  # the unit's keys are final (UnitScan.final): its counts may join a prior at once
    refiled: int = 0  # points the unit moved to key 0 when it proved its file 16-bit after them
    why: str = ""  # why it has no folder: "space" (its spill ran out of room), "16-bit" (see needs_reread),
    #                "bins" (the run reads its later units twice: :func:`scan_unit_reread`)
    compactions: int = 0  # times its spill was compacted (unit_compact_mark)
    written: int = 0  # candidates it wrote in all (``points`` is what its compactions left)
    bins: int = 0  # the distinct bin keys of the unit's own points

    def needs_reread(self, decision: str) -> bool:
        """Whether this spill lacks points the sample may take, its file decided ``decision``: a unit spills
        no candidates for the outcome "16-bit" of points that may still move to key 0 (one heap of T + 1
        words a unit made 8-bit values in 16-bit fields spill 24.5% of N), so a unit with such points in a
        file proved 16-bit (it saw no value above 255, or saw one only after its first points) is read
        again instead."""
        return self.folder is not None and (self.refiled > 0 or (not self.final and decision == "16"))


@task
def scan_unit_spill(ref: UnitRef, options, declared: int, chunk_size: int, spills: str,
                    prior: "Prior | None" = None, budget: int | None = None) -> tuple:
    """Pass one of a unit on the one-read path: its histogram, and every point it may give the sample
    spilled (the whole record) to a folder of its own under ``spills``, so the cutoffs and pass two need
    no second read: (its scan, its :class:`UnitSpill`).

    The unit runs the local engine's candidate filter with the run's target (``declared`` points in
    all): its own counts are part of the run's, so its bound K_t is at least the run's K, and every
    point the sample selects from this unit is spilled, once its file is decided as the unit saw it. A
    unit with points that may yet move to key 0 spills nothing for that outcome; if it comes, the unit
    is read again (:meth:`UnitSpill.needs_reread`). ``prior``: counts of units scanned before, with
    their final keys (:meth:`CandidateFilter.count_elsewhere`), which tighten the bound from the start.
    ``budget``: the most bytes the unit's spill may take (its share of the staging disk's free space);
    past it, as on a full disk, the unit drops its spill and is read again in the cutoffs and pass two.
    """
    _visible(spills)
    folder = os.path.join(spills, f"{ref.ordinal:06d}-{ref.start:013d}-{uuid.uuid4().hex[:8]}")
    spec = options.spec
    candidates = CandidateFilter(spec, options, declared)
    candidates.undecided_heap = False  # a unit whose file proves 16-bit late is read again instead
    if prior is not None:
        candidates.count_elsewhere(prior.histogram.keys, prior.histogram.counts, prior.limit_keys, prior.limits,
                                   prior.evidence)
    try:
        os.mkdir(folder)  # an attempt of its own: a retried task never reads a killed attempt's files
        with ref.opened() as unit, Spill(folder, budget=budget) as spill:
            spill.limit(unit_compact_mark(ref, options, declared))
            result = scan_candidates(unit, candidates, options.color_depth, chunk_size, spill)
            spill.finish()
            facts = UnitSpill(folder, result.decision, spill.size, spill.bytes, result.final, spill.refiled,
                              compactions=spill.compactions, written=spill.written)
    except (OSError, SpillFull) as exc:
        shutil.rmtree(folder, ignore_errors=True)
        if isinstance(exc, OSError) and exc.errno in staging.NOT_ALLOWED and str(exc.filename or "").startswith(
                spills):  # the staging folder made read-only under the run (not an input it cannot read)
            raise OutputError(f"cannot write the units' spills: {exc.strerror}", spills) from None
        if isinstance(exc, OSError) and exc.errno not in staging.OUT_OF_ROOM:
            raise
        return _read_again(ref, options, chunk_size, "space")
    release_memory()  # the decoded batches Arrow's and glibc's allocators keep: the unit's evidence takes their place
    # in key order (the filter's slots are in order of arrival): the merges of priors go a range of keys at a time
    limits = (*keyblocks.in_key_order(*candidates.limits()), keyblocks.in_key_order(*candidates.evidence()))
    # the unit's own counts (a refile moves only its own)
    own = candidates.histogram(None if prior is None else prior.histogram)
    return dataclasses.replace(result, histogram=own), dataclasses.replace(facts, bins=len(own.keys)), limits


@task
def scan_unit_reread(ref: UnitRef, options, chunk_size: int) -> tuple:
    """Pass one of a unit of a one-read run that reads its later units twice (a cloud of more colors than
    the priors fit in a worker's memory: the driver's :data:`.driver.PRIOR_BINS`): its histogram alone, as
    :func:`scan_unit`, in :func:`scan_unit_spill`'s shape, with no spill (the cutoffs and pass two read the
    unit again)."""
    return _read_again(ref, options, chunk_size, "bins")


def _read_again(ref: UnitRef, options, chunk_size: int, why: str) -> tuple:
    """A unit's histogram alone, in :func:`scan_unit_spill`'s shape: no spill, the unit read again in the
    cutoffs and pass two for ``why`` (:attr:`UnitSpill.why`)."""
    result = scan_unit(ref, options.spec, options.color_depth, chunk_size)
    return result, UnitSpill(None, result.decision, why=why, bins=len(result.histogram.keys)), None


UNIT_COMPACT_SHARE = 0.5  # of a unit's share of the bound: after a compaction the next comes at twice what is
# left, so a unit whose compactions cut its spill under the mark ends within its share. 100M points over 15.9M
# bins, T = 5M, two workers: the units' spills 42.6M points at 0.75 (as the local engine's mark), 41.2M at 2/3,
# 39.5M at 0.5 (the bound: 40.0M), pass one 184, 191 and 198 s (119 s without compactions: 85.4M points)


def unit_compact_mark(ref: UnitRef, options, declared: int) -> int:
    """Candidates at which a unit's spill is compacted (:meth:`.Spill.compact`, as the local engine's): half
    its share by points of the run's random-order bound (:data:`UNIT_COMPACT_SHARE`).

    A unit's filter counts the prior's points beside its own, so as the prior grows its K_t and its bin
    priority bound (theta) fall, but a point spilled while they were higher stays unless a compaction
    drops it. Without one, over 2^24 bins (100M points, 15.9M bins, T = 5M on two workers) the units'
    spills took 85% of the points, 2.1 times the bound: the first units' priors knew a fraction of the
    bins, so theta let most of them through. A compaction keeps each bin's standing quota of the unit's
    own points (a point outside its unit's q smallest of a bin is outside the whole run's), the same rule
    the local engine's compaction applies to the whole input's spill."""
    share = spill_bound(declared, target_bound(options, declared)) * ref.points // max(1, declared)
    return max(1, int(share * UNIT_COMPACT_SHARE))


def spilled_keys(keys: np.ndarray, unit_decision: str, decision: str) -> np.ndarray:
    """A unit's spilled keys, which follow its file's color-depth decision (a unit that saw only values
    <= 255 in a file proved 16-bit has no spill: it is read again, :meth:`UnitSpill.needs_reread`)."""
    if unit_decision == decision:
        return keys
    raise AssertionError(f"a unit read as {unit_decision}-bit in a file decided {decision} kept its spill")


@contextlib.contextmanager
def reopened(facts: UnitSpill):
    spill = Spill.reopen(facts.folder)
    try:
        yield spill
    finally:
        spill.close()


def decided_index(facts: UnitSpill, ref: UnitRef, plan: WorkerPlan):
    """(keys, ids) of a unit's spill index, the keys under its file's color-depth decision."""
    decision = plan.sources[ref.ordinal]["color_depth"]
    with reopened(facts) as spill:
        for keys, ids in spill.index():
            yield spilled_keys(keys, facts.decision, decision), ids


def histogram_of(result) -> Histogram:
    """A unit's histogram (under its own keys), of what :func:`scan_unit` or :func:`scan_unit_spill` returns."""
    return (result[0] if isinstance(result, tuple) else result).histogram


def unit_facts(s: UnitScan) -> tuple:
    return s.ordinal, s.points, s.max_value, s.kind


@task
def merge_histograms(*parts):
    """The parts' sum, dense once that is smaller (:func:`.histogram.fold`); :func:`sparse_histogram` at the end."""
    return fold(parts)


@task
def sparse_histogram(h) -> Histogram:
    return as_histogram(h)


@dataclasses.dataclass(frozen=True)
class Prior:
    """What the units done tell the next ones: their counts, and per bin the smallest priority bound any of
    them proved (:meth:`.CandidateFilter.limits`: at least K + 1 of the bin's points lie at or below it)."""

    histogram: Histogram
    limit_keys: np.ndarray  # uint32, sorted, distinct
    limits: np.ndarray  # uint64
    evidence: tuple | None = None  # (keys, levels, counts): the units' CandidateFilter.evidence, summed


EVIDENCE_LEVELS = 8  # levels of summed evidence a prior keeps per bin (the deepest ones): every unit reads them


def sum_evidence(*parts: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Evidence of units that saw distinct points, summed per bin and level and nothing more (no level
    raised to a deeper one's count, none dropped): the first step of :func:`merge_evidence`, which is
    associative, so ``merge_evidence(a, sum_evidence(b, c))`` is ``merge_evidence(a, b, c)`` to the bit. What a
    fold of some units' evidence holds until it joins a prior: at most one entry per bin and level seen."""
    parts = [p for p in parts if p is not None and len(p[0])]
    if not parts:
        return _no_evidence()
    if len(parts) == 1:
        return parts[0]
    return keyblocks.merged(_sum_evidence, [keyblocks.in_key_order(*p) for p in parts])


def _no_evidence() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros(0, np.uint32), np.zeros(0, np.uint8), np.zeros(0, np.int64)


def _sum_evidence(parts: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if not parts:
        return _no_evidence()
    keys = np.concatenate([p[0] for p in parts]).astype(np.uint32)
    levels = np.concatenate([p[1] for p in parts]).astype(np.uint8)
    counts = np.concatenate([p[2] for p in parts]).astype(np.int64)
    order = np.lexsort((-levels.astype(np.int16), keys))  # by key, the deepest level first
    keys, levels, counts = keys[order], levels[order], counts[order]
    at = np.flatnonzero(np.concatenate([[True], (keys[1:] != keys[:-1]) | (levels[1:] != levels[:-1])]))
    return keys[at], levels[at], np.add.reduceat(counts, at)


def merge_evidence(*parts: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Evidence of units that saw distinct points (:meth:`.CandidateFilter.evidence`, or earlier sums), summed:
    per bin and level, a lower bound of the points of all of them below tau[level].

    A count below a deeper level also counts below every shallower one, so each level then takes the
    largest sum at it or deeper, and a level that says no more than a deeper one is dropped; a bin keeps
    its EVIDENCE_LEVELS deepest levels (dropping evidence only leaves lower bounds lower). A range of keys at
    a time (:func:`.keyblocks.merged`)."""
    parts = [p for p in parts if p is not None and len(p[0])]
    return keyblocks.merged(_merge_evidence, [keyblocks.in_key_order(*p) for p in parts])


def _merge_evidence(parts: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if not parts:
        return _no_evidence()
    keys = np.concatenate([p[0] for p in parts]).astype(np.uint32)
    levels = np.concatenate([p[1] for p in parts]).astype(np.int64)
    counts = np.concatenate([p[2] for p in parts]).astype(np.int64)
    order = np.lexsort((-levels, keys))  # by key, the deepest level first
    keys, levels, counts = keys[order], levels[order], counts[order]
    new = np.concatenate([[True], (keys[1:] != keys[:-1]) | (levels[1:] != levels[:-1])])
    at = np.flatnonzero(new)
    keys, levels, counts = keys[at], levels[at], np.add.reduceat(counts, at)
    starts = np.flatnonzero(np.concatenate([[True], keys[1:] != keys[:-1]]))
    group = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, len(keys))))
    # the running max from the deepest level of each bin up: np.maximum.accumulate, restarted at each bin
    offset = group.astype(np.int64) * (int(counts.max()) + 1)
    counts = np.maximum.accumulate(counts + offset) - offset
    # a level whose count is no larger than a deeper one's says nothing more: dropped
    useful = np.concatenate([[True], (group[1:] != group[:-1]) | (counts[1:] > counts[:-1])])
    keys, levels, counts, group = keys[useful], levels[useful], counts[useful], group[useful]
    starts = np.searchsorted(group, group, side="left")
    keep = np.arange(len(keys)) - starts < EVIDENCE_LEVELS
    return keys[keep], levels[keep].astype(np.uint8), counts[keep]


@task
def merge_prior(*parts, fold: bool = False) -> Prior:
    """The prior of the next units: the counts, bounds and evidence of ``parts``, each a :class:`Prior` (an
    earlier merge or fold), a :func:`scan_unit_spill` result (a unit read again for want of space brings
    counts alone) or None.

    ``fold``: a fold of some units' results on their way to a prior, not a prior: its evidence is summed
    (:func:`sum_evidence`), not merged, so that ``merge_prior(p, merge_prior(a, b, fold=True), c)`` is
    ``merge_prior(p, a, b, c)`` to the bit (the counts' sum and the bounds' minimum are associative too).
    :func:`merge_evidence` raises each level to the deeper ones' count and keeps a bin's deepest few, which
    a later sum cannot undo: a prior made of merges of parts would be weaker than one of the parts."""
    priors = [p for p in parts if isinstance(p, Prior)]
    scanned = [p for p in parts if p is not None and not isinstance(p, Prior)]
    histogram = Histogram.sum([p.histogram for p in priors] + [scan.histogram for scan, _, _ in scanned])
    keys = [p.limit_keys for p in priors] + [lim[0] for _, _, lim in scanned if lim is not None]
    values = [p.limits for p in priors] + [lim[1] for _, _, lim in scanned if lim is not None]
    evidence = (sum_evidence if fold else merge_evidence)(
        *[p.evidence for p in priors], *[lim[2] for _, _, lim in scanned if lim is not None and len(lim) > 2])
    keys, values = keyblocks.merged(_smallest_limits, [keyblocks.in_key_order(k, v) for k, v in zip(keys, values)])
    return Prior(histogram, keys, values, evidence)


def _smallest_limits(parts: list) -> tuple[np.ndarray, np.ndarray]:
    """Each key's smallest bound of ``parts`` ((keys, bounds) each), by key."""
    if not parts:
        return np.zeros(0, np.uint32), np.zeros(0, np.uint64)
    keys = np.concatenate([k for k, _ in parts]).astype(np.uint32, copy=False)
    values = np.concatenate([v for _, v in parts]).astype(np.uint64, copy=False)
    order = np.lexsort((values, keys))  # by key, the smallest bound first
    keys, values = keys[order], values[order]
    first = np.concatenate([[True], keys[1:] != keys[:-1]])
    return keys[first], values[first]


# ---------------------------------------------------------------- cutoffs (worker side)

U64_MAX = np.uint64((1 << 64) - 1)
_CACHE: dict = {}


class WorkerPlan:
    """What a worker holds of the run's plan: its scalars (:meth:`.Plan.without_bins`: the bin spec, the seed,
    each source's color depth) and its rules, made on the worker (:func:`worker_plan`). The plan's per-bin arrays
    never reach a worker: its JSON took 27 bytes a kept bin, and 20 more once decoded, on every worker (over
    2^24 bins at T = 50M, 745 MB before a worker did anything)."""

    def __init__(self, plan: Plan, rules: Rules):
        self.plan, self.rules = plan, rules

    @property
    def sources(self) -> tuple:
        return self.plan.sources

    @property
    def spec(self):
        return self.plan.spec

    @property
    def seed(self) -> int:
        return self.plan.seed


def worker_plan(light: Plan, whole_keys: np.ndarray, capped_keys: np.ndarray, caps: np.ndarray) -> WorkerPlan:
    """The :class:`WorkerPlan` of a plan without its bins and its rules' :meth:`.Rules.parts` (4 bytes a bin kept
    whole, 12 a capped one): a task whose arguments are in the graph, so the scheduler makes it again on
    another worker if every worker holding it dies."""
    return WorkerPlan(light, Rules.of_parts(light.spec.key_space, light.seed, whole_keys, capped_keys, caps))


def _selector_of(plan: WorkerPlan, cutoffs: Cutoffs | IdSelector) -> Selector | IdSelector:
    """Pass two's keep rule: the plan's under its cutoffs, or the ids a spatial share chose (:class:`IdSelector`)."""
    if isinstance(cutoffs, IdSelector):
        return cutoffs
    hit = _CACHE.get("selector")
    if hit is None or hit[0] is not plan or hit[1] is not cutoffs:
        _CACHE.pop("selector", None)
        _CACHE["selector"] = hit = (plan, cutoffs, Selector(plan.plan, cutoffs, plan.rules))
    return hit[2]


@task
def unit_bottoms(ref: UnitRef, plan: WorkerPlan, bounds: np.ndarray, chunk_size: int) -> tuple[np.ndarray, np.ndarray]:
    """The unit's smallest priorities per capped bin, at or under the bin's bound: (slot, priority)."""
    with ref.opened() as unit:
        return bounded_bottoms(plan.rules, unit_keys(unit, plan, chunk_size), ref.ordinal, bounds)


@task
def unit_bottoms_of(facts: UnitSpill, ref: UnitRef, plan: WorkerPlan, bounds: np.ndarray, chunk_size: int) -> tuple:
    """:func:`unit_bottoms` from the unit's spill index (keys and ids, 12 bytes a candidate); the unit is
    read again only if it has no spill."""
    if facts.folder is None:
        return unit_bottoms(ref, plan, bounds, chunk_size)
    return spill_bottoms(plan.rules, decided_index(facts, ref, plan), bounds)


def pairs(bottoms) -> int:
    return len(bottoms[0])


@task
def merge_bottom_sets_task(plan: WorkerPlan, lo: int, hi: int, *parts) -> tuple[np.ndarray, np.ndarray]:
    """:func:`.merge_bottom_sets` with the caps of the worker's plan."""
    return merge_bottom_sets(plan.rules.caps, lo, hi, *parts)


def range_cutoffs(plan: WorkerPlan, lo: int, hi: int, merged) -> tuple[np.ndarray, np.ndarray]:
    """(slots of [lo, hi) the bound failed for, cutoff of every slot) from a partition's merged bottoms."""
    return read_cutoffs(plan.rules.caps, lo, hi, merged)


# ---------------------------------------------------------------- pass two (worker side)


def part_name(ordinal: int, start: int) -> str:
    """Parts sort in input order: source ordinal, then first record."""
    return f"{PART_PREFIX}{ordinal:06d}-{start:013d}.parquet"


def _visible(stage: str) -> None:
    if not os.path.isdir(stage):
        raise OutputError("the staging folder is not visible from this worker (is the output on a shared "
                          "filesystem?)", stage)


@contextlib.contextmanager
def selected(ref: UnitRef, facts: UnitSpill | None, plan: WorkerPlan, selector: Selector, chunk_size: int, source=None):
    """Pass two of a unit: (its source, an iterator of (point chunk, keep mask)), from its spill when pass
    one left one (``facts``), else from a second read. ``source``: the unit's source, already open."""
    with contextlib.ExitStack() as stack:
        if source is None:
            source = stack.enter_context(ref.opened()).source
        unit = Unit(source, ref.start, ref.stop)
        if facts is None or facts.folder is None:
            yield source, select(unit, plan, chunk_size=chunk_size, selector=selector)
            return
        spill = stack.enter_context(reopened(facts))
        decision = plan.sources[ref.ordinal]["color_depth"]
        yield source, ((chunk, selector.mask_ids(spilled_keys(keys, facts.decision, decision), ids))
                       for keys, ids, chunk in spill.frames_of(source))


class _KeysSeen:
    """A selector that keeps nothing and holds the keys of the last chunk it was asked about: the spatial
    read wants every point and its bin key, not PRISM's mask."""

    keys = None

    def mask(self, keys, ordinal, start):
        self.keys = keys


@task
def unit_space(refs: list, plan: WorkerPlan, rarity: Rarity, chunk_size: int,
               disk: tuple | None = None) -> space.SpatialScan:
    """The spatial read of consecutive units (``--space``): the scan of their points (each cell's winner and
    count at the scan's level), which the driver has folded with the other groups' (:func:`fold_scans`).

    ``disk``: (path, cap) for a target whose cells do not fit in memory: the scan tracks at most ``cap``
    cells and every point (coordinates, bin key, id) is written to ``path``, beside the output, for the
    driver's scan on disk (:meth:`..spatial_disk.DiskScan.of_parts`), under a name of this attempt's own
    until it is whole."""
    seen = _KeysSeen()
    target, mix = int(plan.plan.target), seed_mix(plan.plan.seed)
    scan = None
    try:
        if disk is None:
            scan = space.SpatialScan(target)
        else:
            path, cap = disk
            folder = os.path.dirname(path)
            scan = DiskScan.part(target, path, rarity, mix, cap)
        for ref in refs:
            with ref.opened() as unit:
                for chunk, _ in select(unit, plan, chunk_size=chunk_size, selector=seen):
                    ids = np.uint64((ref.ordinal << ID_SHIFT) | chunk.start) + np.arange(len(chunk), dtype=np.uint64)
                    scan_chunk(scan, ref.path, coordinates(chunk, ref.path), seen.keys, ids, rarity, mix)
        if disk is None:
            return scan.settled()
        write_part(scan)
    except BaseException as exc:
        if disk is None:
            raise
        if scan is not None:
            scan.points.discard()
        _space_error(exc, folder)
        raise
    return scan.mem.settled()


def full_beside_output(exc: BaseException, what: str, named: str, under: str | None = None) -> None:
    """A full or read-only disk under ``what`` in the staging folder (which goes with the run), said in one
    line naming ``named``, the folder the output goes in; ``under``: only for a file there (or none named)."""
    if isinstance(exc, OSError) and exc.errno in staging.OUT_OF_ROOM + staging.NOT_ALLOWED and (
            under is None or exc.filename is None or str(exc.filename).startswith(under)):
        raise OutputError(f"cannot write {what} beside the output: {exc.strerror}", named) from None


@contextlib.contextmanager
def beside_output(what: str, named: str, under: str | None = None):
    """:func:`full_beside_output` around a write to the staging folder."""
    try:
        yield
    except OSError as exc:
        full_beside_output(exc, what, named, under)
        raise


def _space_error(exc: BaseException, folder: str) -> None:
    """:func:`full_beside_output` for the spatial share's files in ``folder`` (``.space`` in the staging folder)."""
    full_beside_output(exc, "the spatial share's files", os.path.dirname(os.path.dirname(folder)), folder)


def _space_files(path: str):
    """:func:`_space_error`'s translation around a spatial task over ``path`` (a file or folder in ``.space``)."""
    folder = os.path.dirname(path.rstrip(os.sep))
    return beside_output("the spatial share's files", os.path.dirname(os.path.dirname(folder)), folder)


@task
def space_route(path, *args):
    """:func:`..spatial_disk.route_part` on a worker."""
    with _space_files(path):
        return spatial_disk.route_part(path, *args)


@task
def space_visit(frame, rarity, pieces, prefix):
    """:func:`..spatial_disk.expand_part` on a worker."""
    with _space_files(prefix):
        return spatial_disk.expand_part(frame, rarity, pieces, prefix)


@task
def space_recount(frame, rarity, leaves, folder, last):
    """:func:`..spatial_disk.recount_part` on a worker."""
    with _space_files(folder):
        return spatial_disk.recount_part(frame, rarity, leaves, folder, last)


@task
def space_list(frame, rarity, leaves, folder, last):
    """:func:`..spatial_disk.list_part` on a worker."""
    with _space_files(folder):
        return spatial_disk.list_part(frame, rarity, leaves, folder, last)


# what :func:`..spatial_disk.order_in_parts` runs (by name), as the tasks that run it
SPACE_TASKS = {"route_part": space_route, "expand_part": space_visit, "recount_part": space_recount,
               "list_part": space_list}


@task
def fold_scans(target: int, *scans: space.SpatialScan) -> space.SpatialScan:
    """Units' scans folded into one (a new one: a task's inputs stay as they were, should it run again)."""
    folded = space.SpatialScan(target, cap=min((s.cap for s in scans), default=None))  # a scan on disk's cap
    for part in scans:
        folded.absorb(part)
    return folded


@task
def unit_kept(ref: UnitRef, facts: UnitSpill | None, plan: WorkerPlan, cutoffs: Cutoffs,
              chunk_size: int) -> tuple[np.ndarray, np.ndarray]:
    """(bin keys, ids) of the unit's kept points, in input order: what the driver ranks (from the unit's
    spill index when it has one)."""
    selector = _selector_of(plan, cutoffs)
    keys, ids = [np.zeros(0, np.uint32)], [np.zeros(0, np.uint64)]
    if facts is not None and facts.folder is not None:
        for k, i in decided_index(facts, ref, plan):
            m = selector.mask_ids(k, i)
            keys.append(k[m])
            ids.append(i[m])
        return np.concatenate(keys), np.concatenate(ids)
    with ref.opened() as unit:
        for start, k in unit_keys(unit, plan, chunk_size):
            at = np.flatnonzero(selector.mask(k, ref.ordinal, start))
            keys.append(k[at])
            ids.append(np.uint64((ref.ordinal << ID_SHIFT) | start) + at.astype(np.uint64))
    return np.concatenate(keys), np.concatenate(ids)


@dataclass(frozen=True)
class InFile:
    """Values (uint64 ids, int64 ranks) the driver wrote to a file beside the output for a task, sent as their
    path: a tile's sample past the spatial share's memory budget, read a block at a time."""

    path: str
    dtype: str

    def opened(self) -> staging.ArrayFile:
        return staging.ArrayFile(os.path.dirname(self.path), os.path.basename(self.path), np.dtype(self.dtype), "rb")


class _Ranked:
    """A unit's ranks handed out in step with the points written (an array, or an :class:`InFile`'s file)."""

    def __init__(self, ranks: "np.ndarray | InFile | None"):
        self.ranks = ranks.opened() if isinstance(ranks, InFile) else ranks
        self.at = 0

    def write(self, sink, chunk, mask) -> None:
        if self.ranks is None:
            sink.write(chunk, mask)
            return
        n = int(np.count_nonzero(mask))
        part = self.ranks.read(self.at, n) if isinstance(self.ranks, staging.ArrayFile) else \
            self.ranks[self.at:self.at + n]
        sink.write(chunk, mask, ranks=part)
        self.at += n

    def close(self) -> None:
        if isinstance(self.ranks, staging.ArrayFile):
            self.ranks.close()


@dataclasses.dataclass(frozen=True)
class Writing:
    """What every pass-two task of a run writes with: the staging folder, the provenance, the chunk size, the
    rank column (or None) and the parts' schema (Parquet; None for tiles)."""

    stage: str
    prov: dict
    chunk_size: int
    rank: str | None = None
    schema: pa.Schema | None = None

    def __getstate__(self) -> dict:
        # the schema as Arrow IPC bytes: pickling a pa.Schema loses a list's item field (its name and its
        # "not null"), so the parts' schema would differ from the local run's output (pyarrow 26)
        state = dict(self.__dict__)
        if self.schema is not None:
            state["schema"] = self.schema.serialize().to_pybytes()
        return state

    def __setstate__(self, state: dict) -> None:
        if state.get("schema") is not None:
            state = {**state, "schema": pa.ipc.read_schema(pa.py_buffer(state["schema"]))}
        for name, value in state.items():
            object.__setattr__(self, name, value)


@task
def select_part(ref: UnitRef, plan: WorkerPlan, cutoffs: Cutoffs, writing: Writing, ranks: np.ndarray | None = None,
                facts: UnitSpill | None = None) -> int:
    """Write the unit's kept points as its own Parquet part (temporary name, then rename); return the count.

    A unit that keeps nothing leaves no part (and removes one an earlier
    attempt of the same task may have left). ``ranks``: the kept points'
    ranks, written in the column ``writing.rank``. ``facts``: the unit's
    spill, read instead of the input.
    """
    stage, prov, chunk_size, rank, schema = (writing.stage, writing.prov, writing.chunk_size, writing.rank,
                                             writing.schema)
    _visible(stage)
    selector = _selector_of(plan, cutoffs)
    dest = os.path.join(stage, part_name(ref.ordinal, ref.start))
    ranked = _Ranked(ranks)
    with selected(ref, facts, plan, selector, chunk_size) as (source, chunks):
        with ParquetSink(dest, [source], prov, WriteOptions(rank=rank), schema=schema, skip_empty=True) as sink:
            for chunk, mask in chunks:
                ranked.write(sink, chunk, mask)
    return sink.written


@task
def select_tile(refs: list, plan: WorkerPlan, cutoffs: Cutoffs, writing: Writing, tile: tuple,
                ranks: np.ndarray | None = None, facts: list | None = None) -> tuple[int, list[str]]:
    """Write one input tile's kept points as one LAS/LAZ file (its own header), renamed on success;
    ``tile``: (file name, --keep/--drop as it applies to the tile); ``facts``: the spill of each of its
    units. Returns the count written and the writer's notes (what it changed or left out), which the driver
    says as the local run does."""
    stage, prov, chunk_size, rank = writing.stage, writing.prov, writing.chunk_size, writing.rank
    name, selection = tile
    _visible(stage)
    selector = _selector_of(plan, IdSelector(cutoffs.opened()) if isinstance(cutoffs, InFile) else cutoffs)
    first = refs[0]
    ranked = _Ranked(ranks)
    facts = facts or [None] * len(refs)
    try:
        with first.source() as source:
            with open_sink(os.path.join(stage, name), [source], prov,
                           WriteOptions(rank=rank, selection=selection)) as sink:
                sink.quiet = True  # its notes go back to the driver, which says them once the tiles are published
                for ref, spilled in zip(refs, facts):
                    with selected(ref, spilled, plan, selector, chunk_size, source) as (_, chunks):
                        for chunk, mask in chunks:
                            ranked.write(sink, chunk, mask)
    finally:
        ranked.close()
        if isinstance(selector, IdSelector) and selector.file is not None:
            selector.file.close()
    return sink.written, sink.own_notes()
