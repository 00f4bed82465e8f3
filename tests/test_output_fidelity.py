"""The output-fidelity rule, enforced in the sinks (issue 13).

No column or property is dropped or changed without saying which and why
(a PrismWarning, and the same line in ``sink.notes``), or a refusal where it
would lose meaning (a null in an integer LAS dimension or PLY property).
No numpy warning reaches stderr.
"""

from __future__ import annotations

import datetime
import subprocess
import warnings

import laspy
import numpy as np
import plyfile
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream import PrismWarning
from prism_stream.errors import UnsupportedFormat
from prism_stream.formats import open_sink, open_source

from conftest import prism_stream_command, write_parquet

N = 6


def base_columns(n=N):
    return {"x": np.arange(n, dtype=np.float64) + 0.25, "y": np.arange(n, dtype=np.float64) * 2,
            "z": np.arange(n, dtype=np.float64) * 3,
            "red": np.arange(n, dtype=np.uint8) * 10, "green": np.arange(n, dtype=np.uint8) * 20,
            "blue": np.arange(n, dtype=np.uint8) * 30}


def odd_table(n=N) -> pa.Table:
    """Every column kind PLY and LAS cannot hold as such, beside plain numbers."""
    cols = {k: pa.array(v) for k, v in base_columns(n).items()}
    cols.update({
        "label": pa.array([f"p{i}" for i in range(n)]),
        "tags": pa.array([[i, i + 1] for i in range(n)]),
        "meta": pa.array([{"a": i} for i in range(n)]),
        "when": pa.array([datetime.datetime(2024, 1, 1) + datetime.timedelta(seconds=i) for i in range(n)]),
        "score": pa.array([float(i) if i % 2 else None for i in range(n)], pa.float64()),
        "normal": pa.FixedSizeListArray.from_arrays(pa.array(np.arange(3 * n, dtype=np.float32)), 3),
        "flagged": pa.array([i % 2 == 0 for i in range(n)]),
        "wide": pa.array(np.arange(n, dtype=np.int64) * 1000),
        "plain": pa.array(np.arange(n, dtype=np.int16) - 3),
    })
    return pa.table(cols)


def drive(src_path, out_path, keep=None):
    """Write ``src_path`` through the output's sink directly (every point kept unless ``keep``)."""
    src = open_source(str(src_path), 0)
    keep = np.ones(src.count, bool) if keep is None else keep
    prov = {"kept": int(keep.sum()), "points": src.count, "sources": [{"ordinal": 0, "color_depth": "8"}]}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sink = open_sink(str(out_path), [src], prov)
        try:
            for chunk in src.point_chunks(1 << 20):
                sink.write(chunk, keep[chunk.start:chunk.start + len(chunk)])
            sink.commit()
        except BaseException:
            sink.abort()
            raise
    return sink, caught


def prism_warnings(caught):
    return [str(w.message) for w in caught if issubclass(w.category, PrismWarning)]


def assert_no_numpy_warnings(caught):
    stray = [f"{w.category.__name__}: {w.message}" for w in caught if not issubclass(w.category, PrismWarning)]
    assert not stray, stray


def noted(notes, name) -> list:
    return [n for n in notes if f"'{name}'" in n]


