"""What runs on the workers: the core's steps on one work unit, re-opened from a picklable reference.

Every task is a pure function of its arguments (a unit reference, the plan,
the cutoffs), so a task lost with its worker is simply run again elsewhere.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from ...core.cutoffs import (Cutoffs, Rules, bounded_bottoms, candidate_bottoms, merge_bottom_sets, read_cutoffs,
                             unit_candidates, unit_cap)
from ...core.histogram import Histogram, UnitScan, merge_units
from ...core.kernels import ID_SHIFT, seed_mix
from ...core.passes import scan, scan_keys, select, unit_keys
from ...core.quotas import Plan
from ...core.selection import Selector
from ...errors import OutputError
from ...formats import open_sink, open_source
from ...formats.base import Unit
from ...formats.parquet import ParquetSink
from ...run import remote
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
    """The source's work units (LAZ ranges are whole chunks: see LasSource.units), as picklable refs.

    A remote source's refs carry the URL and the store's options (its endpoint, never credentials:
    each worker has its own), so a worker reads the object itself rather than a path the driver sees.
    """
    if remote.is_remote(source.path):
        options = (*options, ("storage_options", remote.storage_options(source.path)))
    return [UnitRef(source.path, source.ordinal, u.start, u.stop, options) for u in source.units(unit_size)]


# ---------------------------------------------------------------- pass one (worker side)


@task
def scan_unit(ref: UnitRef, spec, color_depth: str, chunk_size: int) -> UnitScan:
    with ref.opened() as unit:
        return scan(unit, spec, color_depth, chunk_size)


@task
def scan_unit_candidates(ref: UnitRef, spec, color_depth: str, chunk_size: int, k: int | None,
                         target: int | None, seed: int) -> tuple:
    """Pass one of a unit that also keeps the points it may contribute to the sample, so the cutoff
    reduce needs no second read: (its scan, (its color-depth decision, candidate keys, priorities)).

    The candidates are each bin's ``unit_cap`` smallest priorities, from the unit's own counts; they are
    valid if the file's depth decision is the unit's (otherwise :func:`unit_bottoms_of` reads again).
    """
    with ref.opened() as unit:
        result, keys = scan_keys(unit, spec, color_depth, chunk_size)
    cap = unit_cap(result.histogram.counts, k, target)
    keys, prios = unit_candidates(keys, result.histogram, (ref.ordinal << ID_SHIFT) | ref.start, seed_mix(seed), cap)
    return result, (result.decision, keys, prios)


def first(pair):
    return pair[0]


def second(pair):
    return pair[1]


def unit_facts(s: UnitScan) -> tuple:
    return s.ordinal, s.points, s.max_value, s.kind


def decided_histogram(s: UnitScan, source_facts: UnitScan, color_depth: str) -> Histogram:
    """The unit's histogram once its file's depth is decided.

    ``source_facts`` is an empty scan carrying the whole file's largest value
    and kind; merged beside it, :func:`merge_units` applies the file's
    decision to this unit exactly as it would with every unit in hand.
    """
    return merge_units([s, source_facts], color_depth)[0]


@task
def merge_histograms(*parts: Histogram) -> Histogram:
    return Histogram.sum(parts)


# ---------------------------------------------------------------- cutoffs (worker side)

U64_MAX = np.uint64((1 << 64) - 1)
_CACHE: dict = {}


def rules_of(plan: Plan) -> Rules:
    """The plan's dense rules, built once per worker process (64 MiB at 0 quantization bits)."""
    hit = _CACHE.get("rules")
    if hit is None or hit[0] is not plan:
        _CACHE.pop("rules", None)
        _CACHE["rules"] = hit = (plan, Rules(plan))
    return hit[1]


def _selector_of(plan: Plan, cutoffs: Cutoffs) -> Selector:
    hit = _CACHE.get("selector")
    if hit is None or hit[0] is not plan or hit[1] is not cutoffs:
        _CACHE.pop("selector", None)
        _CACHE["selector"] = hit = (plan, cutoffs, Selector(plan, cutoffs, rules_of(plan)))
    return hit[2]


def worker_plan(plan: Plan) -> Plan:
    """The plan without its dropped bins: what pass two and the cutoffs need, often far smaller to broadcast.

    Its :class:`Rules` are the full plan's (a bin absent from the plan is
    dropped either way), so the cutoffs and the selection are the same.
    """
    kept = plan.quotas > 0
    return dataclasses.replace(plan, keys=plan.keys[kept], counts=plan.counts[kept], quotas=plan.quotas[kept])


@task
def unit_bottoms(ref: UnitRef, plan: Plan, bounds: np.ndarray, chunk_size: int) -> tuple[np.ndarray, np.ndarray]:
    """The unit's smallest priorities per capped bin, at or under the bin's bound: (slot, priority)."""
    with ref.opened() as unit:
        return bounded_bottoms(rules_of(plan), unit_keys(unit, plan, chunk_size), ref.ordinal, bounds)


