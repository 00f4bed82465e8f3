"""--keep/--drop keep what the output needs besides the names given: its coordinates wherever they are held (x, y,
z, a list column, WKB points), its colors and a packed rgba word's alpha; in an output folder sampled file by file
(--per-file) each file gets the names it has, as without --per-file."""

from __future__ import annotations

import os

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream.errors import UsageError

N = 3_000


def colored(rng, **columns) -> dict:
    return {**columns, "red": rng.integers(0, 8, N).astype(np.uint8) * 30,
            "green": rng.integers(0, 8, N).astype(np.uint8) * 30, "blue": rng.integers(0, 4, N).astype(np.uint8),
            "intensity": rng.integers(0, 9, N).astype(np.uint16), "label": rng.integers(0, 3, N).astype(np.int32)}


def wkb(xyz: np.ndarray) -> pa.Array:
    return pa.array([b"\x01" + np.array([1001], "<u4").tobytes() + p.astype("<f8").tobytes() for p in xyz],
                    pa.binary())


@pytest.fixture(scope="module")
def held(tmp_path_factory):
    """Parquet files whose coordinates are a fixed-size list, a list (as DuckDB writes one) or WKB points with no
    GeoParquet metadata."""
    rng = np.random.default_rng(4)
    xyz = rng.random((N, 3))
    d = tmp_path_factory.mktemp("held")
    columns = {"position": pa.FixedSizeListArray.from_arrays(pa.array(xyz.ravel()), 3),
               "coords": pa.array(list(map(list, xyz)), pa.list_(pa.float64())),
               "geometry": wkb(xyz)}
    paths = {}
    for name, column in columns.items():
        paths[name] = d / f"{name}.parquet"
        pq.write_table(pa.table(colored(rng, **{name: column})), paths[name])
    return paths


@pytest.mark.parametrize("name", ["position", "coords", "geometry"])
@pytest.mark.parametrize("selection", [{"keep": ("intensity",)}, {"drop": ("label",)}])
def test_coordinates_in_a_list_or_wkb_column_are_kept(held, tmp_path, name, selection):
    """The output keeps the column its coordinates are in, samples again, and has the rows of the full output."""
    out, whole = tmp_path / "out.parquet", tmp_path / "whole.parquet"
    prism_stream.sample(str(held[name]), str(out), ratio=0.3, seed=2, **selection)
    prism_stream.sample(str(held[name]), str(whole), ratio=0.3, seed=2)
    written = pq.read_table(out)
    assert written.column_names[0] == name
    assert written.column(name).equals(pq.read_table(whole).column(name))
    assert written.column("intensity").equals(pq.read_table(whole).column("intensity"))
    assert "label" not in written.column_names
    again = tmp_path / "again.parquet"
    prism_stream.sample(str(out), str(again), ratio=0.5, space="0.5")  # the coordinates are there to read
    assert pq.read_metadata(again).num_rows > 0
    with pytest.raises(UsageError, match=f"--drop '{name}': the output keeps its coordinates"):
        prism_stream.sample(str(held[name]), str(tmp_path / "d.parquet"), ratio=0.3, drop=(name,))


def test_a_geometry_named_column_beside_x_y_z_can_be_dropped(tmp_path):
    """With x, y, z the coordinates are those: a WKB column named ``geometry`` is one more column."""
    rng = np.random.default_rng(6)
    xyz = rng.random((N, 3))
    src = tmp_path / "both.parquet"
    pq.write_table(pa.table(colored(rng, x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2], geometry=wkb(xyz))), src)
    out = tmp_path / "out.parquet"
    prism_stream.sample(str(src), str(out), ratio=0.3, drop=("geometry",))
    assert "geometry" not in pq.read_schema(out).names
    prism_stream.sample(str(src), str(out), ratio=0.3, keep=("label",), overwrite=True)
    assert pq.read_schema(out).names == ["x", "y", "z", "red", "green", "blue", "label"]


