"""SPEC 4: the quota rules, on random histograms, against brute force over k."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import oracle
from prism_stream.errors import UsageError
from prism_stream.core.quotas import Options, Plan, solve
from prism_stream.core.histogram import Histogram
from prism_stream.core import kernels

SETTINGS = settings(max_examples=150, deadline=None)
KEY_SPACE = 1 << 24


@st.composite
def histograms(draw, max_bins=40, max_count=300):
    """A sparse histogram: distinct sorted keys in the 24-bit key space, positive counts."""
    counts = draw(st.lists(st.integers(1, max_count), min_size=1, max_size=max_bins))
    keys = draw(st.lists(st.integers(0, KEY_SPACE - 1), min_size=len(counts), max_size=len(counts), unique=True))
    keys, counts = zip(*sorted(zip(keys, counts)))
    return Histogram(np.array(keys, dtype=np.uint32), np.array(counts, dtype=np.int64))


seeds = st.integers(0, (1 << 64) - 1)


def S(counts, k):
    return int(np.minimum(counts, k).sum())


@st.composite
def histogram_and_target(draw):
    h = draw(histograms())
    return h, draw(st.integers(1, h.total))


@SETTINGS
@given(histogram_and_target(), seeds)
def test_exact_keeps_exactly_T(ht, seed):
    h, t = ht
    plan = solve(h, Options(count=t, mode="exact", seed=seed))
    assert plan.kept == int(plan.quotas.sum()) == t
    assert plan.target == t
    assert plan.quotas.tolist() == oracle.quotas(h.counts, h.keys, rule="exact", t=t, seed=seed)[0].tolist()


@SETTINGS
@given(histogram_and_target(), seeds)
def test_exact_quotas_are_K_or_K_plus_one(ht, seed):
    h, t = ht
    plan = solve(h, Options(count=t, mode="exact", seed=seed))
    n, q, big_k = h.counts, plan.quotas, plan.k
    # K is the largest integer with S(K) <= T (brute force, not bisection)
    assert S(n, big_k) <= t
    assert big_k >= int(n.max()) or S(n, big_k + 1) > t
    assert plan.extra == t - S(n, big_k)
    assert np.all(q <= n)
    base = np.minimum(n, big_k)
    bumped = q - base
    assert set(bumped.tolist()) <= {0, 1}
    assert np.all(n[bumped == 1] > big_k)
    assert int(bumped.sum()) == plan.extra


@SETTINGS
@given(histogram_and_target(), seeds)
def test_exact_extra_points_go_to_smallest_bin_priority(ht, seed):
    h, t = ht
    plan = solve(h, Options(count=t, mode="exact", seed=seed))
    n, big_k = h.counts, plan.k
    eligible = np.flatnonzero(n > big_k)
    bp = oracle.bin_priority(h.keys[eligible], seed)
    want = set(eligible[np.argsort(bp)[: plan.extra]].tolist())
    got = set(np.flatnonzero(plan.quotas > np.minimum(n, big_k)).tolist())
    assert got == want


@SETTINGS
@given(histograms(), st.data())
def test_exact_with_target_below_bin_count(h, data):
    """T < B: K = 0 and T bins keep one point each (the T smallest bin priorities)."""
    if h.bins < 2:
        return
    t = data.draw(st.integers(1, h.bins - 1))
    seed = data.draw(seeds)
    plan = solve(h, Options(count=t, mode="exact", seed=seed))
    assert plan.k == 0 and plan.extra == t
    assert sorted(set(plan.quotas.tolist())) == [0, 1]
    chosen = h.keys[plan.quotas == 1]
    smallest = h.keys[np.argsort(oracle.bin_priority(h.keys, seed))[:t]]
    assert set(chosen.tolist()) == set(smallest.tolist())


@SETTINGS
@given(histogram_and_target())
def test_paper_k_star_is_closest_over_all_k(ht):
    h, t = ht
    plan = solve(h, Options(count=t, mode="paper"))
    n = h.counts
    # every k from 1 to well past max n_b: S is flat from max n_b on
    dist = {k: abs(S(n, k) - t) for k in range(1, int(n.max()) + 3)}
    best = min(dist.values())
    assert plan.k == min(k for k, d in dist.items() if d == best)
    assert plan.quotas.tolist() == np.minimum(n, plan.k).tolist()
    assert plan.kept == S(n, plan.k)
    assert plan.extra == 0
    assert plan.k == oracle.quotas(n, h.keys, rule="paper", t=t)[1]


def test_paper_tie_goes_to_smaller_k():
    # two bins of 2: S(1) = 2 and S(2) = 4 are both 1 away from T = 3
    h = Histogram(np.array([5, 9], np.uint32), np.array([2, 2], np.int64))
    assert solve(h, Options(count=3, mode="paper")).k == 1


@SETTINGS
@given(histograms(), st.integers(1, 400))
def test_fixed_k_caps_every_bin(h, k):
    plan = solve(h, Options(k=k))
    assert plan.quotas.tolist() == np.minimum(h.counts, k).tolist()
    assert plan.k == k and plan.target is None


@SETTINGS
@given(histograms(), st.floats(0.0, 1.0, exclude_min=True, allow_nan=False))
def test_ratio_target_rounds_half_up(h, ratio):
    plan = solve(h, Options(ratio=ratio, mode="exact"))
    assert plan.target == math.floor(ratio * h.total + 0.5)
    assert plan.kept == plan.target


@pytest.mark.parametrize("ratio", [0.0, -0.1, 1.0000001, 2.0, float("nan"), float("inf"), -float("inf")])
def test_ratio_outside_unit_interval_is_a_usage_error(ratio):
    with pytest.raises(UsageError):
        Options(ratio=ratio)


@pytest.mark.parametrize("k", [0, -1])
def test_k_below_one_is_a_usage_error(k):
    with pytest.raises(UsageError):
        Options(k=k)


@SETTINGS
@given(histograms(), st.integers(1, 50), st.sampled_from(["exact", "paper"]))
def test_count_above_N_is_a_usage_error(h, more, mode):
    with pytest.raises(UsageError):
        solve(h, Options(count=h.total + more, mode=mode))


def test_count_equal_to_N_keeps_everything():
    h = Histogram(np.array([1, 2, 3], np.uint32), np.array([4, 1, 7], np.int64))
    for mode in ("exact", "paper"):
        plan = solve(h, Options(count=12, mode=mode))
        assert plan.quotas.tolist() == [4, 1, 7]


@pytest.mark.parametrize("kw", [{}, {"ratio": 0.5, "count": 3}, {"ratio": 0.5, "k": 2}])
def test_exactly_one_of_ratio_count_k(kw):
    with pytest.raises(UsageError):
        Options(**kw)


@SETTINGS
@given(histogram_and_target(), seeds, st.sampled_from(["exact", "paper"]),
       st.sampled_from(["rgb", "chroma"]), st.integers(0, 7))
def test_plan_json_round_trip(ht, seed, mode, space, bits):
    h, t = ht
    sources = ({"ordinal": 0, "path": "a.las", "points": h.total, "color_depth": "16"},)
    plan = solve(h, Options(count=t, mode=mode, color_space=space, quant_bits=bits, seed=seed), sources)
    back = Plan.from_json(plan.to_json())
    assert back == plan
    assert back.options == plan.options
    assert (back.points, back.target, back.k, back.extra) == (plan.points, plan.target, plan.k, plan.extra)
    for name in ("keys", "counts", "quotas"):
        a, b = getattr(plan, name), getattr(back, name)
        assert a.dtype == b.dtype and a.tolist() == b.tolist(), name
    assert list(back.sources) == list(sources)
    assert back.seed == seed


@pytest.mark.parametrize("mode, k", [("exact", 0), ("paper", 1)])
def test_an_empty_histogram_keeps_nothing_with_the_rules_k(mode, k):
    """No points: nothing kept; exact mode's K is 0, the paper rule's k* is 1 (the smallest k it considers)."""
    plan = solve(Histogram(np.array([], np.uint32), np.array([], np.int64)), Options(ratio=0.5, mode=mode))
    assert (plan.kept, plan.k, plan.extra, plan.target) == (0, k, 0, 0)
    assert "bin_size" not in plan.summary()


def test_largest_k_within_no_bins_is_zero():
    from prism_stream.core.quotas import count_profile, largest_k_within

    assert largest_k_within(count_profile(np.array([], np.int64)), 5) == 0


@SETTINGS
@given(histograms(max_bins=60, max_count=50), st.integers(0, 60))
def test_the_count_profile_gives_s_of_k_as_brute_force(h, k):
    """S(k) from the distinct counts (what the solve keeps instead of a sorted copy of every bin's count)."""
    from prism_stream.core.quotas import capped_total, count_profile, largest_k_within

    profile = count_profile(h.counts)
    assert capped_total(profile, k) == S(h.counts, k)
    t = S(h.counts, k)
    assert largest_k_within(profile, t) == max(c for c in range(int(h.counts.max()) + 1) if S(h.counts, c) <= t)


@SETTINGS
@given(histograms())
def test_the_summary_gives_the_bin_sizes_spread(h):
    spread = solve(h, Options(ratio=0.5)).summary()["bin_size"]
    counts = np.sort(h.counts)
    assert (spread["min"], spread["max"]) == (counts[0], counts[-1])
    for name, q in (("median", 50), ("p90", 90), ("p99", 99)):
        # linear interpolation between the two nearest counts (numpy's default percentile)
        pos = q / 100 * (len(counts) - 1)
        lo, hi = counts[int(math.floor(pos))], counts[int(math.ceil(pos))]
        assert spread[name] == pytest.approx(lo + (hi - lo) * (pos - math.floor(pos))), name


def test_extras_go_only_to_bins_holding_more_than_k():
    """SPEC 4: counts [1, 2, 3] and T = 4 give K = 1 and one extra, which only the bins of 2 and 3 points
    can take (q_b <= n_b). The bin of one point has the smallest bin priority for about a third of the seeds,
    so an extra offered to bins with n_b >= K (not > K) gives it a second point it does not have."""
    keys = np.array([5, 9, 200], np.uint32)
    counts = np.array([1, 2, 3], np.int64)
    h = Histogram(keys, counts)
    takers = set()
    for seed in range(64):
        plan = solve(h, Options(count=4, seed=seed))
        assert plan.k == 1 and plan.extra == 1
        assert plan.quotas.tolist() == oracle.quotas(counts, keys, rule="exact", t=4, seed=seed)[0].tolist(), seed
        assert plan.quotas[0] == 1 and (plan.quotas <= counts).all(), seed
        takers.add(int(np.flatnonzero(plan.quotas == 2)[0]))
    assert takers == {1, 2}  # the seed decides which bin, as it should
    assert any(int(np.argmin(oracle.bin_priority(keys, s))) == 0 for s in range(64))  # the case the rule guards arises


@settings(max_examples=60, deadline=None)
@given(counts=st.lists(st.integers(1, 6), min_size=1, max_size=80), k=st.integers(0, 5),
       extra=st.integers(1, 80), block=st.integers(1, 9), seed=st.integers(0, 2**64 - 1))
def test_extras_given_a_block_at_a_time_are_the_extra_smallest_bin_priorities(counts, k, extra, block, seed):
    """quotas._give_extras against the plain rule: sort the bins past k by bin priority, the first E get one."""
    from prism_stream.core import quotas as q_mod

    counts = np.array(counts, dtype=np.int64)
    keys = np.sort(np.random.default_rng(len(counts)).choice(1 << 24, len(counts), replace=False)).astype(np.uint32)
    quotas = np.minimum(counts, k)
    q_mod._give_extras(keys, counts, quotas, k, extra, seed, block=block)
    eligible = np.flatnonzero(counts > k)
    prio = kernels.priorities_of_np(keys[eligible].astype(np.uint64), kernels.bin_seed_mix(seed))
    want = np.minimum(counts, k)
    want[eligible[np.argsort(prio)[:extra]]] += 1
    assert np.array_equal(quotas, want)


@settings(max_examples=80, deadline=None)
@given(counts=st.lists(st.one_of(st.integers(1, 70), st.integers(1, 2**40)), min_size=1, max_size=80))
def test_the_bin_spread_is_numpys_percentiles(counts):
    """The summary's bin sizes come from one narrow copy partitioned in place; they are np.percentile's of the
    int64 counts, bit for bit, past 2^32 too."""
    from prism_stream.core.quotas import _spread

    c = np.array(counts, dtype=np.int64)
    pct = np.percentile(c, [0, 50, 90, 99, 100])
    assert _spread(c) == {"min": int(pct[0]), "median": float(pct[1]), "p90": float(pct[2]),
                          "p99": float(pct[3]), "max": int(pct[4])}
    assert np.array_equal(c, np.array(counts, dtype=np.int64))  # the plan's own counts untouched


@settings(max_examples=30, deadline=None)
@given(ht=histogram_and_target(), seed=seeds)
def test_a_plan_without_its_bins_says_what_the_plan_says(ht, seed):
    """:meth:`Plan.without_bins` (what a run's cutoffs and pass two hold) keeps every scalar and total of the
    plan and nothing of its per-bin arrays."""
    h, t = ht
    plan = solve(h, Options(count=t, seed=seed))
    light = plan.without_bins()
    assert light.keys is None and light.counts is None and light.quotas is None
    assert light.summary() == plan.summary() and light.totals == plan.totals
    assert (light.bins, light.kept, light.points, light.k, light.extra) == \
        (plan.bins, plan.kept, plan.points, plan.k, plan.extra)
    assert plan.summary()["bins_capped"] == int(plan.capped.sum())


@settings(max_examples=40, deadline=None)
@given(ht=histogram_and_target(), seed=seeds, sources=st.lists(st.text(max_size=5), max_size=3))
def test_the_plans_json_length_is_known_without_making_it(ht, seed, sources):
    """The Dask driver reports the full plan's JSON size; over 2^24 bins making the JSON for it took 425 MB."""
    h, t = ht
    plan = solve(h, Options(count=t, seed=seed), tuple({"path": s} for s in sources))
    assert plan.json_length() == len(plan.to_json())
