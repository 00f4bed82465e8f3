"""The baselines keep what they promise: exact counts, real input points, seeded and chunk-free."""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

import oracle
from conftest import random_colors, write_parquet
from prism_stream.errors import OutputExists, UnsupportedFormat, UsageError
from prism_stream.evaluate import Cloud, nss_sample, random_sample, voxel_sample
from prism_stream.evaluate.baselines import (VoxelGrid, estimate_normal_bins, normal_bins, pca_normals,
                                             search_voxel_size)


def cloud_file(tmp_path, xyz, name="in.parquet", seed=0, row_group_size=None):
    n = len(xyz)
    rgb = random_colors(n, seed=seed, palette=30).astype(np.uint8)
    return write_parquet(tmp_path / name, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "red": rgb[:, 0],
                                           "green": rgb[:, 1], "blue": rgb[:, 2], "idx": np.arange(n)},
                         row_group_size=row_group_size)


def kept_idx(path) -> np.ndarray:
    return pq.read_table(path)["idx"].to_numpy()


def blob(n=2000, seed=0):
    return np.random.default_rng(seed).uniform(0, 50, size=(n, 3))


def wavy_surface(n=6000, seed=0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 100, size=(n, 2))
    z = 5 * np.sin(xy[:, 0] / 8) + 3 * np.cos(xy[:, 1] / 5)
    return np.column_stack([xy, z])


# ---------------------------------------------------------------- Random

@pytest.mark.parametrize("seed", [0, 42])
def test_random_keeps_the_T_smallest_spec_priorities(tmp_path, seed):
    src = cloud_file(tmp_path, blob())
    out = tmp_path / "r.parquet"
    res = random_sample(str(src), str(out), ratio=0.1, seed=seed)
    prio = oracle.priority(oracle.point_ids(0, 2000), seed)  # SPEC 3, computed without the library
    want = np.sort(np.argsort(prio)[:200])
    assert res.kept == res.target == 200
    assert np.array_equal(kept_idx(out), want)  # the oracle's set, in input order


def test_random_does_not_depend_on_chunking_and_changes_with_the_seed(tmp_path):
    src = cloud_file(tmp_path, blob(), row_group_size=333)
    outs = []
    for i, (chunk, seed) in enumerate([(1 << 20, 1), (17, 1), (500, 2)]):
        out = tmp_path / f"r{i}.parquet"
        random_sample(str(src), str(out), count=77, seed=seed, chunk_size=chunk)
        outs.append(kept_idx(out))
    assert np.array_equal(outs[0], outs[1])
    assert not np.array_equal(outs[0], outs[2])
    assert all(len(o) == 77 for o in outs)


def test_baseline_output_rows_are_input_rows_unchanged(tmp_path):
    src = cloud_file(tmp_path, blob())
    full = pq.read_table(src)
    for fn, kw in [(random_sample, {"count": 50}), (voxel_sample, {"voxel_size": 10.0}), (nss_sample, {"count": 50})]:
        out = tmp_path / f"{fn.__name__}.parquet"
        fn(str(src), str(out), **kw)
        got = pq.read_table(out)
        assert got.schema.names == full.schema.names
        assert got.equals(full.take(got["idx"]).cast(got.schema))
        assert np.all(np.diff(got["idx"].to_numpy()) > 0)  # input order


# ---------------------------------------------------------------- Voxel grid

def brute_voxel(xyz, size):
    lo = xyz.min(axis=0)
    best = {}
    for i, p in enumerate(xyz):
        ijk = tuple(np.floor((p - lo) / size).astype(int))
        center = lo + (np.array(ijk) + 0.5) * size
        d = float(((p - center) ** 2).sum())
        if ijk not in best or (d, i) < best[ijk]:
            best[ijk] = (d, i)
    return np.sort([i for _, i in best.values()])


@pytest.mark.parametrize("size", [3.0, 7.5])
def test_voxel_grid_keeps_the_point_nearest_each_occupied_voxels_center(tmp_path, size):
    xyz = blob(1500, seed=3)
    src = cloud_file(tmp_path, xyz)
    for chunk in (1 << 20, 101):
        out = tmp_path / f"v{chunk}.parquet"
        res = voxel_sample(str(src), str(out), voxel_size=size, chunk_size=chunk)
        assert np.array_equal(kept_idx(out), brute_voxel(xyz, size))
        assert res.params["voxel_size"] == size


