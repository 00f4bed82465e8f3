"""Pass two: keep, in every bin, the points at or under its priority cutoff.

``select(unit, plan, cutoffs)`` is the pure per-unit step: it recomputes
each point's bin key from its colors and the source's color-depth decision
recorded in the plan, so any engine can run it on any unit, in any order.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from . import kernels
from .bins import decided_keys
from .cutoff import Cutoffs, Rules, cutoff_table
from .kernels import ID_SHIFT
from .plan import Plan


class Selector:
    """The dense lookup tables of one plan, ready to mask chunks."""

    def __init__(self, plan: Plan, cutoffs: Cutoffs, rules: Rules | None = None):
        self.plan = plan
        self.rule, self.cut = cutoff_table(plan, cutoffs, rules)
        self.seed_mix = kernels.seed_mix(plan.seed)

    def mask(self, keys: np.ndarray, ordinal: int, start: int) -> np.ndarray:
        """Keep mask of the points ``start, start+1, ...`` of source ``ordinal`` with these keys."""
        first_id = np.uint64((ordinal << ID_SHIFT) | start)
        return kernels.keep_mask(keys, first_id, self.seed_mix, self.rule, self.cut)

    def keys(self, source, chunk) -> np.ndarray:
        decision = self.plan.sources[source.ordinal]["color_depth"]
        return decided_keys(self.plan.spec, chunk.rgb, decision, source.path)


def select(unit, plan: Plan, cutoffs: Cutoffs, chunk_size: int = 1 << 20, selector: Selector | None = None
           ) -> Iterator[tuple[object, np.ndarray]]:
    """(point chunk, keep mask) for every chunk of one work unit."""
    selector = selector or Selector(plan, cutoffs)
    for chunk in unit.point_chunks(chunk_size):
        keys = selector.keys(unit.source, chunk)
        yield chunk, selector.mask(keys, unit.source.ordinal, chunk.start)
