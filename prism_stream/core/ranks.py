"""PRISM ranks: the order in which exact-mode samples take their points, so that any prefix is a sample.

For a fixed seed, exact-mode samples nest: the sample for T + 1 is the one
for T and one more point. With K the largest k such that S(K) <= T and
E = T - S(K) (SPEC 4), going from T to T + 1 either gives the next bin (by
bin priority) among those holding more than K points its (K+1)-th point,
or, once every such bin has it, makes K one larger with nothing else
changing. So every point has a rank, the T at which it enters (0-based):
with j its position by priority within its bin (1-based) and B_j the bins
holding at least j points, ordered by bin priority,

    rank = S(j - 1) + (position of its bin in B_j),

and the sample for any T is exactly the points of rank < T.

The points of rank < T_max are the exact sample for T_max. In that set
every layer j < K+1 is whole (|B_j| points) and layer K+1 is a prefix of
B_{K+1} by bin priority, so sorting the set by (j, bin priority) puts each
point at its rank: ranking a sample needs its points' bins and priorities
only, not the rest of the cloud.

:func:`rank_sample` does that with two numpy sorts (about 40 bytes a
point); :func:`..engines.ranking.rank_sample_duckdb` with DuckDB's window
functions, which spill to disk, so that ranking all N points of a large
cloud stays within a memory limit.
"""

from __future__ import annotations

import numpy as np

from . import kernels
from .quotas import Plan, bin_priorities

class BinOrder:
    """Each bin of a plan by its place in bin-priority order, and the points' priorities, for ranking."""

    def __init__(self, plan: Plan):
        if plan.options.rule != "exact":
            raise ValueError("ranks exist for exact mode only")
        self.plan = plan
        self.bins = plan.bins
        order = np.argsort(bin_priorities(plan.keys, plan.seed), kind="stable")
        self.place = np.empty(self.bins, dtype=np.uint32)
        self.place[order] = np.arange(self.bins, dtype=np.uint32)
        self.seed_mix = kernels.seed_mix(plan.seed)

    def of(self, keys: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(bin place, priority) of points with these bin keys and ids."""
        at = np.searchsorted(self.plan.keys, keys)
        return self.place[at], kernels.priorities_of(np.ascontiguousarray(ids, dtype=np.uint64), self.seed_mix)


def rank_sample(place: np.ndarray, priority: np.ndarray, bins: int) -> np.ndarray:
    """Ranks (int64) of the points of an exact sample, given each one's bin place and priority.

    ``place[i]`` is point i's bin by bin priority (0 = the smallest), ``priority[i]``
    its priority; the points must be a whole exact sample (the points of rank < T
    for some T), in any order. The ranks come back in the same order.
    """
    n = len(place)
    place = place.astype(np.int64)
    by_bin = np.lexsort((priority, place))  # by bin, then priority
    b = place[by_bin]
    starts = np.flatnonzero(np.concatenate([[True], b[1:] != b[:-1]])) if n else np.zeros(0, np.int64)
    layer = np.arange(n, dtype=np.int64) - np.repeat(starts, np.diff(np.append(starts, n)))  # j - 1
    if n and int(layer.max()) < (1 << 62) // max(bins, 1):
        by_rank = np.argsort(layer * bins + b, kind="stable")
    else:
        by_rank = np.lexsort((b, layer))
    ranks = np.empty(n, dtype=np.int64)
    ranks[by_bin[by_rank]] = np.arange(n, dtype=np.int64)
    return ranks