def rgba_words(rng) -> np.ndarray:
    return (rng.integers(0, 256, N) << 24 | rng.integers(0, 8, N) * 30 << 16 | rng.integers(0, 8, N) * 30 << 8
            | rng.integers(0, 4, N) * 60).astype(np.uint32)


def write_pcd(path, words, rng) -> None:
    rec = np.zeros(N, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgba", "<u4"), ("label", "<i4")])
    rec["x"], rec["y"], rec["rgba"], rec["label"] = rng.random(N), rng.random(N), words, rng.integers(0, 3, N)
    header = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgba label\nSIZE 4 4 4 4 4\nTYPE F F F U I\nCOUNT 1 1 1 1 1\n"
              f"WIDTH {N}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {N}\nDATA binary\n")
    path.write_bytes(header.encode() + rec.tobytes())


@pytest.mark.parametrize("kind", ["parquet", "pcd"])
def test_a_packed_rgba_words_alpha_stays_with_its_colors(tmp_path, kind):
    """An rgba word is written as red, green, blue and alpha: --keep keeps the alpha as it keeps the colors (the
    values a run without --keep writes); --drop alpha leaves it out."""
    rng = np.random.default_rng(8)
    words = rgba_words(rng)
    src = tmp_path / f"in.{kind}"
    if kind == "parquet":
        pq.write_table(pa.table({"x": rng.random(N), "y": rng.random(N), "z": rng.random(N), "rgba": words,
                                 "label": rng.integers(0, 3, N).astype(np.int32)}), src)
    else:
        write_pcd(src, words, rng)
    whole, kept, dropped = (tmp_path / f"{n}.parquet" for n in ("whole", "kept", "dropped"))
    prism_stream.sample(str(src), str(whole), ratio=0.4, seed=1)
    prism_stream.sample(str(src), str(kept), ratio=0.4, seed=1, keep=("label",))
    prism_stream.sample(str(src), str(dropped), ratio=0.4, seed=1, drop=("alpha",))
    assert pq.read_table(kept).equals(pq.read_table(whole))  # every column is a kept one or a color
    assert "alpha" in pq.read_schema(whole).names
    assert pq.read_table(dropped).equals(pq.read_table(whole).drop_columns(["alpha"]))


def test_per_file_gives_each_file_the_names_it_has(tmp_path):
    """A --keep/--drop name only some files have: each file's output as in an output folder of one solve (no
    refusal), and a name no file has is refused before any output."""
    rng = np.random.default_rng(9)
    (tmp_path / "in").mkdir()
    a = colored(rng, x=rng.random(N), y=rng.random(N), z=rng.random(N))
    pq.write_table(pa.table(a), tmp_path / "in" / "a.parquet")
    b = colored(rng, x=rng.random(N), y=rng.random(N), z=rng.random(N))
    del b["intensity"]
    pq.write_table(pa.table(b), tmp_path / "in" / "b.parquet")
    for selection in ({"keep": ("intensity",)}, {"drop": ("intensity",)}, {"drop": ("intensity", "label")}):
        schemas = {}
        for per_file in (True, False):
            out = tmp_path / f"out_{per_file}"
            prism_stream.sample(str(tmp_path / "in"), f"{out}{os.sep}", ratio=0.3, per_file=per_file,
                                overwrite=True, **selection)
            schemas[per_file] = [pq.read_schema(out / f).names for f in ("a.parquet", "b.parquet")]
        assert schemas[True] == schemas[False], selection
    assert schemas[True] == [["x", "y", "z", "red", "green", "blue"]] * 2  # the last selection drops both
    with pytest.raises(UsageError, match="--keep 'nope': the inputs have no such column"):
        prism_stream.sample(str(tmp_path / "in"), str(tmp_path / "none") + os.sep, ratio=0.3, per_file=True,
                            keep=("nope",))
    assert not (tmp_path / "none").exists()


