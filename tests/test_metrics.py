"""The measures are what their definitions say: each against brute force on small clouds."""

from __future__ import annotations

import laspy
import numpy as np
import pyarrow.parquet as pq
import pytest

from conftest import edge_file, random_colors, real_file, write_parquet
from prism_stream.evaluate import Cloud, chamfer_distance, hausdorff_distance, random_sample, read_sample
from prism_stream.evaluate.cloud import arrow_coordinates
from prism_stream.evaluate.metrics import NotASubset, color_entropy_gain, entropy_bits, sample_distances
from prism_stream.evaluate.plots import chroma_histogram
from prism_stream.core.histogram import Histogram


def brute_one_sided(a, b):
    """min over b of ||a_i - b|| for every a_i, by full pairwise distances."""
    d = np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(axis=2))
    return d.min(axis=1)


def brute_entropy(labels):
    _, c = np.unique(labels, return_counts=True)
    p = c / c.sum()
    return float(-(p * np.log2(p)).sum())


def small_cloud(tmp_path, n=600, seed=0, name="cloud.parquet"):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(n, 3)) * [5.0, 3.0, 1.0]
    rgb = random_colors(n, seed=seed, palette=40)
    path = write_parquet(tmp_path / name, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                                           "red": rgb[:, 0].astype(np.uint8), "green": rgb[:, 1].astype(np.uint8),
                                           "blue": rgb[:, 2].astype(np.uint8), "idx": np.arange(n)})
    return path, xyz, rgb


def test_entropy_is_shannon_in_bits():
    assert entropy_bits([5, 5, 5, 5, 5, 5, 5, 5]) == pytest.approx(3.0)
    assert entropy_bits([7]) == 0.0
    assert entropy_bits([]) == 0.0
    rng = np.random.default_rng(1)
    labels = rng.integers(0, 50, size=3000) ** 2 % 37
    _, counts = np.unique(labels, return_counts=True)
    assert entropy_bits(np.concatenate([counts, [0, 0]])) == pytest.approx(brute_entropy(labels))


def test_entropy_gain_is_output_minus_input():
    inp = Histogram(np.array([1, 2, 3, 4], np.uint32), np.array([97, 1, 1, 1], np.int64))
    out = Histogram(np.array([1, 2, 3, 4], np.uint32), np.array([1, 1, 1, 1], np.int64))
    assert color_entropy_gain(inp, out) == pytest.approx(2.0 - brute_entropy([1] * 97 + [2, 3, 4]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_chamfer_and_hausdorff_match_brute_force_both_ways(seed):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-10, 10, size=(300, 3))
    q = rng.uniform(-8, 12, size=(70, 3))
    pq_, qp = brute_one_sided(p, q), brute_one_sided(q, p)
    assert chamfer_distance(p, q) == pytest.approx(pq_.mean() + qp.mean(), rel=1e-12)
    assert hausdorff_distance(p, q) == pytest.approx(max(pq_.max(), qp.max()), rel=1e-12)
    assert chamfer_distance(p, q) == pytest.approx(chamfer_distance(q, p), rel=1e-12)


@pytest.mark.parametrize("chunk", [37, 1 << 20])
def test_streamed_distances_of_a_subset_equal_the_full_equation(tmp_path, chunk):
    path, xyz, _ = small_cloud(tmp_path)
    keep = np.random.default_rng(5).choice(len(xyz), size=45, replace=False)
    q = xyz[keep]
    with Cloud(path, chunk_size=chunk) as cloud:
        d = sample_distances(cloud, q)
    assert d.chamfer == pytest.approx(brute_one_sided(xyz, q).mean() + brute_one_sided(q, xyz).mean(), rel=1e-12)
    assert brute_one_sided(q, xyz).max() == 0.0  # why the one-pass formula holds
    assert d.hausdorff == pytest.approx(brute_one_sided(xyz, q).max(), rel=1e-12)
    assert d.chamfer == pytest.approx(chamfer_distance(xyz, q), rel=1e-12)
    assert (d.input_points, d.sample_points) == (len(xyz), len(q))


def test_a_sample_that_is_not_a_subset_is_refused(tmp_path):
    path, xyz, _ = small_cloud(tmp_path)
    q = np.vstack([xyz[:10], [[1e3, 1e3, 1e3]]])
    with Cloud(path) as cloud, pytest.raises(NotASubset, match="1 sample points are not input points"):
        sample_distances(cloud, q)


def test_sample_histogram_counts_the_kept_colors(tmp_path):
    path, xyz, rgb = small_cloud(tmp_path)
    out = tmp_path / "s.parquet"
    with Cloud(path) as cloud:
        random_sample(cloud, str(out), count=120, seed=3)
        s = read_sample(str(out), cloud)
        idx = pq.read_table(out)["idx"].to_numpy()
        assert np.array_equal(s.xyz, xyz[idx])
        key = (rgb[idx, 0] << 16) | (rgb[idx, 1] << 8) | rgb[idx, 2]
        assert entropy_bits(s.histogram.counts) == pytest.approx(brute_entropy(key))
        full = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
        assert entropy_bits(cloud.histogram().counts) == pytest.approx(brute_entropy(full))


def test_sample_colors_are_binned_with_the_inputs_color_depth(tmp_path):
    """A 16-bit (v << 8) LAS: the sample's colors go through v >> 8 like the input's did."""
    src = real_file("pdal__warsaw_small.las")
    las = laspy.read(src)
    out = tmp_path / "s.parquet"
    with Cloud(str(src)) as cloud:
        random_sample(cloud, str(out), count=500, seed=0)
        s = read_sample(str(out), cloud)
        assert cloud.decisions == {0: "16"}
    t = pq.read_table(out)
    key = ((t["red"].to_numpy().astype(np.int64) >> 8) << 16) | ((t["green"].to_numpy() >> 8) << 8) \
        | (t["blue"].to_numpy() >> 8)
    assert entropy_bits(s.histogram.counts) == pytest.approx(brute_entropy(key))
    assert s.points == 500 and len(las.points) == 3000


def test_chroma_histogram_is_hsv_hue_and_saturation():
    from matplotlib.colors import rgb_to_hsv

    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 256, size=(2000, 3))
    rgb[:20] = rgb[:20, :1]  # some greys (no hue)
    keys = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
    hist = Histogram.from_keys(keys)
    got = chroma_histogram(hist, 36, 10)
    hsv = rgb_to_hsv(rgb / 255.0)
    # matplotlib's float hue can land a hair below a cell edge (2/3 of a sextant is 19.999...96 cells);
    # nudging by 1e-9 puts edge colors where exact arithmetic does, and moves nothing else
    want = np.zeros((36, 10), np.int64)
    np.add.at(want, (np.minimum((hsv[:, 0] * 36 + 1e-9).astype(int) % 36, 35),
                     np.minimum((hsv[:, 1] * 10 + 1e-9).astype(int), 9)), 1)
    assert np.array_equal(got, want)


