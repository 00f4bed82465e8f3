"""The two passes over one work unit, written once for every engine.

- :func:`scan` (pass one): a unit's color chunks become bin keys, counted
  into a :class:`.histogram.Tally`, with the file's color depth decided as
  the colors stream by (a late switch to 16-bit refiles what was counted).
- :func:`select` (pass two): a unit's point chunks, each with its keep mask.

A unit is records [start, stop) of one source (``formats.base.Unit``). The
engines decide only where these run and how the partial results travel: the
local engine runs them over whole sources with a key cache, the Dask engine
over file ranges on workers, the SQL engine over a query's result.
"""

from __future__ import annotations

from typing import Callable, Iterator

import numpy as np

from ..errors import CorruptInput
from .bins import BinSpec, ColorDepth, decided_keys
from .cutoffs import Cutoffs
from .histogram import Tally, UnitScan, tally_for
from .kernels import ID_SHIFT
from .names import DEFAULT_CHUNK
from .prefetch import prefetched
from .quotas import Plan
from .selection import Selector


def _read_ahead(chunks, unit):
    """Decode the next chunk on a thread while this one is worked on, when the source may use threads."""
    return prefetched(chunks) if getattr(unit.source, "threads", 1) > 1 else chunks


def _check_start(chunk, unit, seen: int) -> None:
    if chunk.start != unit.start + seen:
        raise CorruptInput(f"reader skipped from record {unit.start + seen} to {chunk.start}", unit.source.path)


def _pass_one(unit, chunks, depth: ColorDepth, bar, on_refile):
    """Pass one's loop over a unit, written once: every chunk with its channels prepared for binning.

    Yields (chunk, r, g, b, shift); the streamed color-depth decision calls
    ``on_refile(n)`` when a chunk proves the file 16-bit after ``n`` records
    read as 8-bit. A unit that ends before its declared end is corrupt.
    """
    seen = 0
    for chunk in _read_ahead(chunks, unit):
        _check_start(chunk, unit, seen)
        r, g, b, shift = depth.prepare(*chunk.rgb)
        if depth.refile:
            on_refile(depth.refile)
        yield chunk, r, g, b, shift
        seen += len(chunk)
        if bar is not None:
            bar.update(len(chunk))
    if unit.stop is not None and seen != unit.points:
        raise CorruptInput(f"header declares {unit.points} points but {seen} could be read", unit.source.path)


def scan(unit, spec: BinSpec, color_depth: str = "auto", chunk_size: int = DEFAULT_CHUNK, tally: Tally | None = None,
         bar=None) -> UnitScan:
    """Pass one over one work unit: count its bin keys into ``tally`` (default: its own, dense or sparse).

    Returns the unit's :class:`UnitScan` (points, largest channel value,
    channel kind, and the tally's histogram).
    """
    depth = ColorDepth(color_depth, unit.source.path)
    tally = tally if tally is not None else tally_for(unit.points or 0, spec)
    for _, r, g, b, shift in _pass_one(unit, unit.color_chunks(chunk_size), depth, bar, tally.refile):
        tally.count(spec, r, g, b, shift)
    return UnitScan(unit.source.ordinal, depth.seen, depth.max_value, depth.kind, tally.histogram(), depth.decision)


def scan_held(unit, spec: BinSpec, color_depth: str = "auto", chunk_size: int = DEFAULT_CHUNK,
              bar=None) -> tuple[UnitScan, list]:
    """Pass one of a small input held in memory: (its :class:`UnitScan`, every point chunk with its bin
    keys), with numpy alone (no numba loop is loaded). A late switch to 16-bit sets the keys of every
    chunk held so far to 0, as a refile does."""
    depth = ColorDepth(color_depth, unit.source.path, compiled=False)
    held: list = []

    def refile(n):
        if n != sum(len(k) for _, k in held):
            raise AssertionError(f"{n} points to refile, {sum(len(k) for _, k in held)} held")
        for _, keys in held:
            keys[:] = 0

    for chunk, r, g, b, shift in _pass_one(unit, unit.point_chunks(chunk_size), depth, bar, refile):
        held.append((chunk, spec.keys(r, g, b, shift, compiled=False)))
    return UnitScan(unit.source.ordinal, depth.seen, depth.max_value, depth.kind, None, depth.decision), held


