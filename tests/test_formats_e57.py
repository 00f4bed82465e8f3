"""E57 in: every scan, poses applied, colors mapped from the range the file declares.

Files are written with pye57 (libE57Format) and read back independently of
prism-stream's reader; the oracle says which points a run keeps.
"""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream.errors import NoColorError
from prism_stream.formats.e57 import color_map

import oracle
from conftest import edge_file

import pye57

RATIO = 0.3


def scan(n, seed):
    rng = np.random.default_rng(seed)
    palette = rng.integers(0, 256, size=(30, 3)).astype(np.uint8)
    pick = palette[rng.integers(0, 30, n)]
    return {"cartesianX": rng.normal(size=n), "cartesianY": rng.normal(size=n), "cartesianZ": rng.normal(size=n),
            "intensity": rng.random(n).astype(np.float32),
            "colorRed": pick[:, 0], "colorGreen": pick[:, 1], "colorBlue": pick[:, 2]}


def test_every_scan_is_read_with_its_pose(tmp_path):
    path = tmp_path / "two.e57"
    a, b = scan(700, 1), scan(500, 2)
    e57 = pye57.E57(str(path), mode="w")
    e57.write_scan_raw(a, translation=np.array([100.0, -5.0, 2.0]))
    e57.write_scan_raw(b)
    e57.close()
    out = tmp_path / "out.parquet"
    summary = prism_stream.sample(str(path), str(out), ratio=RATIO, seed=4)
    colors = tuple(np.concatenate([a[c], b[c]]) for c in ("colorRed", "colorGreen", "colorBlue"))
    rows = oracle.sample([colors], ratio=RATIO, seed=4).kept[0]
    assert summary.points == 1200
    t = pq.read_table(out)
    assert t.num_rows == len(rows)
    # pye57 stores cartesian coordinates as single-precision floats; the pose is applied in double
    f32 = {k: {c: v[c].astype(np.float32).astype(np.float64) for c in ("cartesianX", "cartesianY")}
           for k, v in (("a", a), ("b", b))}
    x = np.concatenate([f32["a"]["cartesianX"] + 100.0, f32["b"]["cartesianX"]])
    y = np.concatenate([f32["a"]["cartesianY"] - 5.0, f32["b"]["cartesianY"]])
    assert np.allclose(t.column("x").to_numpy(), x[rows], rtol=0, atol=1e-9)
    assert np.allclose(t.column("y").to_numpy(), y[rows], rtol=0, atol=1e-9)
    for c in ("colorRed", "colorGreen", "colorBlue"):
        assert np.array_equal(t.column(c).to_numpy(), colors[("colorRed", "colorGreen", "colorBlue").index(c)][rows])
    got = t.column("intensity").to_numpy()
    want = np.concatenate([a["intensity"], b["intensity"]])[rows]
    assert np.allclose(got, want, atol=1e-6)


def test_sixteen_bit_color_limits_are_mapped_by_the_16_bit_rule(tmp_path):
    path = edge_file("e57data__ColourRepresentation.e57")
    e57 = pye57.E57(str(path))
    header = e57.get_header(0)
    n = header.point_count
    buffers = pye57.libe57.VectorSourceDestBuffer()
    raw = {}
    for c in ("colorRed", "colorGreen", "colorBlue"):
        raw[c] = np.empty(n, np.uint16)
        buffers.append(pye57.libe57.SourceDestBuffer(e57.image_file, c, raw[c], n, True, True))
    reader = header.points.reader(buffers)
    reader.read()
    reader.close()
    e57.close()
    assert raw["colorRed"].max() > 255  # the trap: 8-bit buffers cannot hold these
    out = tmp_path / "out.parquet"
    prism_stream.sample(str(path), str(out), ratio=RATIO)
    rows = oracle.sample([tuple(raw[c] >> 8 for c in raw)], ratio=RATIO).kept[0]
    t = pq.read_table(out)
    for c in raw:
        assert np.array_equal(t.column(c).to_numpy(), raw[c][rows])


def test_color_map_follows_the_declared_range():
    v = np.array([0, 256, 65280, 65535])
    assert color_map(v, 0, 65535, "f").tolist() == [0, 1, 255, 255]
    assert color_map(np.array([10, 265]), 10, 265, "f").tolist() == [0, 255]
    assert color_map(np.array([0, 511, 1023]), 0, 1023, "f").tolist() == [0, 127, 255]


def test_a_scan_without_color_is_refused():
    with pytest.raises(NoColorError, match="scan 0"):
        prism_stream.plan(str(edge_file("pdal__A_B_different_dims.e57")), ratio=0.5)


def test_without_pye57_the_missing_extra_is_named_with_the_file(tmp_path, monkeypatch):
    """pye57 is an extra: without it, one line naming the file and the install, exit 2 as for --dask or s3://
    without theirs (it was exit 4, "not a format we read", and no file)."""
    from prism_stream.errors import UsageError

    monkeypatch.setitem(__import__("sys").modules, "pye57", None)  # its import then fails
    path = edge_file("e57data__ColourRepresentation.e57")
    with pytest.raises(UsageError) as caught:
        prism_stream.sample(str(path), str(tmp_path / "out.parquet"), ratio=0.5)
    assert caught.value.exit_code == 2 and str(path) in str(caught.value) and ".[e57]" in str(caught.value)
    assert not (tmp_path / "out.parquet").exists()


def test_las_output_takes_e57s_las_extension_fields(tmp_path):
    """E57's LAS extension field ``las:pointSourceId`` is LAS's point_source_id (it was refused after pass one:
    a ':' in a LAS extra-bytes name); every point kept, the values as the E57 holds them."""
    import laspy

    path = edge_file("e57data__ColourRepresentation.e57")
    out = tmp_path / "out.las"
    whole = tmp_path / "whole.parquet"
    prism_stream.sample(str(path), str(out), ratio=1.0)
    prism_stream.sample(str(path), str(whole), ratio=1.0)
    las = laspy.read(out)
    assert np.array_equal(np.asarray(las.point_source_id), pq.read_table(whole).column("las:pointSourceId").to_numpy())