@pytest.mark.parametrize("out_name", ["out.parquet", "out.las", "out.xyz", "out.ply"])
@pytest.mark.parametrize("packed_first", [True, False])
def test_a_packed_rgba_input_beside_one_with_an_alpha_column(tmp_path, out_name, packed_first):
    """One output of a packed rgba input and of one that holds alpha as a column (a sample of the first): the
    alpha is kept whatever the order, and every input's is decoded (the rows a full decode writes)."""
    from prism_stream.formats import parquet as parquet_format

    rng = np.random.default_rng(10)
    packed = tmp_path / "packed.parquet"
    pq.write_table(pa.table({"x": rng.random(N), "y": rng.random(N), "z": rng.random(N), "rgba": rgba_words(rng),
                             "label": rng.integers(0, 3, N).astype(np.int32)}), packed)
    plain = tmp_path / "plain.parquet"
    prism_stream.sample(str(packed), str(plain), ratio=1.0)
    assert "alpha" in pq.read_schema(plain).names
    inputs = [str(packed), str(plain)] if packed_first else [str(plain), str(packed)]
    out = tmp_path / out_name
    prism_stream.sample(inputs, str(out), ratio=0.3, seed=4, keep=("label",))
    whole = tmp_path / f"whole{out.suffix}"
    real = parquet_format.ParquetSource.read_only
    parquet_format.ParquetSource.read_only = lambda self, names: None  # every column decoded
    try:
        prism_stream.sample(inputs, str(whole), ratio=0.3, seed=4, keep=("label",))
    finally:
        parquet_format.ParquetSource.read_only = real
    if out.suffix == ".parquet":
        assert "alpha" in pq.read_schema(out).names
        assert pq.read_table(out).equals(pq.read_table(whole))
    elif out.suffix == ".las":
        import laspy

        a, b = laspy.read(out), laspy.read(whole)
        assert "alpha" in a.point_format.dimension_names
        assert np.array_equal(a.points.array, b.points.array)
    else:
        skip = 1 if out.suffix == ".xyz" else 0  # the provenance line
        assert out.read_bytes().splitlines()[skip:] == whole.read_bytes().splitlines()[skip:]
        assert b"alpha" in out.read_bytes()[:4096].lower()


@pytest.mark.parametrize("ext", ["parquet", "las", "ply"])
def test_a_packed_rgba_word_beside_an_alpha_column_of_its_own(tmp_path, ext):
    """An ``rgba`` word beside an unrelated ``alpha`` column: the colors are the word's (the same sample as
    without that column), and the word is written as it is, as a PCD file's is, so that its alpha does not
    write over the column (it was refused: "no color column 'red'"; a hostile tester's find)."""
    rng = np.random.default_rng(13)
    columns = {"x": rng.random(N), "y": rng.random(N), "z": rng.random(N), "rgba": rgba_words(rng)}
    alone, beside = tmp_path / "alone.parquet", tmp_path / "beside.parquet"
    pq.write_table(pa.table(columns), alone)
    confidence = rng.random(N)
    pq.write_table(pa.table({**columns, "alpha": confidence}), beside)
    a, b = tmp_path / f"a.{ext}", tmp_path / f"b.{ext}"
    prism_stream.sample(str(alone), str(a), ratio=0.3, seed=5)
    prism_stream.sample(str(beside), str(b), ratio=0.3, seed=5)
    if ext == "parquet":
        got, want = pq.read_table(b), pq.read_table(a)
        assert got.column_names == ["x", "y", "z", "rgba", "alpha"]
        assert np.array_equal(got.column("x").to_numpy(), want.column("x").to_numpy())
        words = got.column("rgba").to_numpy()
        assert np.array_equal((words >> 16) & 0xFF, want.column("red").to_numpy())  # the word's own colors
        picked = np.searchsorted(columns["x"], got.column("x").to_numpy(), sorter=np.argsort(columns["x"]))
        assert np.array_equal(got.column("alpha").to_numpy(), confidence[np.argsort(columns["x"])][picked])
        again = tmp_path / "again.parquet"  # read again: its colors are still the word's
        prism_stream.sample(str(b), str(again), ratio=1.0)
        assert pq.read_table(again).equals(got.select(["x", "y", "z", "rgba", "alpha"]))
    elif ext == "las":
        import laspy

        got, want = laspy.read(b), laspy.read(a)
        assert np.array_equal(got.red, want.red) and np.array_equal(got.x, want.x)
    else:
        from prism_stream.formats import open_source

        def colors(path):
            src = open_source(str(path), 0)
            try:
                return list(src.arrow_schema().names), np.concatenate([np.column_stack(c.rgb) for c in
                                                                       src.point_chunks(1 << 20)])
            finally:
                src.close()

        (names_b, got), (_, want) = colors(b), colors(a)
        assert "alpha" in names_b and np.array_equal(got, want)


