"""The cutoff reduce on the cluster: bounded per-unit bottom sets, merged in slot-range partitions.

Each unit keeps, per capped bin, only its smallest priorities at or under a
bound the bin's cutoff almost surely lies under (so a unit sends about
q_b/n_b of its points, not all of them). The bottom sets are folded as units
finish (a tree reduce, level by level: :class:`.Folding`) with the core's
bounded merge in partitions of slots; a bin whose bound
proves too low is redone without a bound, so the cutoffs are exact whatever
happens.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from ...core.cutoffs import Cutoffs, Rules, merge_bottoms
from ...core.folding import Folding
from ...core.quotas import Plan
from .cluster import FAN_IN, gather, held, windowed
from .tasks import U64_MAX, merge_bottom_sets_task, pairs, range_cutoffs, unit_bottoms, unit_bottoms_of

BOTTOMS_PER_REDUCER = 1 << 22  # (slot, priority) pairs one cutoff reducer holds at most: 48 MiB
BOUND_SIGMAS = 8.0  # how far above its expected value a bin's cutoff bound sits


def cutoff_bounds(plan: Plan, rules: Rules, sigmas: float = BOUND_SIGMAS) -> np.ndarray:
    """Per capped slot, a priority the bin's cutoff lies under but for a ~``sigmas``-sigma fluke.

    Priorities are uniform 64-bit words, so the number of a bin's n_b points
    under a bound t is Binomial(n_b, t / 2^64); t is set so that this count
    exceeds q_b by ``sigmas`` standard deviations (plus slack for small
    bins). Only an upper bound: :func:`cutoffs` checks it and redoes the bins
    it fails for.
    """
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


def cutoffs(cluster, plan: Plan, rules: Rules, plan_f) -> Cutoffs:
    """Each capped bin's cutoff: bounded unit bottoms, reduced in slot-range partitions; bins the bound failed redone.

    ``cluster`` is the run on the cluster (:class:`.driver.OnCluster`): its client, work units, chunk size,
    tuning (``bound_sigmas``, ``bottoms_per_reducer``), task key and statistics, and each unit's candidate
    spill (``spilled_units``: :class:`.tasks.UnitSpill`, or None), which the bottoms come from instead of a
    second read of the unit."""
    client, run, stats = cluster.client, cluster.key, cluster.stats
    sigmas, per_reducer = cluster.tuning.bound_sigmas, cluster.tuning.bottoms_per_reducer
    unit_spills = cluster.spilled_units()
    caps = rules.caps
    if not len(caps):
        return merge_bottoms(rules, [])
    cut = np.zeros(len(caps), dtype=np.uint64)
    todo = np.ones(len(caps), dtype=bool)  # the slots whose cutoff is still wanted (a mask: np.isin of two
    #                                        5M-slot arrays sorted both, 120 MB over the driver's plan)
    bounds = cutoff_bounds(plan, rules, sigmas)
    weight = np.cumsum(caps)
    parts = max(1, math.ceil(int(weight[-1]) / max(1, per_reducer)))
    stats["cutoff_partitions"] = parts
    edges = [0] + [int(np.searchsorted(weight, weight[-1] * p / parts, side="left")) + 1
                   for p in range(1, parts)] + [len(caps)]
    edges = sorted(set(min(e, len(caps)) for e in edges))
    for attempt in range(2):
        bounds_f = held(client, bounds, f"prism-bounds-{run}-{attempt}")
        ranges = [(lo, hi) for lo, hi in zip(edges[:-1], edges[1:]) if todo[lo:hi].any()]
        merged = _running_bottoms(cluster, attempt, ranges, plan_f, bounds_f, unit_spills)
        results = [(lo, hi, client.submit(range_cutoffs, plan_f, lo, hi, root, key=f"prism-cut-{run}-{attempt}-{p}"))
                   for p, ((lo, hi), root) in enumerate(zip(ranges, merged))]
        del merged
        short = np.zeros(len(caps), dtype=bool)
        for (lo, hi, fut), (missing, values) in zip(results, gather(client, [r[2] for r in results])):
            take = todo[lo:hi].copy()
            take[missing - lo] = False
            cut[lo:hi][take] = values[take]
            short[missing[todo[missing]]] = True
        del results
        todo = short
        redo = int(np.count_nonzero(todo))
        stats["bins_redone"] = stats.get("bins_redone", 0) + redo
        if not redo:
            return Cutoffs(rules.capped_keys.copy(), cut)
        # the bound was too low for these bins (a fluke, or a tiny bound_sigmas): redo them with no bound
        bounds = np.zeros(len(caps), dtype=np.uint64)
        bounds[todo] = U64_MAX
    raise AssertionError("cutoff merge saw fewer points than the histogram counted")


def _running_bottoms(cluster, attempt: int, ranges: list, plan_f, bounds_f, unit_spills) -> list:
    """Each slot range's merged bottoms (futures), the units' bottom sets folded in as they finish
    (:class:`.Folding`, ``FAN_IN`` at a time, level by level, as a tree reduce would): a bounded number of
    units in flight and ``FAN_IN - 1`` sets a level held, where every unit's set at once grew with the
    number of units (9.4M pairs at 240 units, beside the T = 2.4M pairs of the merged sets)."""
    client, refs, chunk_size, run, stats = cluster.client, cluster.refs, cluster.chunk_size, cluster.key, cluster.stats
    merges = itertools.count()

    def folding(lo: int, hi: int, r: int) -> Folding:
        return Folding(lambda *sets: client.submit(merge_bottom_sets_task, plan_f, lo, hi, *sets,
                                                   key=f"prism-bmerge-{run}-{attempt}-{r}-{next(merges)}"), FAN_IN)

    running = [folding(lo, hi, r) for r, (lo, hi) in enumerate(ranges)]
    sizes = []

    def submit(i: int):
        key = f"prism-bottoms-{run}-{attempt}-{i}"
        if unit_spills is None:
            return client.submit(unit_bottoms, refs[i], plan_f, bounds_f, chunk_size, key=key)
        return client.submit(unit_bottoms_of, unit_spills[i], refs[i], plan_f, bounds_f, chunk_size, key=key)

    def finished(_, f) -> None:
        sizes.append(client.submit(pairs, f, key=f"prism-bsize-{f.key}"))  # gathered at the end: no wait a unit
        for sets in running:
            sets.add(f)

    windowed(client, len(refs), submit, finished)
    stats.setdefault("bottoms_pairs", []).append(int(sum(gather(client, sizes))))
    return [sets.result(fold_one=True) for sets in running]  # a unit's own set spans every slot: cut to the range


