"""Cutoffs within a memory bound whatever T is (issue 26): the capped bins in groups whose quotas fit the
heap words at hand, a scan each, and a radix select for a bin whose quota alone does not fit. Every way
agrees with an in-memory oracle: each capped bin's q_b-th smallest priority, by a sort."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from prism_stream import Options, solve
from prism_stream.core import cutoffs as cut_mod
from prism_stream.core import kernels
from prism_stream.core.histogram import Histogram


def _oracle(rules, keys, ids) -> np.ndarray:
    prios = kernels.priorities_of_np(ids, rules.seed_mix)
    out = np.zeros(len(rules.caps), np.uint64)
    for slot, (key, cap) in enumerate(zip(rules.capped_keys, rules.caps)):
        out[slot] = np.sort(prios[keys == key])[cap - 1]
    return out


def _case(n, bins, skew, seed, **opts):
    rng = np.random.default_rng(seed)
    weights = rng.random(bins) ** skew + 1e-3
    keys = rng.choice(np.arange(bins, dtype=np.uint32) * 7 + 3, size=n, p=weights / weights.sum()).astype(np.uint32)
    plan = solve(Histogram.from_keys(keys), Options(seed=seed, **opts))
    return cut_mod.Rules(plan), keys


@settings(max_examples=40, deadline=None)
@given(n=st.integers(1, 3000), bins=st.integers(1, 40), skew=st.sampled_from([0.5, 1, 4]),
       ratio=st.sampled_from([0.01, 0.2, 0.6]), words=st.integers(1, 400), seed=st.integers(0, 2**31),
       first=st.sampled_from([0, 1 << 40, (5 << 40) + 2**33]), chunk=st.integers(1, 700))
def test_groups_and_radix_agree_with_the_oracle(n, bins, skew, ratio, words, seed, first, chunk):
    rules, keys = _case(n, bins, skew, seed, ratio=ratio)
    ids = np.uint64(first) + np.arange(n, dtype=np.uint64)
    want = _oracle(rules, keys, ids)
    scans = []

    def feed_runs(finder):  # consecutive ids, as the two-read path's key cache gives them
        scans.append(1)
        for a in range(0, n, chunk):
            finder.add(keys[a:a + chunk], first + a)

    def feed_ids(finder):  # explicit ids, as a spill index gives them (a spill skips points)
        for a in range(0, n, chunk):
            finder.add_ids(keys[a:a + chunk], ids[a:a + chunk])

    got = cut_mod.cutoffs_by_groups(rules, feed_runs, words)
    assert np.array_equal(got.cut, want) and np.array_equal(got.keys, rules.capped_keys)
    assert np.array_equal(cut_mod.cutoffs_by_groups(rules, feed_ids, words).cut, want)
    groups = cut_mod.slot_groups(rules.caps, words, cut_mod.FINDER_SLOT_WORDS)  # a slot's offset and fill count
    if len(rules.caps):
        assert len(scans) >= len(groups)
        big = sum(1 for lo, hi in groups if hi - lo == 1 and rules.caps[lo] > words)
        assert big or len(scans) == len(groups)  # a group a scan, radix passes only for a bin too big
        whole = cut_mod.CutoffFinder(rules)
        feed_runs(whole)
        assert np.array_equal(whole.result().cut, want)


def test_groups_hold_at_most_their_words():
    caps = np.array([5, 5, 5, 20, 1, 1, 1, 30, 2], dtype=np.int64)
    groups = cut_mod.slot_groups(caps, 10)
    assert groups == [(0, 2), (2, 3), (3, 4), (4, 7), (7, 8), (8, 9)]
    for lo, hi in groups:
        assert caps[lo:hi].sum() <= 10 or hi - lo == 1
    assert cut_mod.slot_groups(caps, 10**9) == [(0, len(caps))]
    assert cut_mod.slot_groups(np.zeros(0, np.int64), 10) == []


def test_a_bin_past_the_words_is_found_without_holding_its_quota(monkeypatch):
    """One bin of 200,000 points keeping 50,000, with room for 1,000 words: radix passes, and the final
    selection holds fewer than 1,000 priorities."""
    n = 200_000
    keys = np.full(n, 9, np.uint32)
    plan = solve(Histogram.from_keys(keys), Options(count=50_000, seed=11))
    rules = cut_mod.Rules(plan)
    held = []
    real = cut_mod.PriorityCounter._count

    def spy(self, prios):
        real(self, prios)
        if self.keep:
            held.append(sum(len(k) for k in self.kept))

    monkeypatch.setattr(cut_mod.PriorityCounter, "_count", spy)

    def feed(finder):
        for a in range(0, n, 10_000):
            finder.add(keys[a:a + 10_000], a)

    got = cut_mod.cutoffs_by_groups(rules, feed, words=1_000)
    want = _oracle(rules, keys, np.arange(n, dtype=np.uint64))
    assert np.array_equal(got.cut, want)
    assert held and max(held) <= 1_000


def test_a_short_scan_is_caught():
    rules, keys = _case(500, 5, 1, 3, ratio=0.1)
    half = len(keys) // 2

    def feed(finder):
        finder.add(keys[:half], 0)

    with pytest.raises(AssertionError):
        cut_mod.cutoffs_by_groups(rules, feed, words=10)
    with pytest.raises(AssertionError):
        cut_mod.cutoffs_by_groups(rules, feed, words=1)


def test_a_group_finder_holds_arrays_of_its_group_alone():
    """A group's finder takes the memory of its own slots (over millions of capped bins, a finder as long as
    all of them was the cutoff phase's peak), and its cuts land in the caller's array."""
    rules, keys = _case(20_000, 300, 1, 5, ratio=0.2)
    n = len(rules.caps)
    assert n > 100
    ids = np.arange(len(keys), dtype=np.uint64)
    want = _oracle(rules, keys, ids)
    lo, hi = n // 3, n // 3 + 40
    finder = cut_mod.CutoffFinder(rules, lo, hi)
    assert len(finder.offsets) == len(finder.fill) == len(finder.caps) == hi - lo
    assert len(finder.heaps) == int(rules.caps[lo:hi].sum())
    finder.add_ids(keys, ids)
    out = np.zeros(n, np.uint64)
    finder.cuts(out=out[lo:hi])
    assert np.array_equal(out[lo:hi], want[lo:hi]) and not out[:lo].any() and not out[hi:].any()
    slots, prios = finder.bottoms()
    assert slots.min() == lo and slots.max() == hi - 1 and len(prios) == len(finder.heaps)


@given(counts=st.lists(st.integers(0, 3), min_size=0, max_size=60), block=st.integers(1, 9))
def test_the_histogram_of_a_dense_table_is_the_same_a_block_at_a_time(counts, block):
    dense = np.array(counts, dtype=np.int64)
    got = Histogram.from_dense(dense, block=block)
    keys = np.flatnonzero(dense)
    assert got.keys.dtype == np.uint32 and got.counts.dtype == np.int64
    assert np.array_equal(got.keys, keys) and np.array_equal(got.counts, dense[keys])


def whole_of(plan) -> np.ndarray:
    """The bins a plan keeps whole (every point of a bin with points)."""
    return (plan.quotas == plan.counts) & (plan.counts > 0)


@settings(max_examples=60, deadline=None)
@given(n=st.integers(0, 2000), bins=st.integers(1, 30), skew=st.sampled_from([0.5, 1, 4]),
       ratio=st.sampled_from([0.01, 0.3, 0.9, 1.0]), seed=st.integers(0, 2**31), block=st.integers(1, 9))
def test_the_rules_made_a_block_at_a_time_are_the_plain_tables(n, bins, skew, ratio, seed, block):
    """The rule table (drop, keep all, or a capped bin's slot + 1) is made a block of bins at a time, so that no
    temporary as long as the bins sits beside the plan (over 2^24 bins that was where the cutoff phase peaked);
    the blocks' table is the one made in one step from the plan's masks."""
    rng = np.random.default_rng(seed)
    weights = rng.random(bins) ** skew + 1e-3
    keys = rng.choice(np.arange(bins, dtype=np.uint32) * 7 + 3, size=n, p=weights / weights.sum()).astype(np.uint32)
    plan = solve(Histogram.from_keys(keys), Options(seed=seed, ratio=ratio))
    want = np.zeros(plan.spec.key_space, np.int32)
    want[plan.keys[whole_of(plan)]] = kernels.RULE_KEEP
    capped = (plan.quotas > 0) & (plan.quotas < plan.counts)
    want[plan.keys[capped]] = np.arange(1, int(capped.sum()) + 1, dtype=np.int32)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(cut_mod, "RULES_BLOCK", block)
        got = cut_mod.Rules(plan)
    assert np.array_equal(np.asarray(got.rule), want)
    assert np.array_equal(got.capped_keys, plan.keys[capped]) and np.array_equal(got.caps, plan.quotas[capped])
    assert got.caps.dtype == np.int64
    again = cut_mod.Rules.of_parts(plan.spec.key_space, plan.seed, *got.parts())  # what a Dask worker makes
    assert np.array_equal(np.asarray(again.rule), want) and again.seed_mix == got.seed_mix
    assert np.array_equal(again.capped_keys, got.capped_keys) and np.array_equal(again.caps, got.caps)
    whole, _, _ = got.parts()
    assert whole.dtype == np.uint32 and np.array_equal(whole, plan.keys[whole_of(plan)])


@settings(max_examples=200, deadline=None)
@given(data=st.data(), slots=st.integers(1, 30), parts=st.integers(0, 6), block=st.sampled_from([1, 2, 7, None]),
       ordered=st.booleans())
def test_bottom_sets_merged_a_range_of_slots_at_a_time_hold_each_slots_smallest(data, slots, parts, block, ordered):
    """merge_bottom_sets, the cutoff reduce's merge, against brute force: each slot of [lo, hi) keeps its cap
    smallest priorities of all the parts' pairs, in slot then priority order. Parts in slot order (the
    merge's own results) are merged a range of slots at a time (keyblocks.BLOCK pairs of each part, made
    small here); a part in arrival order (a unit's pairs as read) whole."""
    from prism_stream.core import keyblocks
    from prism_stream.core.cutoffs import merge_bottom_sets

    caps = np.array(data.draw(st.lists(st.integers(1, 4), min_size=slots, max_size=slots)), np.int64)
    lo = data.draw(st.integers(0, slots - 1))
    hi = data.draw(st.integers(lo, slots))
    given_parts = []
    for _ in range(parts):
        pairs = data.draw(st.lists(st.tuples(st.integers(0, slots - 1), st.integers(0, 2**64 - 1)), max_size=25,
                                   unique_by=lambda sp: sp[1]))
        if ordered:
            pairs.sort()
        given_parts.append((np.array([s for s, _ in pairs], np.int64), np.array([p for _, p in pairs], np.uint64)))
    everything = sorted((s, p) for sl, pr in given_parts for s, p in zip(sl.tolist(), pr.tolist()) if lo <= s < hi)
    want = [sp for i, sp in enumerate(everything)
            if sum(1 for s, _ in everything[:i] if s == sp[0]) < caps[sp[0]]]
    with pytest.MonkeyPatch.context() as mp:
        if block is not None:
            mp.setattr(keyblocks, "BLOCK", block)
        got_slots, got_prios = merge_bottom_sets(caps, lo, hi, *given_parts)
    assert got_slots.dtype == np.int64 and got_prios.dtype == np.uint64
    assert list(zip(got_slots.tolist(), got_prios.tolist())) == want