@pytest.mark.parametrize("columns", ["union", "intersection"])
def test_packed_words_kept_whole_of_different_types_are_not_written_as_one_column(tmp_path, monkeypatch,
                                                                                   columns):
    """Two inputs whose rgba word is kept whole (beside an alpha column), one a float32 word, one a uint32:
    --columns union widened the word to double (other colors read back) or int32 and uint32 to int64 (a
    sample of it refused); refused before a point is decoded now (a reviewer's find)."""
    from prism_stream.formats import parquet as parquet_format

    rng = np.random.default_rng(14)
    words = rgba_words(rng)
    for name, word in (("u.parquet", words), ("f.parquet", words.view(np.float32)),
                       ("i.parquet", words.view(np.int32))):
        pq.write_table(pa.table({"x": rng.random(N), "y": rng.random(N), "z": rng.random(N), "rgba": word,
                                 "alpha": rng.random(N)}), tmp_path / name)
    monkeypatch.setattr(parquet_format.ParquetSource, "_batches", lambda *a, **k: (_ for _ in ()).throw(
        AssertionError("a point was decoded")))
    for other, kind in (("f.parquet", "float"), ("i.parquet", "int32")):
        with pytest.raises(UsageError, match=f"its packed color word 'rgba' is {kind}, and u.parquet's is uint32"):
            prism_stream.sample([str(tmp_path / "u.parquet"), str(tmp_path / other)], str(tmp_path / "o.parquet"),
                                ratio=0.5, columns=columns)
        assert not (tmp_path / "o.parquet").exists()


def test_a_column_named_xyz_that_is_not_the_coordinates_is_a_column_like_any_other(tmp_path):
    """An ``xyz`` list of text beside WKB points: --keep left it in and --drop refused it (the name was kept
    whatever it held; a reviewer's find); only the coordinates' own column is kept now."""
    rng = np.random.default_rng(15)
    xyz = rng.random((N, 3))
    points = pa.array([b"\x01" + np.array([1001], "<u4").tobytes() + p.astype("<f8").tobytes() for p in xyz])
    src = tmp_path / "in.parquet"
    pq.write_table(pa.table(colored(rng, xyz=pa.array([["a"]] * N), wkb=points)), src)
    out = tmp_path / "out.parquet"
    prism_stream.sample(str(src), str(out), ratio=0.3, keep=("intensity",))
    assert "xyz" not in pq.read_schema(out).names and "wkb" in pq.read_schema(out).names
    prism_stream.sample(str(src), str(out), ratio=0.3, drop=("xyz",), overwrite=True)
    assert "xyz" not in pq.read_schema(out).names


def test_only_the_list_column_coordinates_are_read_from_is_kept(tmp_path):
    """Beside ``position`` (three numbers a row: the coordinates), a ``points`` list of two numbers is one more
    column: --keep leaves it out, --drop may drop it."""
    rng = np.random.default_rng(11)
    xyz = rng.random((N, 3))
    src = tmp_path / "two_lists.parquet"
    pq.write_table(pa.table(colored(rng, position=pa.FixedSizeListArray.from_arrays(pa.array(xyz.ravel()), 3),
                                    points=pa.array([[1, 2]] * N, pa.list_(pa.int32())))), src)
    out = tmp_path / "out.parquet"
    prism_stream.sample(str(src), str(out), ratio=0.3, keep=("intensity",))
    assert pq.read_schema(out).names == ["position", "red", "green", "blue", "intensity"]
    prism_stream.sample(str(src), str(out), ratio=0.3, drop=("points",), overwrite=True)
    assert "points" not in pq.read_schema(out).names and "position" in pq.read_schema(out).names


