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
        self.plan = plan
        self.rules = rules if rules is not None else Rules(plan)
        self.rule, self.cut = cutoff_table(plan, cutoffs, self.rules)

    def mask(self, keys: np.ndarray, ordinal: int, start: int) -> np.ndarray:
        """Keep mask of the points ``start, start+1, ...`` of source ``ordinal`` with these keys."""
        first_id = np.uint64((ordinal << ID_SHIFT) | start)
        return kernels.keep_mask(keys, first_id, self.rules.seed_mix, self.rule, self.cut)

    def mask_ids(self, keys: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """Keep mask of points with explicit ids (the candidates of a spill)."""
        return kernels.keep_mask_ids(keys, ids, self.rules.seed_mix, self.rule, self.cut)
