"""PRISM's order and the merge with their arrays on disk (``engines/spatial_merge.py``): the in-memory
steps' results (``spatial.prism_order``, ``space.merge``), for any run and block size of the sorts, and
nothing left in the folder."""

from __future__ import annotations

import os
from types import SimpleNamespace

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from prism_stream.core import space
from prism_stream.engines import spatial, spatial_merge
from prism_stream.engines.spatial_merge import Sizes, _layers, merge_files, prism_order_file
from prism_stream.run.staging import ArrayFile

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                            HealthCheck.too_slow])
SIZES = st.builds(Sizes, st.integers(1, 40), st.integers(1, 12))


def _fresh(tmp_path):
    folder = tmp_path / f"f{len(os.listdir(tmp_path))}"
    folder.mkdir()
    return str(folder)


def _read(f):
    values = f.read(0, f.size).copy()
    f.discard()
    return values


def _merged(*args):
    ids, places, filled = merge_files(*args)
    return _read(ids), _read(places), filled


def _ids(folder, name, values):
    f = ArrayFile(folder, name, np.uint64)
    f.append(np.asarray(values, np.uint64))
    return f


@SETTINGS
@given(data=st.data(), n=st.integers(0, 200), bins=st.sampled_from([1, 3, 40, 1 << 24]), sizes=SIZES,
       seed=st.integers(0, 2**64 - 1))
def test_prism_order_on_disk_is_the_in_memory_order(tmp_path, data, n, bins, sizes, seed):
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    keys = rng.integers(0, bins, n).astype(np.uint32)
    ids = rng.choice(1 << 40, n, replace=False).astype(np.uint64)
    cuts = sorted(data.draw(st.lists(st.integers(0, n), max_size=4)))

    def kept():
        for lo, hi in zip([0] + cuts, cuts + [n]):
            yield keys[lo:hi], ids[lo:hi]

    want = spatial.prism_order(SimpleNamespace(seed=seed), kept)
    folder = _fresh(tmp_path)
    f = prism_order_file(seed, kept, folder, sizes)
    got = f.read(0, f.size)
    f.discard()
    assert np.array_equal(got, want)
    assert os.listdir(folder) == []


@SETTINGS
@given(data=st.data(), t=st.integers(1, 80), a=st.sampled_from([0, 1, 250_000, 500_000, 999_999, 1_000_000]),
       sizes=SIZES, early=st.booleans(), walk=st.sampled_from([1, 2, 5, 1 << 18]))
def test_the_merge_on_disk_is_the_in_memory_merge(tmp_path, data, t, a, sizes, early, walk, monkeypatch):
    """Random orders over ids both share and ids only one has; with ``early``, the spatial order leads with
    PRISM's first ids, shuffled (where a side meets an id the other is about to reach); the walk reading
    ``walk`` places of each order at a time."""
    monkeypatch.setattr(spatial_merge, "WALK", walk)
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    universe = int(rng.integers(t, 3 * t + 3))
    prism = rng.permutation(universe)[:t]
    spatial_ids = rng.choice(universe, int(rng.integers(0, min(universe, t + 5) + 1)), replace=False)
    if early:
        lead = rng.permutation(prism[:int(rng.integers(0, t + 1))])
        spatial_ids = np.concatenate([lead, spatial_ids[~np.isin(spatial_ids, lead)]])
    scale = np.uint64(data.draw(st.sampled_from([1, 2**40 + 7])))  # ids far apart too
    prism, spatial_ids = prism.astype(np.uint64) * scale, spatial_ids.astype(np.uint64) * scale
    want, want_filled = space.merge(spatial_ids, prism, a, t)
    folder = _fresh(tmp_path)
    ids, places, filled = _merged(_ids(folder, "s", spatial_ids), _ids(folder, "p", prism), a, t, folder,
                                      sizes)
    by = np.argsort(want, kind="stable")
    assert np.array_equal(ids, want[by]) and np.array_equal(places, by) and filled == want_filled
    assert os.listdir(folder) == []


def test_a_bins_places_go_on_across_blocks():
    b = np.array([5, 5, 7, 7, 7, 9], np.uint64)
    assert _layers(b, None, 0).tolist() == [0, 1, 0, 1, 2, 0]
    assert _layers(b, np.uint64(5), 3).tolist() == [3, 4, 0, 1, 2, 0]
    assert _layers(b, np.uint64(4), 3).tolist() == [0, 1, 0, 1, 2, 0]
    assert _layers(b[:2], np.uint64(5), 2).tolist() == [2, 3]


def test_a_spatial_id_prism_has_not_reached_is_the_spatial_sides(tmp_path):
    """The spatial order's id at the place PRISM's order would look at next is still the spatial side's."""
    folder = str(tmp_path)
    for sizes in (Sizes(4, 2), Sizes()):
        ids, places, filled = _merged(_ids(folder, "s", [5, 0, 1]), _ids(folder, "p", [0, 2, 3]), 1_000_000,
                                          3, folder, sizes)
        assert ids.tolist() == [0, 1, 5] and places.tolist() == [1, 2, 0] and filled == 3
    ids, places, filled = _merged(_ids(folder, "s", [2, 0]), _ids(folder, "p", [0, 1, 2]), 500_000, 3,
                                      folder, Sizes(1, 1))
    want, want_filled = space.merge(np.array([2, 0], np.uint64), np.array([0, 1, 2], np.uint64), 500_000, 3)
    assert ids.tolist() == sorted(want.tolist()) and filled == want_filled
    assert os.listdir(folder) == []