def test_geoparquet_wkb_points_read_as_the_xyz_column():
    xyz = arrow_coordinates(pq.read_table(edge_file("pdal__1.2-with-color.parquet")).to_batches()[0])
    wkb = arrow_coordinates(pq.read_table(edge_file("pdal__1.2-with-color_wkb.parquet")).to_batches()[0])
    assert xyz.shape == (1065, 3)
    assert np.array_equal(xyz, wkb)


def test_a_list_column_that_is_not_coordinates_leaves_the_search_to_the_next_one():
    """Found by a review: a `points` list of text, or a fixed-size list of two, stopped the search before the
    WKB geometry beside it; it is said only when no other column holds coordinates. A list of numbers of any
    length is coordinates by its type (as DuckDB writes FLOAT[3]): rows of two are refused, WKB or not (the
    schema decides, the same for every chunk; a later review)."""
    import struct

    import pyarrow as pa
    import pytest

    from prism_stream.errors import UnsupportedFormat

    wkb = pa.array([b"\x01" + struct.pack("<I", 1001) + struct.pack("<3d", 1, 2, 3)], pa.binary())
    others = [pa.array([["a", "b", "c"]]), pa.array([[1.0, 2.0]]),
              pa.FixedSizeListArray.from_arrays(pa.array([1.0, 2.0]), 2)]
    for col in (others[0], others[2]):
        batch = pa.RecordBatch.from_arrays([col, wkb], ["points", "geometry"])
        assert arrow_coordinates(batch).tolist() == [[1.0, 2.0, 3.0]]
    for columns in ([others[1]], [others[1], wkb]):
        with pytest.raises(UnsupportedFormat, match="'points' holds lists that are not 3 numbers"):
            arrow_coordinates(pa.RecordBatch.from_arrays(columns, ["points", "geometry"][:len(columns)]),
                              "f.parquet")
    with pytest.raises(UnsupportedFormat, match="not numbers"):
        arrow_coordinates(pa.RecordBatch.from_arrays([others[0]], ["points"]), "f.parquet")
    # found by a second hostile test: a null row of a fixed-size list was flattened away, and every later
    # point took its neighbour's coordinates
    holed = pa.FixedSizeListArray.from_arrays(pa.array([1.0, 2.0, 3.0, 0, 0, 0, 7.0, 8.0, 9.0]), 3,
                                              mask=pa.array([False, True, False]))
    with pytest.raises(UnsupportedFormat, match="'xyz' holds null rows"):
        arrow_coordinates(pa.RecordBatch.from_arrays([holed], ["xyz"]), "f.parquet")
    lists = pa.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])  # a list of 3 numbers a row is coordinates
    assert arrow_coordinates(pa.RecordBatch.from_arrays([lists], ["xyz"])).tolist() == [[1, 2, 3], [4, 5, 6]]
