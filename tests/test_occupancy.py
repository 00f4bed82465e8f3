"""The candidate filter reads only the blocks of its key table where a bin may be.

The table has a word for each of 2^24 keys (128 MiB, mapped by the OS only where a bin writes). Its end-of-pass
scans (the histogram, the standing rules of a compaction, the re-admission of bins left without a heap) read the
blocks marked as keys were first seen (``jit._slot``) or given counts, and nothing else: reading the whole table
made the OS map every page of it, 32,000 page faults and 50-100 ms of each streamed run and Dask unit. What must
hold is that no key outside the marked blocks holds anything, whatever path wrote it; the tests check that
against the table itself.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from prism_stream.core import candidates as cand_mod
from prism_stream.core import kernels
from prism_stream.core.histogram import Histogram
from prism_stream.core.kernels import loop_channels
from prism_stream.core.sparse import marked_runs


@settings(max_examples=200, deadline=None)
@given(marks=st.lists(st.booleans(), min_size=1, max_size=40), shift=st.integers(0, 4),
       cut=st.integers(0, 40), block_shift=st.integers(0, 7))
def test_runs_cover_exactly_the_marked_blocks(marks, shift, cut, block_shift):
    size = max(1, (len(marks) << shift) - cut)  # the table may end inside the last block
    block = 1 << block_shift
    runs = marked_runs(np.array(marks, np.uint8), shift, size, block)
    want = set()
    for i, m in enumerate(marks):
        if m:
            want |= set(range(i << shift, min((i + 1) << shift, size)))
    got = [k for a, b in runs for k in range(a, b)]
    assert sorted(got) == sorted(want) and len(got) == len(set(got))  # every marked key once, no other
    assert all(a < b and b - a <= max(block, 1 << shift) for a, b in runs)
    assert [r[0] for r in runs] == sorted(r[0] for r in runs)


def _outside(f) -> int:
    """Nonzero table entries outside the filter's runs (must be none)."""
    inside = np.zeros(len(f.dense), bool)
    for a, b in f.runs():
        inside[a:b] = True
    return int(np.count_nonzero(f.dense[~inside]))


def _truth(f, keys_seen) -> Histogram:
    return Histogram.from_keys(np.concatenate(keys_seen))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), spread=st.sampled_from([1, 40, 256]), budget=st.sampled_from([0, 4096, None]),
       bits=st.sampled_from([0, 3]), chunks=st.integers(1, 4))
def test_every_counted_key_lies_in_a_marked_block(seed, spread, budget, bits, chunks):
    """Colors in one corner of the key space or all over it; a heap pool with room for every bin, for a few
    (then new bins keep no heap, and a widening re-admits them), or for none; the histogram read over the runs
    is the one counted from the keys."""
    rng = np.random.default_rng(seed)
    spec = cand_mod.BinSpec("rgb", bits)
    n = 3_000 * chunks
    kw = {} if budget is None else {"pool_budget": budget}
    f = cand_mod.CandidateFilter(spec, cand_mod.Options(count=max(1, n // 50)), n, **kw)
    seen = []
    for c in range(chunks):
        rgb = rng.integers(0, spread, size=(3_000, 3)).astype(np.uint8)
        keys, _ = f.chunk(*loop_channels(*rgb.T), 0, c * 3_000, False)
        seen.append(keys)
        assert _outside(f) == 0
    got = f.histogram()
    want = _truth(f, seen)
    assert np.array_equal(got.keys, want.keys) and np.array_equal(got.counts, want.counts)


def test_counts_given_before_the_points_and_a_16_bit_rebuild_are_marked():
    """Counts from elsewhere (a Dask unit's priors) and the points a 16-bit switch moves to key 0 are written
    by numpy, not the kernel: their blocks are marked too, and the histogram less the prior is the unit's own."""
    spec = cand_mod.BinSpec("rgb", 0)
    f = cand_mod.CandidateFilter(spec, cand_mod.Options(count=100), 20_000)
    prior_keys = np.array([5, 70_000, (1 << 24) - 1], np.uint32)  # three blocks no point of this unit touches
    prior_counts = np.array([3, 1, 9], np.int64)
    f.count_elsewhere(prior_keys, prior_counts)
    rgb = np.full((1_000, 3), 200, np.uint8)
    keys, _ = f.chunk(*loop_channels(*rgb.T), 0, 0, False)
    assert _outside(f) == 0
    own = f.histogram(Histogram(prior_keys, prior_counts))
    assert own.keys.tolist() == [int(keys[0])] and own.counts.tolist() == [1_000]

    g = cand_mod.CandidateFilter(spec, cand_mod.Options(count=100), 20_000)
    keys, _ = g.chunk(*loop_channels(*rgb.T), 0, 0, False)
    g.uncount(keys[:400])
    g.rebuild(400, iter([]))  # 400 points moved to key 0, whose block no point marked
    assert g.dense[0] & kernels.COUNT_MASK == 400 and _outside(g) == 0
    h = g.histogram()
    assert h.keys.tolist() == [0, int(keys[0])] and h.counts.tolist() == [400, 600]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), spread=st.sampled_from([1, 40, 256]), step=st.sampled_from([None, 2.5]),
       bits=st.sampled_from([0, 3]), refile=st.booleans())
def test_a_tally_over_the_table_marks_what_it_counts(seed, spread, step, bits, refile):
    """The two-read path's tally (a dense table, counted by the kernel, or by numpy for a float step): every
    counted key lies in a marked block, a refile (the points so far go to key 0) included, and the
    histogram read over the marked runs is the one counted from the keys."""
    from prism_stream.core.bins import BinSpec
    from prism_stream.core.histogram import DenseTally
    from prism_stream.core.sparse import table_runs

    rng = np.random.default_rng(seed)
    spec = BinSpec("rgb", 0 if step else bits, step=step)
    tally = DenseTally(spec)
    seen = []
    for _ in range(3):
        rgb = rng.integers(0, spread, size=(2_000, 3)).astype(np.uint8)
        seen.append(tally.count(spec, *loop_channels(*rgb.T), 0))
        if refile and len(seen) == 2:
            tally.refile(4_000)
            seen = [np.zeros(4_000, np.uint32)]
    inside = np.zeros(len(tally.dense), bool)
    for a, b in table_runs(tally.marks, len(tally.dense)):
        inside[a:b] = True
    assert not np.count_nonzero(tally.dense[~inside])
    got, want = tally.histogram(), Histogram.from_keys(np.concatenate(seen))
    assert np.array_equal(got.keys, want.keys) and np.array_equal(got.counts, want.counts)
