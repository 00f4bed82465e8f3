"""Flag mode (--flag): every point is written, and the keep decision is recorded
instead of applied. The flagged points are exactly the sample's points."""

import laspy
import numpy as np
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream.errors import UsageError

from conftest import real_file

CASES = ["pdal__autzen_trim.las", "laspy__fullwave.laz", "potree__lion_takanawa.copc.laz"]


def _sampled_records(src, tmp_path, **opts):
    out = tmp_path / "sample.las"
    prism_stream.sample(src, out, **opts)
    return laspy.read(out).points.array


@pytest.mark.parametrize("name", CASES)
def test_extra_bytes_flag_marks_exactly_the_sample(tmp_path, name):
    src = real_file(name)
    opts = dict(ratio=0.02, seed=3)
    out = tmp_path / "flagged.laz"
    summary = prism_stream.sample(src, out, flag="keep", **opts)
    flagged = laspy.read(out)
    original = laspy.read(src)
    assert len(flagged.points) == len(original.points)
    keep = np.asarray(flagged.keep)
    assert set(np.unique(keep)) <= {0, 1} and keep.sum() == summary.kept
    # every original dimension is unchanged, byte for byte
    for dim in original.point_format.dimension_names:
        assert np.array_equal(np.asarray(flagged[dim]), np.asarray(original[dim])), dim
    # the flagged points are the sampled points, in order
    sample = _sampled_records(src, tmp_path, **opts)
    assert original.points.array[keep == 1].tobytes() == sample.tobytes()


@pytest.mark.parametrize("name", CASES[:2])
def test_withheld_flag_marks_exactly_the_dropped_points(tmp_path, name):
    src = real_file(name)
    out = tmp_path / "withheld.las"
    summary = prism_stream.sample(src, out, flag="withheld", ratio=0.05)
    flagged, original = laspy.read(out), laspy.read(src)
    assert flagged.header.point_format.id == original.header.point_format.id
    withheld = np.asarray(flagged.withheld)
    was = np.asarray(original.withheld)
    assert np.all(withheld >= was)  # a kept point keeps its own bit
    dropped = (withheld == 1) & (was == 0)
    assert len(flagged.points) - dropped.sum() == summary.kept
    sample = _sampled_records(src, tmp_path, ratio=0.05)
    assert original.points.array[~dropped].tobytes() == sample.tobytes()


def test_parquet_and_las_flags_agree(tmp_path):
    src = real_file("pdal__warsaw_small.las")
    prism_stream.sample(src, tmp_path / "f.parquet", flag="keep", count=300, mode="paper")
    prism_stream.sample(src, tmp_path / "f.las", flag="keep", count=300, mode="paper")
    a = pq.read_table(tmp_path / "f.parquet")["keep"].to_numpy()
    b = np.asarray(laspy.read(tmp_path / "f.las").keep) == 1
    assert np.array_equal(a, b)


def test_flag_name_that_exists_is_refused(tmp_path):
    with pytest.raises(UsageError, match="already has"):
        prism_stream.sample(real_file("pdal__warsaw_small.las"), tmp_path / "f.las", flag="intensity", ratio=0.1)
    with pytest.raises(UsageError, match="already has"):
        prism_stream.sample(real_file("pdal__warsaw_small.las"), tmp_path / "f.parquet", flag="red", ratio=0.1)
    assert list(tmp_path.iterdir()) == []


def test_ply_flag_marks_exactly_the_sample(tmp_path):
    import plyfile

    src = real_file("open3d__frag_115.ply")
    summary = prism_stream.sample(src, tmp_path / "flagged.ply", flag="keep", ratio=0.05, seed=2)
    prism_stream.sample(src, tmp_path / "sample.ply", ratio=0.05, seed=2)
    flagged = plyfile.PlyData.read(tmp_path / "flagged.ply")["vertex"].data
    sample = plyfile.PlyData.read(tmp_path / "sample.ply")["vertex"].data
    original = plyfile.PlyData.read(src)["vertex"].data
    assert len(flagged) == len(original) and int(flagged["keep"].sum()) == summary.kept
    for name in original.dtype.names:
        assert np.array_equal(flagged[name], original[name]), name
    assert np.array_equal(flagged[flagged["keep"] == 1][list(sample.dtype.names)], sample)
