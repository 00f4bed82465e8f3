"""The keep decision of pass two: in every bin, the points at or under its priority cutoff.

A :class:`Selector` holds the dense tables of one plan and its cutoffs;
:func:`.passes.select` runs it over a unit's chunks.
"""

from __future__ import annotations

import numpy as np

from . import kernels
from .cutoffs import Cutoffs, Rules, cutoff_table
from .kernels import ID_SHIFT
from .quotas import Plan


class Selector:
    """The dense lookup tables of one plan, ready to mask chunks."""

    def __init__(self, plan: Plan, cutoffs: Cutoffs, rules: Rules | None = None):
        self.rules = rules if rules is not None else Rules(plan)
        self.rule, self.cut = cutoff_table(plan, cutoffs, self.rules)

    def mask(self, keys: np.ndarray, ordinal: int, start: int) -> np.ndarray:
        """Keep mask of the points ``start, start+1, ...`` of source ``ordinal`` with these keys."""
        first_id = np.uint64((ordinal << ID_SHIFT) | start)
        keys = kernels.read_only(keys, np.uint32)  # one compiled type, whoever made the keys
        return kernels.keep_mask(keys, first_id, self.rules.seed_mix, self.rule, self.cut)

    def mask_ids(self, keys: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """Keep mask of points with explicit ids (the candidates of a spill)."""
        keys, ids = kernels.read_only(keys, np.uint32), kernels.read_only(ids, np.uint64)  # one compiled type
        return kernels.keep_mask_ids(keys, ids, self.rules.seed_mix, self.rule, self.cut)


def held_mask(plan: Plan, keys: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Keep mask of points all in hand (a small input held in memory), with numpy alone: in each bin, its
    q_b points of smallest priority (SPEC 5), found by one sort by (bin, priority) instead of cutoffs."""
    keys = np.asarray(keys, dtype=np.uint32)
    quota = plan.quotas[np.searchsorted(plan.keys, keys)]
    prio = kernels.priorities_of_np(ids, kernels.seed_mix(plan.seed))
    order = np.lexsort((prio, keys))
    ranked = keys[order]
    rank = np.empty(len(keys), dtype=np.int64)
    rank[order] = np.arange(len(keys)) - np.searchsorted(ranked, ranked, side="left")
    return rank < quota