@task
def unit_bottoms_of(candidates, ref: UnitRef, plan: Plan, bounds: np.ndarray, chunk_size: int) -> tuple:
    """:func:`unit_bottoms` from the unit's scan-time candidates; read again only if its file's depth
    decision turned out other than the unit's (an 8-bit-looking unit of a 16-bit file)."""
    decision, keys, prios = candidates
    if decision != plan.sources[ref.ordinal]["color_depth"]:
        return unit_bottoms(ref, plan, bounds, chunk_size)
    return candidate_bottoms(rules_of(plan), keys, prios, bounds)


def pairs(bottoms) -> int:
    return len(bottoms[0])


merge_bottom_sets_task = task(merge_bottom_sets)


def range_cutoffs(plan: Plan, lo: int, hi: int, merged) -> tuple[np.ndarray, np.ndarray]:
    """(slots of [lo, hi) the bound failed for, cutoff of every slot) from a partition's merged bottoms."""
    return read_cutoffs(rules_of(plan).caps, lo, hi, merged)


# ---------------------------------------------------------------- pass two (worker side)


def part_name(ordinal: int, start: int) -> str:
    """Parts sort in input order: source ordinal, then first record."""
    return f"{PART_PREFIX}{ordinal:06d}-{start:013d}.parquet"


def _visible(stage: str) -> None:
    if not os.path.isdir(stage):
        raise OutputError("the staging folder is not visible from this worker (is the output on a shared "
                          "filesystem?)", stage)


@task
def unit_kept(ref: UnitRef, plan: Plan, cutoffs: Cutoffs, chunk_size: int) -> tuple[np.ndarray, np.ndarray]:
    """(bin keys, ids) of the unit's kept points, in input order: what the driver ranks."""
    selector = _selector_of(plan, cutoffs)
    keys, ids = [np.zeros(0, np.uint32)], [np.zeros(0, np.uint64)]
    with ref.opened() as unit:
        for start, k in unit_keys(unit, plan, chunk_size):
            at = np.flatnonzero(selector.mask(k, ref.ordinal, start))
            keys.append(k[at])
            ids.append(np.uint64((ref.ordinal << ID_SHIFT) | start) + at.astype(np.uint64))
    return np.concatenate(keys), np.concatenate(ids)


class _Ranked:
    """A unit's ranks handed out in step with the points written."""

    def __init__(self, ranks: np.ndarray | None):
        self.ranks = ranks
        self.at = 0

    def write(self, sink, chunk, mask) -> None:
        if self.ranks is None:
            sink.write(chunk, mask)
            return
        n = int(np.count_nonzero(mask))
        sink.write(chunk, mask, ranks=self.ranks[self.at:self.at + n])
        self.at += n


@task
def select_part(ref: UnitRef, plan: Plan, cutoffs: Cutoffs, stage: str, schema: pa.Schema, prov: dict,
                chunk_size: int, ranks: np.ndarray | None = None, rank: str | None = None) -> int:
    """Write the unit's kept points as its own Parquet part (temporary name, then rename); return the count.

    A unit that keeps nothing leaves no part (and removes one an earlier
    attempt of the same task may have left). ``ranks``: the kept points'
    ranks, written in the column ``rank``.
    """
    _visible(stage)
    selector = _selector_of(plan, cutoffs)
    dest = os.path.join(stage, part_name(ref.ordinal, ref.start))
    ranked = _Ranked(ranks)
    with ref.opened() as unit, ParquetSink(dest, [unit.source], prov, schema=schema, skip_empty=True,
                                           rank=rank) as sink:
        for chunk, mask in select(unit, plan, chunk_size=chunk_size, selector=selector):
            ranked.write(sink, chunk, mask)
    return sink.written


@task
def select_tile(refs: list, plan: Plan, cutoffs: Cutoffs, stage: str, name: str, prov: dict, chunk_size: int,
                ranks: np.ndarray | None = None, rank: str | None = None) -> int:
    """Write one input tile's kept points as one LAS/LAZ file (its own header), renamed on success."""
    _visible(stage)
    selector = _selector_of(plan, cutoffs)
    first = refs[0]
    ranked = _Ranked(ranks)
    with open_source(first.path, first.ordinal, **dict(first.options)) as source:
        with open_sink(os.path.join(stage, name), [source], prov, rank=rank) as sink:
            for ref in refs:
                for chunk, mask in select(Unit(source, ref.start, ref.stop), plan, chunk_size=chunk_size,
                                          selector=selector):
                    ranked.write(sink, chunk, mask)
    return sink.written
