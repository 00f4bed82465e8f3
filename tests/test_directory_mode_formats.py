"""Directory mode writes one output per input; each holds that input's share of one global sample.

A PLY header states its vertex count before the vertices, and an input's
share is known only after pass two: every output format must still agree
with the Parquet output of the same run, point for point.
"""

from __future__ import annotations

import shutil

import numpy as np
import plyfile
import pyarrow.parquet as pq
import pytest

import prism_stream

from conftest import real_file

INPUTS = ("pdal__autzen_trim.las", "pdal__warsaw_small.las")


@pytest.fixture(scope="module")
def tiles(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiles")
    for name in INPUTS:
        shutil.copy(real_file(name), folder / name)
    return folder


@pytest.mark.parametrize("fmt", ["ply", "las"])
def test_each_output_holds_its_inputs_share(tiles, tmp_path, fmt):
    ref = prism_stream.sample(str(tiles), str(tmp_path / "pq") + "/", ratio=0.01, seed=4, output_format="parquet")
    got = prism_stream.sample(str(tiles), str(tmp_path / fmt) + "/", ratio=0.01, seed=4, output_format=fmt)
    assert got.kept == ref.kept == sum(len(pq.read_table(p)) for p in ref.outputs)
    for want, path in zip(ref.outputs, got.outputs):
        table = pq.read_table(want)
        if fmt == "ply":
            vertices = plyfile.PlyData.read(path)["vertex"].data
            assert len(vertices) == table.num_rows  # the header's count is the share actually written
            assert np.allclose(vertices["x"], table.column("x").to_numpy())
        else:
            import laspy

            las = laspy.read(path)
            assert las.header.point_count == len(las.points) == table.num_rows
            assert np.array_equal(np.asarray(las.red), table.column("red").to_numpy())


@pytest.mark.parametrize("staged, public", [
    ("/tmp/a/.out.ply.host-1-abc.prism-tmp/out.ply", "/tmp/a/out.ply"),
    ("/tmp/o/..prism-staging.host-2-def.prism-tmp/sub/t.ply", "/tmp/o/sub/t.ply"),
    (".o.ply.host-3-x.prism-tmp/o.ply", "o.ply"),
    ("out.ply", "out.ply"),
    ("/x/out.ply", "/x/out.ply"),
])
def test_notices_name_where_a_staged_output_is_published(staged, public):
    from prism_stream.run.staging import public_name

    assert public_name(staged) == public