@pytest.mark.parametrize("columns", ["union", "intersection"])
@pytest.mark.parametrize("other", ["position", "upper"])
def test_inputs_holding_points_in_different_columns_are_refused_before_pass_one(tmp_path, monkeypatch, columns,
                                                                                  other):
    """One output of an input with x, y, z and red, green, blue and one with a ``position`` list (or X, Y, Z and
    Red, Green, Blue, as PDAL writes them): a union would leave each input's points without the other's
    coordinates or colors (nulls), an intersection without any; refused before a point is decoded."""
    from prism_stream.formats import parquet as parquet_format

    rng = np.random.default_rng(12)
    xyz = rng.random((N, 3))
    a, b = tmp_path / "a.parquet", tmp_path / "b.parquet"
    pq.write_table(pa.table(colored(rng, x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2])), a)
    if other == "position":
        pq.write_table(pa.table(colored(rng, position=pa.FixedSizeListArray.from_arrays(pa.array(xyz.ravel()), 3))),
                       b)
        said = "its coordinates are in position, and a.parquet's in x, y, z"
    else:
        upper = {("Red" if k == "red" else "Green" if k == "green" else "Blue" if k == "blue" else k): v
                 for k, v in colored(rng, X=xyz[:, 0], Y=xyz[:, 1], Z=xyz[:, 2]).items()}
        pq.write_table(pa.table(upper), b)
        said = "its colors are in Red, Green, Blue, and a.parquet's in red, green, blue"

    def never(*args, **kwargs):
        raise AssertionError("a point was decoded")

    monkeypatch.setattr(parquet_format.ParquetSource, "_batches", never)
    for selection in ({}, {"keep": ("label",)}):
        with pytest.raises(UsageError, match=f"--columns {columns}: {said}"):
            prism_stream.sample([str(a), str(b)], str(tmp_path / "out.parquet"), ratio=0.3, columns=columns,
                                **selection)
    assert not (tmp_path / "out.parquet").exists()


def test_a_lower_case_name_wins_over_one_differing_by_case(tmp_path):
    """Beside x, y, z a column ``X`` (zeros) is one more column: --keep keeps x, LAS output takes its
    coordinates from x; a --keep name that only matches ignoring case and matches two columns is refused."""
    import laspy

    rng = np.random.default_rng(13)
    xyz = rng.random((N, 3)) * 100
    src = tmp_path / "both.parquet"
    pq.write_table(pa.table(colored(rng, x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2], X=np.zeros(N),
                                    Intensity=np.ones(N, np.uint16))), src)
    out = tmp_path / "out.parquet"
    prism_stream.sample(str(src), str(out), ratio=0.5, keep=("label",))
    assert pq.read_schema(out).names == ["x", "y", "z", "red", "green", "blue", "label"]
    las = tmp_path / "out.las"
    prism_stream.sample(str(src), str(las), ratio=0.5, seed=1)
    written = pq.read_table(tmp_path / "out.parquet")
    assert laspy.read(las).x.max() > 1 and written.column("x").to_numpy().max() > 1
    with pytest.raises(UsageError, match="--keep 'INTENSITY' could be any of the columns Intensity, intensity"):
        prism_stream.sample(str(src), str(tmp_path / "amb.parquet"), ratio=0.5, keep=("INTENSITY",))
    prism_stream.sample(str(src), str(tmp_path / "exact.parquet"), ratio=0.5, keep=("Intensity",))
    assert "Intensity" in pq.read_schema(tmp_path / "exact.parquet").names


