"""`prism-stream info` (issue 28): every format in tests/data, its JSON held to the file's own header read by
another library (laspy, plyfile, pyarrow), and to the points where a target makes it read them."""

from __future__ import annotations

import json
import os

import laspy
import numpy as np
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

import prism_stream

from conftest import REAL, cli, random_colors, write_las, write_parquet

CLOUDS = sorted(p.name for p in REAL.iterdir())


def info_json(capsys, *args) -> dict:
    code, out, err = cli(capsys, "info", *args, "--json")
    assert code == 0, err
    return json.loads(out)


def _no_decoding(monkeypatch):
    """info without a target reads headers only: any chunk read fails the test."""
    from prism_stream.formats import READERS

    def decoded(*_, **__):
        raise AssertionError("info decoded points")

    for reader in set(READERS.values()):
        monkeypatch.setattr(reader, "color_chunks", decoded, raising=False)
        monkeypatch.setattr(reader, "point_chunks", decoded, raising=False)


@pytest.mark.parametrize("name", CLOUDS)
def test_each_real_cloud_as_its_header_says(capsys, monkeypatch, name):
    path = REAL / name
    _no_decoding(monkeypatch)
    d = info_json(capsys, path)
    (f,) = d["files"]
    assert f["path"] == str(path) and f["bytes"] == os.path.getsize(path) and d["points"] == f["points"]
    assert len(f["color_columns"]) == 3 and set(f["color_columns"]) <= set(f["columns"])
    if name.endswith((".las", ".laz")):
        with laspy.open(str(path)) as r:
            h = r.header
            assert f["points"] == h.point_count and f["point_format"] == h.point_format.id
            assert f["version"] == str(h.version)
            assert f["bounds"] == {"min": list(map(float, h.mins)), "max": list(map(float, h.maxs))}
            try:
                crs = h.parse_crs()
            except Exception:  # noqa: BLE001 - an empty WKT VLR (the COPC tile): no CRS, as info says
                crs = None
            assert (f["crs"] is None) == (crs is None)
            if crs is not None:
                assert f["crs"]["epsg"] == crs.to_epsg() and f["crs"]["name"] == crs.name
            dims = set(h.point_format.dimension_names)
        assert f["color_depth_by_type"].startswith("8 or 16")
        assert {"intensity", "classification"} <= set(f["columns"]) and len(f["columns"]) == len(dims)
    elif name.endswith(".ply"):
        import plyfile

        vertex = plyfile.PlyData.read(str(path))["vertex"]
        assert f["points"] == vertex.count and f["bounds"] is None and f["crs"] is None
        assert list(f["columns"]) == [p.name for p in vertex.properties]
        assert f["color_depth_by_type"] == "8"
    else:  # PCD: its header's POINTS less the NaN points, which the describe() part counts
        assert f["format"] == "pcd" and f["points"] == f["points_declared"] - f["nan_points_skipped"]
        assert list(f["color_columns"]) == ["red", "green", "blue"] and f["color_depth_by_type"] == "8"


def test_parquet_bounds_provenance_and_a_glob(capsys, tmp_path):
    cloud = REAL / "pdal__autzen_trim.las"
    out = tmp_path / "s.parquet"
    summary = prism_stream.sample(str(cloud), str(out), ratio=0.05)
    table = pq.read_table(out)
    d = info_json(capsys, out)
    (f,) = d["files"]
    assert f["points"] == summary.kept == table.num_rows
    assert f["bounds"] == {"min": [pc.min(table[a]).as_py() for a in "xyz"],
                           "max": [pc.max(table[a]).as_py() for a in "xyz"]}
    assert f["prism_stream"]["kept"] == summary.kept and f["prism_stream"]["points"] == 110_000
    code, text, _ = cli(capsys, "info", out)
    assert code == 0 and f"written by  prism-stream {prism_stream.__version__}: {summary.kept:,} of 110,000" in text
    write_parquet(tmp_path / "t.parquet", {"x": np.arange(5.0), "red": np.arange(5, dtype=np.uint8),
                                           "green": np.zeros(5, np.uint8), "blue": np.zeros(5, np.uint8)})
    d = info_json(capsys, tmp_path / "*.parquet")
    assert [os.path.basename(f["path"]) for f in d["files"]] == ["s.parquet", "t.parquet"]
    assert d["points"] == summary.kept + 5 and d["files"][1]["bounds"] is None  # no y, z: no bounds
    assert d["files"][1]["prism_stream"] is None


