"""The numpy twins of the numba loops (``core/kernels.py``) compute the same values.

A small input held in memory runs on the twins alone, so that the numba
loops never load; its output is the streaming path's only if every twin
agrees with its loop on every input, which these property tests check
(against the pure-Python splitmix64 too).
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from prism_stream.core import kernels

SETTINGS = settings(max_examples=150, deadline=None)
U64 = st.integers(0, 2**64 - 1)


@SETTINGS
@given(ids=st.lists(U64, max_size=300), seed=U64)
def test_priorities_match_the_loop_and_the_reference(ids, seed):
    ids = np.array(ids, dtype=np.uint64)
    mix = kernels.seed_mix(seed)
    got = kernels.priorities_of_np(ids, mix)
    assert np.array_equal(got, kernels.priorities_of(ids, mix))
    assert [int(v) for v in got] == [int(kernels.splitmix64_scalar(int(i) ^ int(mix))) for i in ids]


@SETTINGS
@given(n=st.integers(0, 400), wide=st.booleans(), shift=st.sampled_from([0, 8]), chroma=st.booleans(),
       bits=st.integers(0, 7), seed=st.integers(0, 2**32 - 1))
def test_bin_keys_match_the_loop(n, wide, shift, chroma, bits, seed):
    rng = np.random.default_rng(seed)
    dtype = np.uint16 if wide else np.uint8
    top = 65536 if (wide and shift) else 256
    r, g, b = (rng.integers(0, top, n).astype(dtype) for _ in range(3))
    if n:
        r[0] = g[0] = b[0] = 0  # r + g + b = 0: chroma's special case
    want = kernels.bin_keys(r, g, b, shift, chroma, bits)
    got = kernels.bin_keys_np(r, g, b, shift, chroma, bits)
    assert got.dtype == np.uint32 and np.array_equal(got, want)


@SETTINGS
@given(values=st.lists(st.tuples(*[st.integers(-2**31, 2**31 - 1)] * 3), max_size=200),
       dtype=st.sampled_from([np.uint8, np.int8, np.uint16, np.int16, np.int32, np.int64]))
def test_channel_range_matches_the_loop(values, dtype):
    """Any integer type a Parquet column may hold, negative values included (they are refused after)."""
    info = np.iinfo(dtype)
    a = np.clip(np.array(values, dtype=np.int64).reshape(-1, 3), info.min, info.max).astype(dtype)
    r, g, b = a[:, 0], a[:, 1], a[:, 2]
    assert tuple(int(v) for v in kernels.channel_range(r, g, b)) == kernels.channel_range_np(r, g, b)
