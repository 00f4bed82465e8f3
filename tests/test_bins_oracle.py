"""bins.BinSpec and decided_keys against the independent oracle (SPEC 1 and 2).

Written for the survivors of the first `make mutate` (docs/MUTATION.md): the
chroma switch of ``BinSpec.keys`` without counts (the path of pass two in
every engine, through ``decided_keys``), ``channels`` (the key unpacking), the
16-bit shift of ``decided_keys`` and the 0..7 bounds of the quantization bits
were pinned by no test. Expectations come from tests/oracle.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from prism_stream.core.bins import BinSpec, ColorDepth, decided_keys
from prism_stream.errors import UsageError

import oracle

SPEC_COLORS = np.array([(0, 0, 0), (255, 255, 255), (10, 20, 30), (200, 100, 50), (1, 0, 0), (128, 128, 127)])


def colors8(n=3000, seed=5):
    rgb = np.random.default_rng(seed).integers(0, 256, size=(n, 3))
    return np.concatenate([SPEC_COLORS, rgb]).astype(np.uint16)


@pytest.mark.parametrize("space", ["rgb", "chroma"])
@pytest.mark.parametrize("bits", [0, 1, 4, 7])
def test_keys_with_and_without_counts_are_the_oracles(space, bits):
    c = colors8()
    r, g, b = c[:, 0], c[:, 1], c[:, 2]
    spec = BinSpec(space, bits)
    want = oracle.bin_keys(r, g, b, space, bits)
    assert np.array_equal(spec.keys(r, g, b), want)  # the default shift is 0
    counts = np.zeros(spec.key_space, dtype=np.int64)
    assert np.array_equal(spec.counted_keys(r, g, b, 0, counts), want)
    assert np.array_equal(counts, np.bincount(want, minlength=spec.key_space))


@pytest.mark.parametrize("bits", [0, 3, 7])
def test_channels_unpack_the_key(bits):
    c = colors8().astype(np.int64)
    spec = BinSpec("rgb", bits)
    keys = oracle.bin_keys(c[:, 0], c[:, 1], c[:, 2], "rgb", bits)
    got = spec.channels(keys)
    for j in range(3):
        assert np.array_equal(got[j], c[:, j] >> bits)


@pytest.mark.parametrize("space", ["rgb", "chroma"])
def test_decided_keys_follow_the_decision(space):
    spec = BinSpec(space, 0)
    c8 = colors8()
    c16 = (c8.astype(np.uint32) * 257).astype(np.uint16)
    for stored, decision in ((c8, "8"), (c16, "16")):
        channels = (stored[:, 0], stored[:, 1], stored[:, 2])
        (r, g, b), got_decision = oracle.to_8bit(channels)
        assert got_decision == decision
        assert np.array_equal(decided_keys(spec, channels, decision, "x"), oracle.bin_keys(r, g, b, space))
    floats = tuple(c8[:, j] / 255.0 for j in range(3))
    (r, g, b), _ = oracle.to_8bit(floats)
    assert np.array_equal(decided_keys(spec, floats, "float", "x"), oracle.bin_keys(r, g, b, space))


@pytest.mark.parametrize("bits", [-1, 8])
def test_quantization_bits_outside_0_7_are_refused(bits):
    with pytest.raises(UsageError, match="0..7"):
        BinSpec("rgb", bits)


@pytest.mark.parametrize("bits", [0, 7])
def test_quantization_bits_at_the_bounds_are_taken(bits):
    assert BinSpec("rgb", bits).width == 8 - bits


def test_signed_and_unsigned_channels_together_are_integer_colors():
    depth = ColorDepth("auto", "x")
    r = np.array([10, 200], np.int16)
    g = np.array([20, 30], np.uint16)
    b = np.array([0, 255], np.uint8)
    out = depth.prepare(r, g, b)
    assert out[3] == 0 and depth.decision == "8"