def scan_candidates(unit, candidates, color_depth: str = "auto", chunk_size: int = DEFAULT_CHUNK, spill=None,
                    bar=None) -> UnitScan:
    """Pass one of the one-read path: every attribute read once, counted, and the candidates spilled.

    ``candidates`` is the run's :class:`.candidates.CandidateFilter` (its dense histogram is the
    run's); ``spill`` takes ``begin_source(source)``, ``add(chunk, keys, mask, first_id)``,
    ``log_keys(keys)`` (the keys of a file's points while its color depth is undecided, which a switch
    to 16-bit takes out of the counts; not needed, and not written, when the file's points are the only
    ones the filter has counted) and ``refile(candidates, n)`` (the file proved 16-bit after ``n``
    points); given the filter, ``add`` compacts the spill when it would grow past its mark, whenever no
    point counted may still change bins (and ``due``, ``compact(candidates)`` at a whole file's end).
    A filter without ``undecided_heap`` spills nothing for the outcome "16-bit" of points that may still
    move to key 0 (a cluster unit's, which is read again in that case instead). A spill without
    ``records`` (a plan's dry run) keeps the index alone: the colors alone are read.
    """
    colors_only = not spill.records
    source = unit.source
    depth = ColorDepth(color_depth, source.path)
    candidates.begin_source()
    spill.begin_source(source)
    chunks = unit.color_chunks(chunk_size) if colors_only else unit.point_chunks(chunk_size)
    for chunk, r, g, b, shift in _pass_one(unit, chunks, depth, bar, lambda n: spill.refile(candidates, n)):
        first_id = (source.ordinal << ID_SHIFT) | chunk.start
        keys, mask = candidates.chunk(r, g, b, shift, first_id, depth.undecided and candidates.undecided_heap)
        if depth.undecided and not candidates.first_source:
            spill.log_keys(keys)  # 4 bytes a point, for a switch that rarely comes: only when it is needed
        spill.add(chunk, keys, mask, first_id, None if depth.undecided else candidates)
    if spill.due and (not depth.undecided or unit.start == 0 and unit.stop == source.count):
        spill.compact(candidates)  # a whole file's end decides it (a cluster's unit may be only part of one)
    return UnitScan(source.ordinal, depth.seen, depth.max_value, depth.kind, None, depth.decision,
                    not depth.undecided)


def unit_keys(unit, plan: Plan, chunk_size: int = DEFAULT_CHUNK) -> Iterator[tuple[int, np.ndarray]]:
    """(first record, bin keys) of every chunk of a unit, its source's color depth decided in the plan.

    The cutoff step of an engine that keeps no key cache (a cluster's units).
    """
    source = unit.source
    decision = plan.sources[source.ordinal]["color_depth"]
    for chunk in _read_ahead(unit.color_chunks(chunk_size), unit):
        yield chunk.start, decided_keys(plan.spec, chunk.rgb, decision, source.path)


def select(unit, plan: Plan, cutoffs: Cutoffs | None = None, chunk_size: int = DEFAULT_CHUNK,
           selector: Selector | None = None, keys_of: Callable[[int, int], np.ndarray] | None = None,
           bar=None) -> Iterator[tuple[object, np.ndarray]]:
    """Pass two over one work unit: (point chunk, keep mask) for every chunk, in input order.

    ``keys_of(start, n)`` gives the keys pass one cached for records
    [start, start + n) (the local engine); without it the keys are computed
    again from the colors and the source's recorded color-depth decision.
    A source whose second read may differ from its first (a re-run query)
    has its cached keys checked against the colors.
    """
    selector = selector or Selector(plan, cutoffs)
    source = unit.source
    decision = plan.sources[source.ordinal]["color_depth"] if keys_of is None or source.reread_may_differ else None
    seen = 0
    for chunk in _read_ahead(unit.point_chunks(chunk_size), unit):
        n = len(chunk)
        _check_start(chunk, unit, seen)
        if keys_of is None:
            keys = decided_keys(plan.spec, chunk.rgb, decision, source.path)
        else:
            keys = keys_of(chunk.start, n)
            if len(keys) != n or (source.reread_may_differ and
                                  not np.array_equal(keys, decided_keys(plan.spec, chunk.rgb, decision, source.path))):
                raise CorruptInput(f"{source.changed}: pass two read other points than pass one", source.path)
        yield chunk, selector.mask(keys, source.ordinal, chunk.start)
        seen += n
        if bar is not None:
            bar.update(n)
    if unit.stop is not None and seen != unit.points:
        raise CorruptInput(f"{source.changed}: pass two read {seen} points, pass one {unit.points}", source.path)