def test_voxel_ties_go_to_the_smaller_id(tmp_path):
    # one voxel of side 4 from (0,0,0), center (2,2,2): ids 1, 2 and 3 all lie at squared distance 3
    xyz = np.array([[0, 0, 0], [3, 3, 3], [1, 1, 1], [3, 3, 3]], float)
    src = cloud_file(tmp_path, xyz)
    voxel_sample(str(src), str(tmp_path / "v.parquet"), voxel_size=4.0)
    assert kept_idx(tmp_path / "v.parquet").tolist() == [1]


def test_voxel_search_lands_near_the_target_and_reports_what_it_reached(tmp_path):
    src = cloud_file(tmp_path, wavy_surface(8000))
    out = tmp_path / "v.parquet"
    res = voxel_sample(str(src), str(out), ratio=0.05)
    assert res.target == 400
    assert abs(res.kept - 400) <= 0.01 * 400 + 1
    assert res.ratio_achieved == res.kept / 8000
    assert len(kept_idx(out)) == res.kept
    with Cloud(str(src)) as c:
        size, n, passes = search_voxel_size(c, 400)
        assert n == res.kept and 1 <= passes <= 4
        assert len(brute_voxel(wavy_surface(8000), size)) == n


def test_voxel_grid_refuses_sizes_it_cannot_index(tmp_path):
    with pytest.raises(UsageError, match="too small"):
        VoxelGrid(np.zeros(3), np.full(3, 1e6), 1e-9)
    with pytest.raises(UsageError, match="positive"):
        VoxelGrid(np.zeros(3), np.ones(3), 0.0)


def test_a_voxel_far_larger_than_the_cloud_is_one_voxel_without_a_warning(tmp_path):
    """--voxel-size 1e300: one voxel, its point the smallest id (every distance to a center that far is inf),
    and no numpy overflow warning on the user's terminal."""
    import warnings

    src = cloud_file(tmp_path, wavy_surface(500))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        voxel_sample(str(src), str(tmp_path / "v.parquet"), voxel_size=1e300)
    assert kept_idx(tmp_path / "v.parquet").tolist() == [0]


# ---------------------------------------------------------------- Normal space sampling

def test_pca_normal_of_a_plane_is_its_normal():
    rng = np.random.default_rng(0)
    uv = rng.normal(size=(50, 10, 2))
    a, b = np.array([1.0, 0, 1]) / np.sqrt(2), np.array([0, 1.0, 0])
    pts = uv[..., :1] * a + uv[..., 1:] * b
    n = pca_normals(pts)
    want = np.cross(a, b)
    assert np.allclose(np.abs(n @ want), 1.0)