@pytest.mark.parametrize("ext", [".ply", ".las"])
def test_every_column_the_format_cannot_hold_is_named_with_a_reason(tmp_path, ext):
    table = odd_table().drop(["score"])  # nulls: their own tests
    src = write_parquet(tmp_path / "odd.parquet", table)
    out = tmp_path / f"out{ext}"
    sink, caught = drive(src, out)
    assert_no_numpy_warnings(caught)
    # every note is a warning too, word for word, and names the output
    assert sink.notes == prism_warnings(caught)
    assert all(n.startswith(f"{out}: ") for n in sink.notes)
    for name, why in (("label", "text"), ("tags", "one number per point"), ("meta", "one number per point"),
                      ("when", "time")):
        found = noted(sink.notes, name)
        assert len(found) == 1 and "dropped" in found[0] and why in found[0], (name, sink.notes)
    for name in ("normal", "flagged", "wide" if ext == ".ply" else "flagged"):
        assert noted(sink.notes, name), (name, sink.notes)
    # the vector column survives, one property (dimension) per element, values exact
    got = read_back(out)
    for j in range(3):
        assert np.array_equal(got[f"normal_{j}"], np.arange(3 * N, dtype=np.float32).reshape(N, 3)[:, j])
    assert np.array_equal(got["plain"], np.arange(N) - 3) and got["plain"].dtype == np.int16
    assert not noted(sink.notes, "plain")  # kept with its own type: nothing to say
    assert not [n for n in sink.notes if "no value" in n], sink.notes  # no nulls here: none reported
    assert np.array_equal(got["wide"], np.arange(N) * 1000)
    assert np.array_equal(got["flagged"], [1, 0] * (N // 2))


def read_back(path) -> dict:
    if str(path).endswith(".ply"):
        v = plyfile.PlyData.read(str(path))["vertex"].data
        return {n: np.asarray(v[n]) for n in v.dtype.names}
    las = laspy.read(str(path))
    return {n: np.asarray(las[n]) for n in las.point_format.dimension_names}


@pytest.mark.parametrize("ext", [".ply", ".las"])
def test_nulls_in_a_float_column_become_nan_and_are_counted(tmp_path, ext):
    table = pa.table({**{k: pa.array(v) for k, v in base_columns().items()},
                      "score": pa.array([1.5, None, 2.5, None, None, 4.0])})
    src = write_parquet(tmp_path / "n.parquet", table)
    out = tmp_path / f"out{ext}"
    keep = np.array([1, 1, 1, 1, 0, 1], bool)  # one of the three nulls is not written
    sink, caught = drive(src, out, keep)
    assert_no_numpy_warnings(caught)
    found = noted(sink.notes, "score")
    assert len(found) == 1 and "'score': 2 points with no value (null)" in found[0] and "NaN" in found[0], sink.notes
    got = read_back(out)["score"]
    assert np.array_equal(got, [1.5, np.nan, 2.5, np.nan, 4.0], equal_nan=True)


@pytest.mark.parametrize("ext", [".ply", ".las"])
@pytest.mark.parametrize("kind", [pa.int32(), pa.uint8(), pa.bool_()])
def test_nulls_in_an_integer_column_refuse_the_output_in_one_whole_line(tmp_path, ext, kind):
    values = [1, None, 3, None, 5, 6] if kind != pa.bool_() else [True, None, False, None, True, True]
    table = pa.table({**{k: pa.array(v) for k, v in base_columns().items()}, "count": pa.array(values, kind)})
    src = write_parquet(tmp_path / "n.parquet", table)
    out = tmp_path / f"out{ext}"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(UnsupportedFormat) as info:
            prism_stream.sample(str(src), str(out), ratio=1.0)
    assert_no_numpy_warnings(caught)
    msg = str(info.value)
    assert info.value.path == str(src) and "\n" not in msg
    assert "'count' has 2 points with no value (null)" in msg and "cannot hold a missing value" in msg
    assert msg.endswith("(fill the nulls, or write Parquet)")  # a whole sentence, not one cut short
    assert not out.exists() and not list(tmp_path.glob("*.prism-tmp")) and not list(tmp_path.glob("*.spool"))


def test_parquet_to_ply_cli_prints_one_line_per_notice_and_no_numpy_warning(tmp_path):
    src = write_parquet(tmp_path / "odd.parquet", odd_table())
    out = tmp_path / "out.ply"
    r = subprocess.run([*prism_stream_command(), str(src), str(out), "--ratio", "1", "--quiet"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert lines and all(ln.startswith("prism-stream: warning: ") for ln in lines), r.stderr
    assert "invalid value" not in r.stderr and "RuntimeWarning" not in r.stderr
    for name in ("label", "tags", "meta", "when", "score", "normal", "flagged", "wide"):
        assert any(f"'{name}'" in ln for ln in lines), (name, r.stderr)


def test_parquet_to_parquet_changes_nothing_and_says_nothing(tmp_path):
    table = odd_table()
    src = write_parquet(tmp_path / "odd.parquet", table)
    out = tmp_path / "out.parquet"
    sink, caught = drive(src, out)
    assert sink.notes == [] and prism_warnings(caught) == []
    got = pq.read_table(out)
    assert got.schema.remove_metadata().equals(table.schema.remove_metadata())
    assert got.drop([]).equals(table.replace_schema_metadata(got.schema.metadata))


def test_ply_faces_are_named_when_left_out(tmp_path):
    v = np.zeros(4, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    v["x"] = np.arange(4)
    v["red"] = [10, 20, 30, 40]
    faces = np.array([([0, 1, 2],), ([1, 2, 3],)], dtype=[("vertex_indices", "i4", (3,))])
    src = tmp_path / "mesh.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex"), plyfile.PlyElement.describe(faces, "face")],
                    comments=["made by a test"], obj_info=["scanner: none"]).write(str(src))
    for ext in (".ply", ".parquet", ".las"):
        out = tmp_path / f"out{ext}"
        sink, caught = drive(src, out)
        assert_no_numpy_warnings(caught)
        assert [n for n in sink.notes if "face (2 records)" in n], (ext, sink.notes)
    # PLY -> PLY keeps the comments and obj_info lines
    data = plyfile.PlyData.read(str(tmp_path / "out.ply"))
    assert "made by a test" in data.comments and "scanner: none" in data.obj_info


def test_double_coordinates_stay_double_in_ply(tmp_path):
    """A georeferenced double coordinate written as float would move by up to 0.25 m at 5e6."""
    cols = base_columns()
    cols["x"] = 5_000_000.0 + np.arange(N) * 0.001
    src = write_parquet(tmp_path / "geo.parquet", cols)
    sink, caught = drive(src, tmp_path / "out.ply")
    got = read_back(tmp_path / "out.ply")
    assert got["x"].dtype == np.float64 and np.array_equal(got["x"], cols["x"])
    assert not [n for n in sink.notes if "coordinate" in n]


def test_las_colors_to_ply_say_how_they_were_converted(tmp_path):
    from conftest import write_las

    src = write_las(tmp_path / "c.las", np.array([[0, 128, 255]] * 4))
    sink, caught = drive(src, tmp_path / "out.ply")
    assert_no_numpy_warnings(caught)
    found = [n for n in sink.notes if "color" in n]
    assert len(found) == 1 and "uint16" in found[0] and "uchar" in found[0], sink.notes


@pytest.mark.parametrize("ext, kind", [(".ply", "PLY"), (".xyz", "XYZ text")])
def test_a_format_without_a_crs_says_the_inputs_is_not_written(tmp_path, ext, kind):
    """A newcomer's LAS -> PLY and LAS -> XYZ lost the CRS without a word."""
    from conftest import real_file

    src = real_file("pdal__autzen_trim.las")  # NAD83(HARN) / Oregon GIC Lambert
    sink, caught = drive(src, tmp_path / f"out{ext}")
    found = [n for n in sink.notes if "CRS" in n]
    assert len(found) == 1 and f"not written: {kind} has no place" in found[0] and "Lambert" in found[0], sink.notes
    sink, _ = drive(real_file("open3d__frag_115.ply"), tmp_path / f"again{ext}")  # no CRS: nothing to say
    assert not [n for n in sink.notes if "CRS" in n], sink.notes


def test_copc_input_to_las_says_the_octree_is_not_kept(tmp_path):
    from conftest import edge_file

    src = edge_file("pdal__1.2-with-color.copc.laz")
    source = open_source(str(src), 0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sink = open_sink(str(tmp_path / "out.laz"), [source], {"kept": 0})
        sink.commit()  # notes are warned when the output is committed: an aborted output warns of nothing
    assert len(sink.notes) == 1 and "COPC" in sink.notes[0]
    assert sink.notes == prism_warnings(caught)


def test_an_aborted_output_warns_of_nothing(tmp_path):
    """A run that fails has no output, so nothing to say about what the output would have lost."""
    from conftest import edge_file

    source = open_source(str(edge_file("pdal__1.2-with-color.copc.laz")), 0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sink = open_sink(str(tmp_path / "out.laz"), [source], {"kept": 0})
        sink.abort()
    assert len(sink.notes) == 1 and prism_warnings(caught) == []
    assert not (tmp_path / "out.laz").exists()


def test_nulls_counted_across_chunks_and_in_vector_elements(tmp_path):
    """Float nulls in two chunks add up; a null element of a float vector is NaN in its own property."""
    n = 8
    vec = pa.FixedSizeListArray.from_arrays(
        pa.array([0.0, 1.0, None, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0,
                  12.0, 13.0, None, 15.0, 16.0, 17.0, 18.0, 19.0, 20.0, 21.0, 22.0, 23.0], pa.float64()), 3)
    table = pa.table({**{k: pa.array(v) for k, v in base_columns(n).items()},
                      "score": pa.array([None, 1.0, 2.0, 3.0, None, 5.0, None, 7.0]), "vec": vec})
    src = write_parquet(tmp_path / "n.parquet", table, row_group_size=4)  # two chunks of four
    out = tmp_path / "out.ply"
    sink, caught = drive(src, out)
    assert_no_numpy_warnings(caught)
    assert [n_ for n_ in sink.notes if "'score': 3 points with no value (null)" in n_], sink.notes
    assert [n_ for n_ in sink.notes if "'vec_2': 2 points with no value (null)" in n_], sink.notes
    assert not [n_ for n_ in sink.notes if "'vec_0':" in n_ or "'vec_1':" in n_], sink.notes
    got = read_back(out)
    assert np.isnan(got["vec_2"][[0, 4]]).all() and got["vec_2"][1] == 5.0


@pytest.mark.parametrize("column", [pa.array([b"ab"] * N, pa.binary()), pa.array([b"ab"] * N, pa.large_binary()),
                                    pa.array(["a", "b"] * (N // 2)).dictionary_encode()], ids=str)
def test_bytes_and_categories_are_dropped_as_not_numbers(tmp_path, column):
    table = pa.table({**{k: pa.array(v) for k, v in base_columns().items()}, "blob": column})
    src = write_parquet(tmp_path / "b.parquet", table)
    sink, _ = drive(src, tmp_path / "out.ply")
    found = noted(sink.notes, "blob")
    assert len(found) == 1 and "dropped" in found[0] and "not text or bytes" in found[0], sink.notes


def test_a_pcd_color_word_is_written_as_red_green_blue_and_alpha(tmp_path):
    """PCL's packed 0xAARRGGBB word: uint8 red, green, blue (the output's colors) and alpha (a column of its
    own), in every format; PLY keeps them as uchar without a note, LAS scales the colors to 16 bits and says so."""
    rec = np.zeros(4, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgba", "<u4")])
    rec["rgba"] = 0xFF102030
    head = ("VERSION 0.7\nFIELDS x y z rgba\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\nWIDTH 4\nHEIGHT 1\n"
            "POINTS 4\nDATA binary\n")
    src = tmp_path / "c.pcd"
    src.write_bytes(head.encode() + rec.tobytes())
    sink, _ = drive(src, tmp_path / "out.ply")
    assert not [n for n in sink.notes if "red" in n], sink.notes
    back = read_back(tmp_path / "out.ply")
    assert [back[c].tolist() for c in ("red", "green", "blue", "alpha")] == [[0x10] * 4, [0x20] * 4, [0x30] * 4,
                                                                            [0xFF] * 4]
    sink, _ = drive(src, tmp_path / "out.las")
    assert [n for n in sink.notes if "color columns red, green, blue (uint8) stored as LAS 16-bit" in n], sink.notes
    back = read_back(tmp_path / "out.las")
    assert [back[c].tolist() for c in ("red", "green", "blue", "alpha")] == [[0x1000] * 4, [0x2000] * 4,
                                                                            [0x3000] * 4, [0xFF] * 4]
    sink, _ = drive(src, tmp_path / "out.parquet")
    table = pq.read_table(tmp_path / "out.parquet")
    assert table.column_names == ["x", "y", "z", "red", "green", "blue", "alpha"]


@pytest.mark.parametrize("ext, how", [(".ply", "written as float"), (".las", "stored as LAS extra-bytes float32")])
def test_a_half_float_column_is_named_where_it_is_widened(tmp_path, ext, how):
    cols = {k: pa.array(v) for k, v in base_columns().items()}
    cols["half"] = pa.array(np.linspace(0, 1, N).astype(np.float16))
    src = write_parquet(tmp_path / "in.parquet", pa.table(cols))
    sink, caught = drive(src, tmp_path / f"out{ext}")
    found = noted(sink.notes, "half")
    assert len(found) == 1 and "halffloat" in found[0] and how in found[0], sink.notes
    assert_no_numpy_warnings(caught)
    assert np.array_equal(read_back(tmp_path / f"out{ext}")["half"],
                          np.linspace(0, 1, N).astype(np.float16).astype(np.float32))
