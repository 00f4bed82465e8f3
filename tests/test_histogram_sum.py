"""Histograms summed: Histogram.sum and add against a count of the keys themselves, and the running sum of a
cluster's units (RunningHistogram) against merge_units over every unit at once, in any order they finish."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prism_stream.core.folding import Folding
from prism_stream.core import histogram
from prism_stream.core.histogram import (DenseHistogram, Histogram, RunningHistogram, UnitScan, as_histogram, fold,
                                         merge_units)

keys_lists = st.lists(st.lists(st.integers(0, 2**24 - 1) | st.integers(0, 40), max_size=60), max_size=7)


def counted(points: list[int]) -> dict:
    return dict(Counter(points))


def as_dict(h: Histogram) -> dict:
    assert h.keys.dtype == np.uint32 and h.counts.dtype == np.int64
    assert np.all(np.diff(h.keys.astype(np.int64)) > 0) and np.all(h.counts > 0)
    return dict(zip(h.keys.tolist(), h.counts.tolist()))


@settings(max_examples=300, deadline=None)
@given(keys_lists, st.sampled_from([1, 2, 5, None]))
def test_sum_counts_every_key_of_every_part(lists, block):
    """Also summed a range of keys at a time (keyblocks.BLOCK: the bins of each part a range holds, 2^20
    unless made small here)."""
    from prism_stream.core import keyblocks

    parts = [Histogram.from_keys(np.array(k, np.uint32)) for k in lists]
    expected = counted([k for ks in lists for k in ks])
    with pytest.MonkeyPatch.context() as mp:
        if block is not None:
            mp.setattr(keyblocks, "BLOCK", block)
        assert as_dict(Histogram.sum(parts)) == expected
        assert as_dict(Histogram.sum(reversed(parts))) == expected
    total = Histogram.empty()
    for p in parts:
        total = total.add(p)
        assert as_dict(p.add(Histogram.empty())) == counted([int(k) for k in np.repeat(p.keys, p.counts)])
    assert as_dict(total) == expected


@st.composite
def nested_folds(draw, parts):
    """``parts`` folded in a drawn tree: each fold takes a drawn run of the parts and folds left."""
    items = list(parts)
    while len(items) > 1:
        a = draw(st.integers(0, len(items) - 1))
        b = draw(st.integers(a + 1, len(items)))
        items[a:b] = [fold(items[a:b])]
        if b - a == 1 and len(items) > 1:  # a fold of one: join it to its neighbour next
            items[a:a + 2] = [fold(items[a:a + 2])]
    return items[0] if items else fold([])


@settings(max_examples=300, deadline=None)
@given(st.data(), keys_lists, st.sampled_from([12, 10**6]), st.booleans())
def test_folds_in_any_tree_count_every_key_dense_or_not(data, lists, sparse_bytes, big):
    """``fold`` (the cluster's sum) in any tree of folds, dense or sparse as each fold finds smaller (made dense
    at any size by pricing a sparse bin high), counts of any size (``big``: past 2^32, int64 tables), against a
    count of the keys."""
    weight = 2**31 if big else 1
    parts = [Histogram(h.keys, h.counts * weight) for h in (Histogram.from_keys(np.array(k, np.uint32))
                                                             for k in lists)]
    expected = {k: c * weight for k, c in counted([k for ks in lists for k in ks]).items()}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(histogram, "SPARSE_BYTES", sparse_bytes)
        total = data.draw(nested_folds(parts))
    if isinstance(total, DenseHistogram):
        assert total.bins == len(expected) and total.total == sum(expected.values())
        assert total.table.dtype == (np.int64 if sum(expected.values()) >= 2**32 else np.uint32)
    assert as_dict(as_histogram(total)) == expected


def test_a_fold_of_millions_of_bins_is_a_table_and_of_few_is_not():
    rng = np.random.default_rng(1)
    wide = [Histogram.from_keys(rng.integers(0, 2**24, 2_000_000).astype(np.uint32)) for _ in range(4)]
    total = fold(wide)
    assert isinstance(total, DenseHistogram) and total.table.nbytes == 2**24 * 4  # 64 MiB, not ~90 MB sparse
    assert as_dict(as_histogram(total)) == as_dict(Histogram.sum(wide))
    few = [Histogram.from_keys(np.array([0, 2**24 - 1, 5], np.uint32)), Histogram.from_keys(np.array([5], np.uint32))]
    assert isinstance(fold(few), Histogram) and as_dict(fold(few)) == {0: 1, 5: 2, 2**24 - 1: 1}
    assert isinstance(fold([fold(wide), *few]), DenseHistogram)
    # found by a review: parts of one cloud share their colors; four parts of the same 1.5M keys are 1.5M bins,
    # 18 MB sparse, not the 72 MB their bins add up to: no 64 MiB table
    keys = np.sort(rng.choice(2**24, 1_500_000, replace=False)).astype(np.uint32)
    same = fold([Histogram(keys, np.full(len(keys), i + 1, np.int64)) for i in range(4)])
    assert isinstance(same, Histogram) and same.bins == len(keys) and np.all(same.counts == 10)


def test_sum_never_shares_arrays_with_its_parts():
    one = Histogram.from_keys(np.array([3, 3, 9], np.uint32))
    total = Histogram.sum([one, Histogram.empty()])
    total.counts[0] += 5
    assert one.counts.tolist() == [2, 1]


@pytest.mark.parametrize("dtype", [np.int32, np.uint32, np.uint64, np.int64])
def test_add_takes_counts_of_any_integer_type(dtype):
    a = Histogram(np.array([1, 5, 2**32 - 1], np.uint32), np.array([1, 1, 1], dtype))
    b = Histogram(np.array([5, 2**32 - 1], np.uint32), np.array([2, 3], dtype))
    assert as_dict(Histogram.sum([a, b])) == {1: 1, 5: 3, 2**32 - 1: 4}
    assert as_dict(b.add(a)) == as_dict(a.add(b)) == {1: 1, 5: 3, 2**32 - 1: 4}


def test_a_lone_part_is_folded_only_when_asked():
    running = Folding(lambda *parts: ("folded", parts), 4)
    running.add("a")
    assert running.result() == "a" and running.result(fold_one=True) == ("folded", ("a",))


def test_add_inserts_runs_of_new_keys_in_order():
    a = Histogram(np.array([10, 20], np.uint32), np.array([1, 1], np.int64))
    b = Histogram(np.array([1, 2, 11, 12, 13, 20, 30, 31], np.uint32), np.ones(8, np.int64))
    assert as_dict(a.add(b)) == {1: 1, 2: 1, 10: 1, 11: 1, 12: 1, 13: 1, 20: 2, 30: 1, 31: 1}


# ---------------------------------------------------------------- the running sum of a cluster's units

def immediate(func, *args):
    return func(*args)


@st.composite
def units(draw):
    """Files of units, each unit with its own facts (max value, kind) and histogram under its own keys, the
    way a unit scans itself: values <= 255 in integer fields are 8-bit colors until another unit says not."""
    files = draw(st.integers(1, 4))
    out = []
    for ordinal in range(files):
        kind = draw(st.sampled_from(["int", "int", "float"]))
        for _ in range(draw(st.integers(1, 6))):
            points = draw(st.integers(0, 30))
            max_value = draw(st.sampled_from([0, 17, 255, 256, 4000, 65535])) if points else 0
            keys = draw(st.lists(st.integers(0, 200), min_size=points, max_size=points))
            out.append(UnitScan(ordinal, points, max_value, kind if points else None,
                                Histogram.from_keys(np.array(keys, np.uint32))))
    return out


@settings(max_examples=400, deadline=None)
@given(units(), st.randoms(use_true_random=False), st.sampled_from(["auto", "8", "16"]), st.integers(2, 4),
       st.booleans())
def test_the_running_sum_is_merge_units_in_any_finishing_order(scans, rnd, color_depth, fan_in, folded):
    """``folded``: summed as the cluster sums them (:func:`fold`, dense once a table is smaller: here past
    about 85 bins a fold, keys under 256), made sparse at the end."""
    expected, _ = merge_units(scans, color_depth)
    units_of = Counter(s.ordinal for s in scans)
    calls = []

    def submit(func, *args):
        calls.append(len(args))
        return func(*args)

    merge = (lambda *h: fold(h)) if folded else (lambda *h: Histogram.sum(h))
    running = RunningHistogram(submit, merge, units_of, color_depth, fan_in=fan_in)
    order = list(scans)
    rnd.shuffle(order)
    held = 0
    for s in order:
        running.unit_done(s.ordinal, s.points, s.max_value, s.kind, s.histogram)
        held = max(held, running.held())
    assert as_dict(as_histogram(running.total())) == as_dict(expected)
    # at most fan_in - 1 histograms a level (log_fan_in of the units' count) for the decided ones and for
    # each file's waiting ones, whatever the units
    levels = 1 + math.floor(math.log(len(scans), fan_in))
    assert held <= (fan_in - 1) * levels * (1 + len(units_of))
    assert set(calls) <= set(range(2, fan_in + 1)) or calls == [0]  # no fold takes more than fan_in parts


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(0, 1000), max_size=200), st.integers(2, 5))
def test_folding_sums_every_part_once_and_holds_few(values, fan_in):
    folds = []

    def add(*parts):
        folds.append(len(parts))
        return sum(parts)

    running = Folding(add, fan_in)
    most = 0
    for v in values:
        running.add(v)
        most = max(most, len(running))
    assert sum(running.held()) == sum(values)
    assert set(folds) <= {fan_in} and len(folds) == sum(len(values) // fan_in ** j for j in range(1, 12))
    folds.clear()
    assert running.result(7) == sum(values) + 7 and set(folds) <= set(range(2, fan_in + 1))
    assert most <= (fan_in - 1) * (1 + (math.floor(math.log(len(values), fan_in)) if values else 0))


def test_the_running_sum_refuses_an_unfinished_file():
    running = RunningHistogram(immediate, lambda *h: Histogram.sum(h), {0: 2}, "auto")
    running.unit_done(0, 1, 10, "int", Histogram.from_keys(np.array([5], np.uint32)))
    try:
        running.total()
    except AssertionError as exc:
        assert "not done" in str(exc)
    else:
        raise AssertionError("a total before every unit finished")


def test_a_running_sum_lets_its_handles_go_with_it():
    """The handles a RunningHistogram folded (a cluster's futures) go when it goes, without waiting for
    Python's cycle collector: a future still held is still wanted, so when a worker died in pass two the
    scheduler ran pass one's units again (their spill folders were left in the output)."""
    import gc
    import weakref

    class Handle:
        def __init__(self, value):
            self.value = value

    def submit(func, *args):
        return Handle(func(*[a.value for a in args]))

    parts = [Handle(Histogram.from_keys(np.array([i % 3, 7], np.uint32))) for i in range(9)]
    refs = [weakref.ref(p) for p in parts]
    running = RunningHistogram(submit, lambda *h: Histogram.sum(h), {0: 9}, "8")
    for p in parts:
        running.unit_done(0, 2, 200, None, p)
    assert as_dict(running.total().value) == {0: 3, 1: 3, 2: 3, 7: 9}
    gc.disable()
    try:
        del running, parts, p
        assert [r() for r in refs] == [None] * 9
    finally:
        gc.enable()


def test_a_part_out_of_order_is_refused_not_summed_wrong():
    """Histogram.sum merges a range of keys at a time, which needs each part's keys in order (a Histogram's
    promise): a part out of order is a ValueError, never a sum with a key counted twice."""
    from prism_stream.core import keyblocks

    parts = [Histogram(np.array([5, 0, 1], np.uint32), np.array([10, 1, 1], np.int64)),
             Histogram(np.array([0, 1, 2, 3], np.uint32), np.array([10, 100, 1, 1], np.int64))]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(keyblocks, "BLOCK", 2)
        with pytest.raises(ValueError, match="not in order"):
            Histogram.sum(parts)