def test_normal_bins_are_sign_free_and_cover_the_hemisphere():
    rng = np.random.default_rng(1)
    v = rng.normal(size=(5000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    a, b = normal_bins(v, 4, 8), normal_bins(-v, 4, 8)
    assert np.array_equal(a, b)
    counts = np.bincount(a, minlength=32)
    assert counts.min() > 0 and counts.max() < 2.0 * counts.mean()  # equal-area bins
    assert normal_bins(np.array([[0, 0, 1.0]]), 4, 8)[0] // 8 == 3  # a vertical normal is in the top band


def test_nss_draws_round_robin_across_normal_bins(tmp_path):
    xyz = wavy_surface(5000)
    src = cloud_file(tmp_path, xyz)
    out = tmp_path / "n.parquet"
    res = nss_sample(str(src), str(out), count=300, seed=7, bands=4, sectors=8)
    keep = kept_idx(out)
    assert res.kept == len(keep) == 300
    with Cloud(str(src)) as c:
        cache, _ = estimate_normal_bins(c, str(tmp_path), bands=4, sectors=8)
        bins = np.asarray(cache).copy()
    n_b = np.bincount(bins, minlength=32)
    q_b = np.bincount(bins[keep], minlength=32)
    k = res.params["k_rounds"]
    assert np.all((q_b == np.minimum(n_b, k)) | (q_b == k + 1))  # K full rounds, then one more in E bins
    assert int((q_b == k + 1).sum()) == res.params["extra"]
    # inside a bin, the points taken are those of smallest priority (seeded)
    prio = oracle.priority(oracle.point_ids(0, 5000), 7)  # SPEC 3, computed without the library
    for b in np.flatnonzero((q_b > 0) & (q_b < n_b)):
        members = np.flatnonzero(bins == b)
        assert set(members[np.argsort(prio[members])[:q_b[b]]]) == set(keep[bins[keep] == b])


def test_nss_tiles_agree_with_one_tile_away_from_nothing_but_their_borders(tmp_path):
    xyz = wavy_surface(12000, seed=4)
    src = cloud_file(tmp_path, xyz)
    with Cloud(str(src)) as c:
        one, info1 = estimate_normal_bins(c, str(tmp_path), tile_points=10**7)
        one = np.asarray(one).copy()
        (tmp_path / "t").mkdir()
        many, info = estimate_normal_bins(c, str(tmp_path / "t"), tile_points=1500, overlap=0.1)
        many = np.asarray(many).copy()
    assert info1["tiles"] == 1 and info["tiles"] >= 8
    assert info["spilled_points"] > 12000  # overlaps are read twice: the cost of tiling
    assert (one == many).mean() >= 0.99


def test_nss_does_not_depend_on_chunking(tmp_path):
    src = cloud_file(tmp_path, wavy_surface(3000))
    a, b = tmp_path / "a.parquet", tmp_path / "b.parquet"
    nss_sample(str(src), str(a), ratio=0.05, seed=1)
    nss_sample(str(src), str(b), ratio=0.05, seed=1, chunk_size=97, tile_points=1000)
    assert len(kept_idx(a)) == len(kept_idx(b)) == 150
    # tiles change normals only near tile borders: the samples overlap almost entirely
    assert len(np.intersect1d(kept_idx(a), kept_idx(b))) >= 0.9 * 150


# ---------------------------------------------------------------- Bad input

def test_baselines_refuse_bad_targets_and_outputs(tmp_path):
    src = cloud_file(tmp_path, blob(100))
    out = tmp_path / "o.parquet"
    with pytest.raises(UsageError):
        random_sample(str(src), str(out), ratio=1.5)
    with pytest.raises(UsageError):
        nss_sample(str(src), str(out), count=101)
    with pytest.raises(UsageError):
        voxel_sample(str(src), str(out))
    with pytest.raises(UnsupportedFormat):
        random_sample(str(src), str(tmp_path / "o.txt"), count=5)
    random_sample(str(src), str(out), count=5)
    with pytest.raises(OutputExists):
        random_sample(str(src), str(out), count=5)
    with pytest.raises(UsageError, match="overwrite an input"):
        random_sample(str(src), str(src), count=5, overwrite=True)
    assert not [p for p in tmp_path.iterdir() if "prism-tmp" in p.name]


def test_nss_with_more_neighbours_than_points_is_a_usage_error_and_a_large_k_stays_bounded(tmp_path, monkeypatch):
    """--nss-k above the cloud's points is refused in one line from its header, before any row (it asked for
    90 GiB); a k the cloud holds is queried as many rows at a time as QUERY_BYTES allows (k = 5,000 over
    110,000 points asked for 4.1 GiB at once), with the same normal bins as one query of every row."""
    from prism_stream.errors import UsageError
    from prism_stream.evaluate import baselines, denoise
    from prism_stream.evaluate.run import evaluate

    src = cloud_file(tmp_path, wavy_surface(3000, seed=2))
    rows = []
    with pytest.raises(UsageError, match="more than the cloud's 3,000 points") as caught:
        evaluate([str(src)], ratios=(0.1,), methods=("random", "nss"), nss_k=3001, metrics=False,
                 log=rows.append)
    assert "\n" not in str(caught.value) and str(caught.value).startswith(str(src))
    assert not [r for r in rows if "Random" in str(r)], "a row ran before the refusal"
    asked = []

    class Counted(baselines.cKDTree):
        def query(self, x, k=1, **kw):
            asked.append(len(np.atleast_2d(x)) * k * 16)
            return super().query(x, k=k, **kw)

    with Cloud(str(src)) as c:
        (tmp_path / "whole").mkdir()
        whole = np.asarray(estimate_normal_bins(c, str(tmp_path / "whole"), k=500)[0]).copy()
        monkeypatch.setattr(baselines, "cKDTree", Counted)
        monkeypatch.setattr(denoise, "QUERY_BYTES", 1 << 20)
        (tmp_path / "parts").mkdir()
        parts = np.asarray(estimate_normal_bins(c, str(tmp_path / "parts"), k=500)[0]).copy()
    assert asked and max(asked) <= 1 << 20 and len(asked) > 1
    assert np.array_equal(whole, parts)
    monkeypatch.undo()
    tiny = cloud_file(tmp_path, wavy_surface(6, seed=3))  # the default k = 10 over 6 points: all of them, as before
    nss_sample(str(tiny), str(tmp_path / "tiny.parquet"), ratio=0.5, seed=1)
    assert len(kept_idx(tmp_path / "tiny.parquet")) == 3
