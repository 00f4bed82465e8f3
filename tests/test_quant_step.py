"""--quant-step: the authors' float quantization step, the same strata in every engine (SPEC 2, step variant).

The oracle computes each point's stratum from the definition, one point at a
time in plain Python, then the SPEC selection (smallest priority per bin, the
exact quota rule) in memory; every engine must keep exactly that set.
"""

from __future__ import annotations

import math

import numpy as np
import pyarrow.parquet as pq
import pytest

import prism_stream
from conftest import write_parquet
from prism_stream.core.bins import BinSpec
from prism_stream.errors import UsageError


def splitmix64(x):
    m = (1 << 64) - 1
    z = (x + 0x9E3779B97F4A7C15) & m
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & m
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & m
    return z ^ (z >> 31)


def oracle_level(v, s, q, chroma):
    if chroma:
        return 0 if s == 0 else math.floor((255.0 * v) / (s * q) + 0.5)
    return math.floor(v / q + 0.5)


def oracle_bin(rgb, q, chroma):
    s = sum(rgb)
    return tuple(oracle_level(v, s, q, chroma) for v in rgb)


def oracle_exact(rgb, q, chroma, target, seed):
    """SPEC 4 exact rule and SPEC 5 selection on the step strata, in memory."""
    bins = {}
    for i, c in enumerate(rgb.tolist()):
        bins.setdefault(oracle_bin(c, q, chroma), []).append(i)
    sizes = {b: len(v) for b, v in bins.items()}
    K = 0
    while sum(min(n, K + 1) for n in sizes.values()) <= target:
        K += 1
    extra = target - sum(min(n, K) for n in sizes.values())
    w = max(1, math.floor(255.0 / q + 0.5).bit_length())
    key = {b: (b[0] << 2 * w) | (b[1] << w) | b[2] for b in bins}
    mix1 = splitmix64(seed + 1)
    bigger = sorted((b for b in bins if sizes[b] > K), key=lambda b: splitmix64(key[b] ^ mix1))
    quota = {b: min(sizes[b], K) for b in bins}
    for b in bigger[:extra]:
        quota[b] += 1
    mix = splitmix64(seed)
    keep = []
    for b, ids in bins.items():
        keep += sorted(ids, key=lambda i: (splitmix64(i ^ mix), i))[:quota[b]]
    return sorted(keep)


def cloud(tmp_path, n=2500, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, size=(25, 3))
    rgb = np.clip(base[rng.integers(0, 25, n)] + rng.integers(-9, 10, size=(n, 3)), 0, 255).astype(np.uint8)
    rgb[:4] = [[0, 0, 0], [255, 255, 255], [1, 2, 3], [3, 3, 3]]
    xyz = rng.uniform(0, 10, size=(n, 3))
    path = write_parquet(tmp_path / "in.parquet", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "red": rgb[:, 0],
                                                   "green": rgb[:, 1], "blue": rgb[:, 2], "idx": np.arange(n)},
                         row_group_size=600)
    return path, rgb


@pytest.mark.parametrize("space, q", [("rgb", 2.0), ("rgb", 4.0), ("rgb", 2.5), ("chroma", 1.0), ("chroma", 2.0),
                                      ("chroma", 4.0), ("chroma", 3.3)])
def test_step_keys_follow_the_definition(space, q):
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, size=(3000, 3))
    rgb[:3] = [[0, 0, 0], [255, 255, 255], [1, 0, 0]]
    spec = BinSpec(space, 0, q)
    keys = spec.keys(rgb[:, 0], rgb[:, 1], rgb[:, 2], 0)
    r, g, b = spec.channels(keys)
    want = [oracle_bin(c, q, space == "chroma") for c in rgb.tolist()]
    assert [tuple(t) for t in np.column_stack([r, g, b]).tolist()] == want


def test_step_one_is_the_unquantized_key_and_16_bit_shifts_first():
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 256, size=(4000, 3))
    for space in ("rgb", "chroma"):
        a = BinSpec(space, 0, 1.0).keys(*rgb.T, 0)
        b = BinSpec(space, 0).keys(*rgb.T, 0)
        assert np.array_equal(a, b)
        c = BinSpec(space, 0, 4.0)
        assert np.array_equal(c.keys(*(rgb.T * 257), 8), c.keys(*rgb.T, 0))


@pytest.mark.parametrize("space, q", [("rgb", 4.0), ("chroma", 2.0), ("chroma", 2.5)])
def test_every_engine_keeps_the_oracles_points(tmp_path, space, q):
    src, rgb = cloud(tmp_path)
    want = oracle_exact(rgb, q, space == "chroma", 250, 7)
    local = tmp_path / "local.parquet"
    prism_stream.sample(str(src), str(local), count=250, color_space=space, quant_step=q, seed=7, chunk_size=333)
    assert sorted(pq.read_table(local)["idx"].to_pylist()) == want

    from prism_stream.engines.sql import sample_query

    sql = tmp_path / "sql.parquet"
    sample_query(f"SELECT * FROM read_parquet('{src}')", str(sql), count=250, color_space=space, quant_step=q,
                 seed=7)
    assert sorted(pq.read_table(sql)["idx"].to_pylist()) == want

    distributed = pytest.importorskip("distributed")
    from prism_stream.engines import dask as dask_engine

    out = tmp_path / "dask"
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        dask_engine.sample(client, str(src), str(out), count=250, color_space=space, quant_step=q, seed=7,
                           unit_size=700)
    assert sorted(dask_engine.read_dataset(str(out))["idx"].to_pylist()) == want


@pytest.mark.parametrize("kw", [dict(quant_step=0.5), dict(quant_step=float("nan")), dict(quant_step=2.0, quant_bits=1)])
def test_bad_steps_are_usage_errors(tmp_path, kw):
    src, _ = cloud(tmp_path, n=100)
    with pytest.raises(UsageError, match="--quant-step|--quant-bits"):
        prism_stream.sample(str(src), str(tmp_path / "o.parquet"), ratio=0.1, **kw)