def test_las_converted_output_says_which_dimensions_are_written_as_zero(tmp_path):
    """LAS from Parquet: a column of a point-format dimension that --drop (or --keep) leaves out is written as
    0 in every record, and the run says so, as it does for LAS inputs."""
    import laspy

    from prism_stream.errors import PrismWarning

    rng = np.random.default_rng(14)
    src = tmp_path / "in.parquet"
    pq.write_table(pa.table(colored(rng, x=rng.random(N), y=rng.random(N), z=rng.random(N),
                                    gps_time=np.arange(N, dtype=float))), src)
    out = tmp_path / "out.las"
    with pytest.warns(PrismWarning, match="--drop: gps_time, intensity written as 0 in every record"):
        prism_stream.sample(str(src), str(out), ratio=0.5, drop=("gps_time", "intensity"))
    las = laspy.read(out)
    assert not las.intensity.any() and not las.gps_time.any()


def test_a_packed_color_words_name_keeps_or_refuses_as_the_colors(tmp_path):
    """PCL's ``rgba`` is written as red, green, blue (and alpha): --keep rgba keeps the colors (as always),
    --drop rgba is refused as a color column is, not as a column the inputs lack."""
    rng = np.random.default_rng(15)
    src = tmp_path / "packed.parquet"
    pq.write_table(pa.table({"x": rng.random(N), "y": rng.random(N), "z": rng.random(N), "rgba": rgba_words(rng),
                             "label": rng.integers(0, 3, N).astype(np.int32)}), src)
    out = tmp_path / "out.parquet"
    prism_stream.sample(str(src), str(out), ratio=0.3, keep=("RGBA",))
    assert pq.read_schema(out).names == ["x", "y", "z", "red", "green", "blue", "alpha"]
    with pytest.raises(UsageError, match="--drop 'rgba': the packed color word is written as red, green, blue"):
        prism_stream.sample(str(src), str(tmp_path / "d.parquet"), ratio=0.3, drop=("rgba",))


def test_a_keep_name_intersection_leaves_out_says_so(tmp_path):
    rng = np.random.default_rng(16)
    a, b = tmp_path / "a.parquet", tmp_path / "b.parquet"
    pq.write_table(pa.table(colored(rng, x=rng.random(N), y=rng.random(N), z=rng.random(N), extra=np.ones(N))), a)
    pq.write_table(pa.table(colored(rng, x=rng.random(N), y=rng.random(N), z=rng.random(N))), b)
    with pytest.raises(UsageError, match="--keep 'extra': only some inputs have it, and this output's columns"):
        prism_stream.sample([str(a), str(b)], str(tmp_path / "o.parquet"), ratio=0.3, keep=("extra",),
                            columns="intersection")


def test_one_parquet_output_of_inputs_of_different_color_depths_says_so(tmp_path):
    """8-bit and 16-bit colors in one Parquet output are written as they are (both scales in one column): the
    run says so and names the files of each depth."""
    from prism_stream.errors import PrismWarning

    rng = np.random.default_rng(17)
    for name, top in (("eight", 255), ("sixteen", 65535)):
        pq.write_table(pa.table({"x": rng.random(N), "y": rng.random(N), "z": rng.random(N),
                                 **{c: rng.integers(0, top, N).astype(np.uint16) for c in ("red", "green", "blue")}}),
                       tmp_path / f"{name}.parquet")
    with pytest.warns(PrismWarning, match=r"colors differ in depth \(8-bit in eight.parquet; 16-bit in sixteen"):
        prism_stream.sample([str(tmp_path / "eight.parquet"), str(tmp_path / "sixteen.parquet")],
                            str(tmp_path / "o.parquet"), ratio=0.3)
    import warnings

    pq.write_table(pq.read_table(tmp_path / "eight.parquet").slice(0, 0), tmp_path / "empty.parquet")
    with warnings.catch_warnings(record=True) as said:  # an empty input has no colors to differ
        warnings.simplefilter("always")
        prism_stream.sample([str(tmp_path / "empty.parquet"), str(tmp_path / "sixteen.parquet")],
                            str(tmp_path / "e.parquet"), ratio=0.3)
    assert not [w for w in said if "differ in depth" in str(w.message)]
    for name, top in (("eight", 255), ("sixteen", 65535)):  # LAS from LAS: the records copied as they are
        import laspy

        las = laspy.create(point_format=3, file_version="1.2")
        las.x, las.y, las.z = rng.random(N), rng.random(N), rng.random(N)
        las.red, las.green, las.blue = (rng.integers(0, top, N) for _ in range(3))
        las.write(tmp_path / f"{name}.las")
    with pytest.warns(PrismWarning, match=r"colors differ in depth \(8-bit in eight.las; 16-bit in sixteen.las"):
        prism_stream.sample([str(tmp_path / "eight.las"), str(tmp_path / "sixteen.las")],
                            str(tmp_path / "o.las"), ratio=0.3)