def test_a_target_adds_the_plan_and_the_decided_depths(capsys, tmp_path):
    a = write_las(tmp_path / "a.las", random_colors(3_000, seed=1, palette=400))
    b = write_las(tmp_path / "b.las", random_colors(2_000, seed=2, palette=300, depth=16))
    d = info_json(capsys, tmp_path, "--ratio", "0.1")
    plan = prism_stream.plan([str(a), str(b)], ratio=0.1)
    assert d["plan"]["bins"] == plan.bins and d["plan"]["target"] == plan.target and d["plan"]["kept"] == plan.kept
    assert [f["color_depth"] for f in d["files"]] == ["8", "16"]
    code, text, _ = cli(capsys, "info", tmp_path, "--k", "2")
    assert code == 0 and "distinct bins" in text and "K = 2" in text


def test_info_errors_are_one_line(capsys, tmp_path):
    code, _, err = cli(capsys, "info", tmp_path / "nothere.laz")
    assert code == 3 and err.count("\n") == 1
    (tmp_path / "bad.laz").write_bytes(b"not a las file")
    code, _, err = cli(capsys, "info", tmp_path / "bad.laz")
    assert code in (4, 6) and err.count("\n") == 1 and "bad.laz" in err
    code, _, err = cli(capsys, "info", REAL / "pdal__warsaw_small.las", "--ratio", "2")
    assert code == 2 and err.count("\n") == 1


def test_a_file_it_cannot_describe_does_not_hide_the_others(capsys, tmp_path):
    """A folder of clouds with one colorless LAS among them: every other file is described, the colorless one
    is a line on stderr and its exit code ends the command (one such file ended the whole listing)."""
    import shutil

    from conftest import EDGE

    shutil.copy(REAL / "pdal__autzen_trim.las", tmp_path / "a.las")
    shutil.copy(EDGE / "pdal__1.2_0.las", tmp_path / "b.las")  # point format 0: no RGB
    shutil.copy(REAL / "pdal__warsaw_small.las", tmp_path / "c.las")
    code, out, err = cli(capsys, "info", tmp_path)
    assert code == 5 and "a.las" in out and "c.las" in out and "2 file(s)" in out, out + err
    assert err.count("\n") == 1 and "b.las: point format 0 has no RGB" in err
    code, out, err = cli(capsys, "info", tmp_path, "--json")
    data = json.loads(out)
    assert code == 5 and len(data["files"]) == 2 and [e["exit_code"] for e in data["errors"]] == [5]
    code, out, err = cli(capsys, "info", tmp_path / "b.las")  # one file: its error, as before
    assert code == 5 and not out and "no RGB" in err


def test_the_depth_a_column_type_allows_says_none_for_what_a_run_refuses(capsys, tmp_path):
    """info said '8 or 16' of a bool, string or mixed float/int color column, which a run then refused."""
    import pyarrow as pa

    n = 50
    x = np.arange(n, dtype="f8")
    u8 = np.arange(n, dtype="u1")
    cases = {"bool": (u8 > 5, "bool is not a number"), "string": (u8.astype(str), "is not a number"),
             "mixed": (np.linspace(0, 1, n), "floats and integers mixed")}
    for name, (red, says) in cases.items():
        path = tmp_path / f"{name}.parquet"
        pq.write_table(pa.table({"x": x, "y": x, "z": x, "red": red, "green": u8, "blue": u8}), path)
        code, out, err = cli(capsys, "info", path)
        assert code == 0 and "color depth none: " in out and says in out, (name, out, err)
        code, _, err = cli(capsys, path, tmp_path / "o.parquet", "--ratio", "0.5")
        assert code == 6 and err.count("\n") == 1, (name, err)
    code, _, err = cli(capsys, tmp_path / "mixed.parquet", tmp_path / "o.parquet", "--ratio", "0.5")
    assert "mix floats and integers (red float64, green uint8, blue uint8)" in err, err
