"""The spatial scan with its points on disk (``engines/spatial_disk.py``): the in-memory scan's order, and the
oracle's, for any cap on the cells held, any file size loaded whole and any fan-out of the routing.

Small caps and files send small clouds down every path a large target takes: the top scan alone (its level
already has T cells), one routing into files loaded whole, and files too large to load, scanned again and
routed again (by cells of a finer level, or of the same level by another hash)."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import oracle
from prism_stream.core import space
from prism_stream.core.kernels import priorities_of_np, seed_mix
from prism_stream.engines.spatial_disk import DiskScan
from test_space import clouds


class _Rarity:
    """Each point's rarity by its bin key (the key here is the point's index)."""

    def __init__(self, rarity):
        self.rarity = rarity

    def of(self, keys):
        return self.rarity[np.asarray(keys, np.int64)]


def _disk_order(folder, xyz, rarity, ids, seed, t, chunk, cap, leaf, fan):
    scan = DiskScan(t, str(folder), _Rarity(rarity), seed_mix(seed), cap, leaf=leaf, fan=fan)
    keys = np.arange(len(ids), dtype=np.uint32)
    for a in range(0, len(ids), chunk):
        scan.add(xyz[a:a + chunk], keys[a:a + chunk], ids[a:a + chunk])
    return scan.order(seed), scan


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                   HealthCheck.function_scoped_fixture])
@given(cloud=clouds(), chunk=st.sampled_from([7, 100, 1 << 20]), cap=st.integers(8, 40),
       leaf=st.integers(1, 120), fan=st.integers(2, 5))
def test_the_order_on_disk_is_the_oracles(tmp_path, cloud, chunk, cap, leaf, fan):
    xyz, rarity, ids, seed, t = cloud
    folder = tmp_path / f"run{len(os.listdir(tmp_path))}"
    folder.mkdir()
    want = ids[oracle.spatial_order(xyz, rarity, oracle.priority(ids, seed), t, seed)]
    got, _ = _disk_order(folder, xyz, rarity, ids, seed, t, chunk, cap, leaf, fan)
    assert np.array_equal(got, want)
    assert os.listdir(folder) == []  # every file it wrote is gone


def _city(n, seed=3):
    """Streets of points 1 cm apart, a few dense blobs and far outliers: many levels between the cells a
    small cap tracks and the first level with T cells."""
    rng = np.random.default_rng(seed)
    parts = [np.round(rng.uniform(0, 200, (n // 2, 3)) * [1, 1, 0.05], 2),
             rng.normal(50, 0.01, (n // 4, 3)), rng.normal(-3000, 1e-4, (n // 8, 3)),
             rng.uniform(-1e6, 1e6, (n - n // 2 - n // 4 - n // 8, 3))]
    xyz = np.concatenate(parts)[rng.permutation(n)] + [500_000.0, 4_000_000.0, 0.0]
    return xyz, rng.integers(1, 50, n).astype(np.uint64), np.arange(n, dtype=np.uint64)


@pytest.mark.parametrize("t", [5, 3_000, 20_000])
def test_a_large_cloud_routed_twice_is_the_in_memory_order(tmp_path, t):
    xyz, rarity, ids = _city(60_000)
    prio = priorities_of_np(ids, seed_mix(11))
    mem = space.SpatialScan(t)
    mem.add(xyz, rarity, prio, ids)
    want = mem.order(11)
    got, scan = _disk_order(tmp_path, xyz, rarity, ids, 11, t, 10_000, cap=256, leaf=2_000, fan=4)
    assert np.array_equal(got, want)
    if t > 256:  # the top scan stopped coarser than the last level: the points were routed, some twice
        assert scan.routed > len(ids)
    assert os.listdir(tmp_path) == []