def test_a_union_says_nothing_of_a_column_drop_leaves_out(tmp_path):
    """--columns union notes each column some input lacks, but not one --drop leaves out of the output."""
    from prism_stream.errors import PrismWarning

    rng = np.random.default_rng(18)
    a, b = tmp_path / "a.parquet", tmp_path / "b.parquet"
    pq.write_table(pa.table(colored(rng, x=rng.random(N), y=rng.random(N), z=rng.random(N), extra=np.ones(N),
                                    other=np.ones(N))), a)
    pq.write_table(pa.table(colored(rng, x=rng.random(N), y=rng.random(N), z=rng.random(N))), b)
    with pytest.warns(PrismWarning) as said:
        prism_stream.sample([str(a), str(b)], str(tmp_path / "o.parquet"), ratio=0.3, columns="union",
                            drop=("extra",))
    texts = [str(w.message) for w in said]
    assert any("column 'other' is missing from b.parquet" in t for t in texts), texts
    assert not any("'extra'" in t for t in texts), texts


def test_a_warning_made_an_error_leaves_no_output(tmp_path):
    """Notes are said once every output is written and before any is published: under ``-W error`` the first
    one ends the run and leaves nothing (a reviewer found the output published first)."""
    import subprocess
    import sys

    rng = np.random.default_rng(19)
    src = tmp_path / "in.parquet"
    pq.write_table(pa.table(colored(rng, x=rng.random(N), y=rng.random(N), z=rng.random(N))), src)
    out = tmp_path / "out.las"  # 8-bit colors stored as 16-bit: a note
    done = subprocess.run([sys.executable, "-W", "error::UserWarning", "-c",
                           "from prism_stream_cli.main import run; run()", str(src), str(out), "--ratio", "0.5",
                           "--quiet"], capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode != 0, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.parquet"], done.stderr


def test_per_file_says_no_note_of_a_folder_a_later_file_fails(tmp_path):
    """--per-file: a file's notes are said once every file is written; when a later one fails nothing is
    published, and nothing is said of the earlier file's output (a reviewer found its notes printed)."""
    import warnings

    rng = np.random.default_rng(20)
    (tmp_path / "in").mkdir()
    pq.write_table(pa.table(colored(rng, x=rng.random(N), y=rng.random(N), z=rng.random(N))),
                   tmp_path / "in" / "a.parquet")
    bad = rng.random(N)
    bad[:] = np.nan  # every point: whichever is kept, LAS cannot store it
    pq.write_table(pa.table(colored(rng, x=bad, y=rng.random(N), z=rng.random(N))), tmp_path / "in" / "b.parquet")
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        with pytest.raises(UsageError, match="which LAS, LAZ and COPC cannot store"):
            prism_stream.sample(str(tmp_path / "in"), f"{tmp_path / 'out'}{os.sep}", ratio=0.5, per_file=True,
                                output_format="las")
    assert not [str(w.message) for w in said if "a.las" in str(w.message)]
    assert not (tmp_path / "out").exists()
