"""SPEC 7: the pinned test vectors, against the numba kernels and the oracle.

The numbers below are copied from SPEC.md section 7, never computed here.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import oracle
from conftest import real_file
from prism_stream import sample
from prism_stream.core import kernels

SPLITMIX64_0 = 0xE220A8397B1DCDAF

IDS = [0, 1, 2, 12345, (1 << 40) | 7]
PRIORITIES = {
    0: [0xA706DD2F4D197E6F, 0x08B4FDA8C892B50E, 0xD7CC9674FF5FFA39, 0x7A52563B68FEEF07, 0xB3C704B86519A95D],
    42: [0x57E1FABA65107204, 0xF34FE9248C9342E5, 0x725395388690AE46, 0xCBF6B25960247D3B, 0x6FA0CAF539D18C87],
}

COLORS = [(0, 0, 0), (255, 255, 255), (10, 20, 30), (200, 100, 50), (1, 0, 0), (128, 128, 127)]
KEYS = {
    ("rgb", 0): [0, 16777215, 660510, 13132850, 65536, 8421503],
    ("rgb", 4): [0, 4095, 17, 3171, 0, 2183],
    ("chroma", 0): [0, 5592405, 2839936, 9586980, 16711680, 5592405],
    ("chroma", 1): [0, 693546, 349504, 1200658, 2080768, 693546],
}


def test_splitmix64_of_zero_kernels():
    assert int(kernels.splitmix64_scalar(0)) == SPLITMIX64_0
    assert int(kernels.splitmix64_array(np.zeros(1, np.uint64))[0]) == SPLITMIX64_0
    assert int(kernels.seed_mix(0)) == SPLITMIX64_0


def test_splitmix64_of_zero_oracle():
    assert oracle.splitmix64_int(0) == SPLITMIX64_0
    assert int(oracle.splitmix64(np.zeros(1, np.uint64))[0]) == SPLITMIX64_0


@pytest.mark.parametrize("seed", sorted(PRIORITIES))
def test_priorities_kernels(seed):
    want = np.array(PRIORITIES[seed], dtype=np.uint64)
    ids = np.array(IDS, dtype=np.uint64)
    mix = kernels.seed_mix(seed)
    assert kernels.priorities_of(ids, mix).tolist() == want.tolist()
    # the run-of-consecutive-ids kernel the engine uses on chunks
    assert kernels.priorities(np.uint64(0), 3, mix).tolist() == want[:3].tolist()
    assert kernels.priorities(np.uint64(12345), 1, mix).tolist() == want[3:4].tolist()
    assert kernels.priorities(np.uint64((1 << 40) | 7), 1, mix).tolist() == want[4:].tolist()


@pytest.mark.parametrize("seed", sorted(PRIORITIES))
def test_priorities_oracle(seed):
    assert oracle.priority(np.array(IDS, dtype=np.uint64), seed).tolist() == PRIORITIES[seed]
    assert [oracle.splitmix64_int(i ^ oracle.splitmix64_int(seed)) for i in IDS] == PRIORITIES[seed]


def test_point_id_packs_source_ordinal_above_bit_40():
    assert kernels.ID_SHIFT == 40
    assert oracle.point_ids(1, 8)[7] == (1 << 40) | 7


def test_bin_seed_mix_is_splitmix_of_seed_plus_one():
    for seed in (0, 42, (1 << 64) - 1):
        assert int(kernels.bin_seed_mix(seed)) == oracle.splitmix64_int((seed + 1) % (1 << 64))


@pytest.mark.parametrize("space,bits", sorted(KEYS))
def test_keys_kernels(space, bits):
    c = np.array(COLORS, dtype=np.uint16)
    got = kernels.bin_keys(c[:, 0], c[:, 1], c[:, 2], 0, space == "chroma", bits)
    assert got.tolist() == KEYS[space, bits]


@pytest.mark.parametrize("space,bits", sorted(KEYS))
def test_keys_kernels_from_16bit_fields(space, bits):
    """The same colors stored as v*256 and v*257 give the same keys after >> 8."""
    c = np.array(COLORS, dtype=np.int64)
    for scale in (256, 257):
        s = (c * scale).astype(np.uint16)
        got = kernels.bin_keys(s[:, 0], s[:, 1], s[:, 2], 8, space == "chroma", bits)
        assert got.tolist() == KEYS[space, bits], scale


@pytest.mark.parametrize("space,bits", sorted(KEYS))
def test_keys_oracle(space, bits):
    c = np.array(COLORS)
    assert oracle.bin_keys(c[:, 0], c[:, 1], c[:, 2], space, bits).tolist() == KEYS[space, bits]


# -- autzen_trim: the paper rule overshoots, the exact rule does not --------------------

AUTZEN = "pdal__autzen_trim.las"


@pytest.fixture(scope="module")
def autzen():
    return real_file(AUTZEN)


def test_autzen_plan_numbers(autzen):
    s = sample(str(autzen), None, ratio=0.01, mode="paper")
    assert (s.points, s.bins, s.target) == (110_000, 19_492, 1_100)
    assert (s.k, s.kept) == (1, 19_492)
    assert s.sources[0]["color_depth"] == "8"
    e = sample(str(autzen), None, ratio=0.01, mode="exact")
    assert (e.points, e.bins, e.target) == (110_000, 19_492, 1_100)
    assert (e.k, e.extra, e.kept) == (0, 1_100, 1_100)


def test_autzen_oracle_numbers(autzen):
    colors = oracle.read_las_colors(autzen)
    paper = oracle.sample([colors], ratio=0.01, mode="paper")
    assert (paper.points, paper.bins, paper.target, paper.k, paper.kept_total) == (110_000, 19_492, 1_100, 1, 19_492)
    exact = oracle.sample([colors], ratio=0.01, mode="exact")
    assert (exact.k, exact.extra, exact.kept_total) == (0, 1_100, 1_100)


def test_autzen_exact_keeps_one_point_of_each_lowest_priority_bin(autzen, tmp_path):
    out = tmp_path / "autzen.parquet"
    s = sample(str(autzen), str(out), ratio=0.01, mode="exact", seed=0)
    assert s.kept == 1_100
    t = pq.read_table(out, columns=["red", "green", "blue"])
    assert t.num_rows == 1_100
    kept_keys = oracle.bin_keys(*(t.column(c).to_numpy() for c in ("red", "green", "blue")))
    assert len(np.unique(kept_keys)) == 1_100  # one point per bin

    r, g, b = oracle.read_las_colors(autzen)
    all_keys = np.unique(oracle.bin_keys(r, g, b))
    assert len(all_keys) == 19_492
    smallest = all_keys[np.argsort(oracle.bin_priority(all_keys, 0))[:1_100]]
    assert set(kept_keys.tolist()) == set(smallest.tolist())


# -- beyond the pinned numbers: kernels and oracle agree everywhere ----------------------------

u64 = st.integers(0, (1 << 64) - 1)


@settings(max_examples=200, deadline=None)
@given(st.lists(u64, min_size=1, max_size=50), u64)
def test_priorities_kernels_equal_oracle(ids, seed):
    a = np.array(ids, dtype=np.uint64)
    got = kernels.priorities_of(a, kernels.seed_mix(seed)).tolist()
    assert got == oracle.priority(a, seed).tolist()
    assert got == [oracle.splitmix64_int(i ^ oracle.splitmix64_int(seed)) for i in ids]


@settings(max_examples=100, deadline=None)
@given(u64, st.integers(0, 1 << 40), st.integers(1, 64))
def test_consecutive_priorities_equal_oracle(seed, first, n):
    got = kernels.priorities(np.uint64(first), n, kernels.seed_mix(seed)).tolist()
    assert got == oracle.priority(np.arange(first, first + n, dtype=np.uint64), seed).tolist()


def _round_half_up(num: Fraction) -> int:
    return int((num + Fraction(1, 2)).__floor__())


def test_chroma_is_exact_round_half_up():
    """The oracle's integer chroma equals round-half-up of 255 v / s in exact rationals."""
    rng = np.random.default_rng(0)
    c = np.concatenate([rng.integers(0, 256, size=(3000, 3)), [[1, 1, 0], [3, 0, 0], [1, 2, 3], [5, 5, 6]]])
    got = np.stack(oracle.chroma(c[:, 0], c[:, 1], c[:, 2]), axis=1)
    for (r, g, b), row in zip(c.tolist(), got.tolist()):
        s = r + g + b
        want = [0, 0, 0] if s == 0 else [_round_half_up(Fraction(255 * v, s)) for v in (r, g, b)]
        assert row == want, (r, g, b)


@pytest.mark.parametrize("space", ["rgb", "chroma"])
@pytest.mark.parametrize("bits", range(8))
def test_keys_kernels_equal_oracle(space, bits):
    rng = np.random.default_rng(bits)
    c = rng.integers(0, 256, size=(20_000, 3)).astype(np.uint16)
    c[:5] = [[0, 0, 0], [255, 255, 255], [0, 0, 1], [1, 1, 1], [255, 0, 0]]
    got = kernels.bin_keys(c[:, 0], c[:, 1], c[:, 2], 0, space == "chroma", bits)
    want = oracle.bin_keys(c[:, 0], c[:, 1], c[:, 2], space, bits)
    assert got.tolist() == want.tolist()
    assert int(want.max()) < 1 << (3 * (8 - bits))
