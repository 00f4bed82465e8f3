"""A cluster unit's scan-time candidates hold every point of the unit the run can select (issue 14).

The Dask engine's units keep, per bin, the ``unit_cap`` smallest priorities
of their own points, the cap taken from the unit's counts alone
(``core.cutoffs.unit_cap``), so the cutoff reduce reads no unit again. The
promise, for any split of the cloud into units and every rule: the union
of the units' candidates contains every point the oracle (tests/oracle.py)
selects. Priorities are distinct (splitmix64 is a bijection), so a point is
named by its priority.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from prism_stream.core import kernels
from prism_stream.core.cutoffs import unit_cap, unit_candidates
from prism_stream.core.histogram import Histogram

import oracle

SETTINGS = settings(max_examples=120, deadline=None)


def keys_of(rgb) -> np.ndarray:
    r, g, b = (rgb[:, i].astype(np.uint32) for i in range(3))
    return (r << 16) | (g << 8) | b


@SETTINGS
@given(n=st.integers(1, 3_000), palette=st.integers(1, 60), units=st.integers(1, 7), seed=st.integers(0, 2**64 - 1),
       rule=st.sampled_from(["ratio", "paper", "count", "k"]), ratio=st.floats(0.001, 1.0), k=st.integers(1, 6),
       data=st.data())
def test_the_units_candidates_hold_the_sample(n, palette, units, seed, rule, ratio, k, data):
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    colors = rng.integers(0, 256, (palette, 3))
    rgb = colors[np.minimum(rng.geometric(0.15, n) - 1, palette - 1)].astype(np.uint16)
    options = {"ratio": dict(ratio=ratio), "paper": dict(ratio=ratio, mode="paper"),
               "count": dict(count=max(1, int(ratio * n))), "k": dict(k=k)}[rule]
    result = oracle.sample([(rgb[:, 0], rgb[:, 1], rgb[:, 2])], seed=seed, **options)
    selected = set(oracle.priority(oracle.point_ids(0, n)[result.kept[0]], seed).tolist())
    keys = keys_of(rgb)
    cuts = sorted(set(rng.integers(0, n + 1, units - 1).tolist()) | {0, n})
    found = set()
    for a, b in zip(cuts[:-1], cuts[1:]):
        part = keys[a:b]
        histogram = Histogram.from_keys(part)
        cap = unit_cap(histogram.counts, k if rule == "k" else None, None if rule == "k" else result.target)
        _, prios = unit_candidates(part, histogram, a, kernels.seed_mix(seed), cap)
        found.update(prios.tolist())
    assert selected <= found


def test_unit_cap_is_the_largest_k_within_t_plus_one():
    counts = np.array([5, 3, 1, 1])  # S(1) = 4, S(2) = 6, S(3) = 8, S(4) = 9, S(5) = 10
    assert [unit_cap(counts, None, t) for t in (3, 4, 5, 6, 8, 9, 10, 50)] == [1, 2, 2, 3, 4, 5, 5, 5]
    assert unit_cap(counts, 2, None) == 2
    assert unit_cap(np.zeros(0, np.int64), None, 3) == 0
