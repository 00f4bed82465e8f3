"""Every output format takes a point's coordinates wherever a Parquet input holds them: x, y, z columns, a
fixed-size list or a list of three numbers (``position``, ``coords``...), WKB points without GeoParquet
metadata. LAS, COPC, PLY and XYZ write them as x, y, z (the same points as from x, y, z columns); an input with
none is refused before a point is decoded."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream.errors import PrismError, UsageError
from prism_stream.evaluate.cloud import coordinates
from prism_stream.formats import open_source

N = 2_000


def wkb(xyz: np.ndarray) -> pa.Array:
    return pa.array([b"\x01" + np.array([1001], "<u4").tobytes() + p.astype("<f8").tobytes() for p in xyz],
                    pa.binary())


@pytest.fixture(scope="module")
def forms(tmp_path_factory):
    rng = np.random.default_rng(3)
    xyz = rng.random((N, 3)) * 100
    colors = {"red": rng.integers(0, 9, N).astype(np.uint8) * 20, "green": (np.arange(N) % 200).astype(np.uint8),
              "blue": np.zeros(N, np.uint8)}
    held = {"xyz": {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]},
            "position": {"position": pa.FixedSizeListArray.from_arrays(pa.array(xyz.ravel()), 3)},
            "coords": {"coords": pa.array(list(map(list, xyz)), pa.list_(pa.float64()))},
            "wkb": {"wkb": wkb(xyz)}, "geometry": {"geometry": wkb(xyz)}}
    d = tmp_path_factory.mktemp("forms")
    for name, columns in held.items():
        pq.write_table(pa.table({**columns, **colors}), d / f"{name}.parquet")
    return d


def read_back(path) -> np.ndarray:
    source = open_source(str(path), 0)
    try:
        return np.concatenate([coordinates(c) for c in source.point_chunks(1 << 20)])
    finally:
        source.close()


@pytest.mark.parametrize("ext", ["las", "copc.laz", "ply", "xyz"])
@pytest.mark.parametrize("form", ["position", "coords", "wkb", "geometry"])
def test_coordinates_held_in_a_list_or_wkb_are_written_as_x_y_z(forms, tmp_path, form, ext):
    expected = tmp_path / f"xyz.{ext}"
    prism_stream.sample(str(forms / "xyz.parquet"), str(expected), ratio=0.5, seed=2)
    out = tmp_path / f"{form}.{ext}"
    prism_stream.sample(str(forms / f"{form}.parquet"), str(out), ratio=0.5, seed=2)
    got, want = read_back(out), read_back(expected)
    assert got.shape == want.shape == (N // 2, 3)
    if ext == "copc.laz":  # COPC orders its points by octree node
        got, want = got[np.lexsort(got.T)], want[np.lexsort(want.T)]
    assert np.array_equal(got, want)


@pytest.mark.parametrize("ext", ["las", "copc.laz", "xyz"])
def test_an_input_without_coordinates_is_refused_before_pass_one(tmp_path, monkeypatch, ext):
    from prism_stream.formats import parquet as parquet_format

    src = tmp_path / "colors.parquet"
    pq.write_table(pa.table({"red": np.arange(100, dtype=np.uint8), "green": np.zeros(100, np.uint8),
                             "blue": np.zeros(100, np.uint8)}), src)

    def never(*args, **kwargs):
        raise AssertionError("a point was decoded")

    monkeypatch.setattr(parquet_format.ParquetSource, "_batches", never)
    with pytest.raises(UsageError, match="output needs the points' coordinates: x, y and z columns"):
        prism_stream.sample(str(src), str(tmp_path / f"o.{ext}"), ratio=0.5)
    assert not (tmp_path / f"o.{ext}").exists()


@pytest.mark.parametrize("form", ["position", "coords"])
def test_float32_coordinates_in_a_list_keep_their_grid_and_type(tmp_path, form):
    """float32 values in a list column are float32 coordinates: the LAS grid their spacing allows (as from
    float32 x, y, z columns), and PLY float, not double (a reviewer's find)."""
    import laspy

    rng = np.random.default_rng(5)
    xyz = (rng.random((N, 3)) * 2).astype(np.float32)
    colors = {"red": rng.integers(0, 9, N).astype(np.uint8), "green": np.zeros(N, np.uint8),
              "blue": np.zeros(N, np.uint8)}
    held = pa.FixedSizeListArray.from_arrays(pa.array(xyz.ravel()), 3) if form == "position" else \
        pa.array(list(map(list, xyz)), pa.list_(pa.float32()))
    pq.write_table(pa.table({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], **colors}), tmp_path / "cols.parquet")
    pq.write_table(pa.table({form: held, **colors}), tmp_path / "list.parquet")
    for name in ("cols", "list"):
        prism_stream.sample(str(tmp_path / f"{name}.parquet"), str(tmp_path / f"{name}.las"), ratio=0.5, seed=1)
        prism_stream.sample(str(tmp_path / f"{name}.parquet"), str(tmp_path / f"{name}.ply"), ratio=0.5, seed=1)
    a, b = laspy.read(tmp_path / "cols.las"), laspy.read(tmp_path / "list.las")
    assert np.array_equal(a.header.scales, b.header.scales) and np.array_equal(a.x, b.x)
    header = (tmp_path / "list.ply").read_bytes().split(b"end_header")[0]
    assert b"property float x" in header


def test_geometry_from_wkb_points_in_a_geom_column(tmp_path):
    """--geometry over WKB points held in ``geom``: the new ``geometry`` column holds the same points (the
    output's own new column is not taken for the input's; a reviewer found an internal error)."""
    from prism_stream.evaluate.cloud import wkb_points

    rng = np.random.default_rng(6)
    xyz = rng.random((N, 3))
    pq.write_table(pa.table({"geom": wkb(xyz), "red": rng.integers(0, 9, N).astype(np.uint8),
                             "green": np.zeros(N, np.uint8), "blue": np.zeros(N, np.uint8)}), tmp_path / "g.parquet")
    prism_stream.sample(str(tmp_path / "g.parquet"), str(tmp_path / "o.parquet"), ratio=0.5, geometry=True)
    table = pq.read_table(tmp_path / "o.parquet")
    assert np.array_equal(wkb_points(table.column("geom").combine_chunks()),
                          wkb_points(table.column("geometry").combine_chunks()))


def lists_beside_wkb(forms, tmp_path, rows) -> tuple[np.ndarray, np.ndarray]:
    """in.parquet: a ``coords`` list column (``rows``, over the points of forms' xyz.parquet) beside the points
    as WKB, and its colors; returns (the points, the list's values where three a row)."""
    points = np.column_stack([pq.read_table(forms / "xyz.parquet").column(a).to_numpy() for a in "xyz"])
    colors = pq.read_table(forms / "xyz.parquet", columns=["red", "green", "blue"])
    table = pa.table({"coords": pa.array(rows(points), pa.list_(pa.float64())), "wkb": wkb(points),
                      **{n: colors.column(n) for n in colors.column_names}})
    pq.write_table(table, tmp_path / "in.parquet")
    return points, points + 1000


@pytest.mark.parametrize("ext", ["las", "copc.laz", "ply", "xyz", "parquet"])
def test_a_list_named_like_coordinates_that_does_not_hold_them_is_refused_by_every_reader(forms, tmp_path, ext):
    """A ``coords`` list of two numbers a row before WKB points: the schema says the list holds the coordinates
    (a list of any length, as DuckDB writes FLOAT[3], comes before WKB points: a second reviewer's find), so
    every writer of x, y, z and --space refuse it in one line that says how to have the WKB points read, and
    leave no output."""
    lists_beside_wkb(forms, tmp_path, lambda p: [list(r[:2]) for r in p])
    extra = {"geometry": True} if ext == "parquet" else {}
    for options in ({**extra}, {"space": 0.3}):
        out = tmp_path / f"o.{ext}"
        with _quiet(), pytest.raises(PrismError, match="'coords' holds lists that are not 3 numbers each "
                                                       r"\(a list of numbers named like coordinates is read"):
            prism_stream.sample(str(tmp_path / "in.parquet"), str(out), ratio=0.5, seed=2, **options)
        assert not out.exists()


@pytest.mark.parametrize("ext", ["xyz", "las", "parquet"])
def test_the_coordinate_column_is_decided_by_the_schema_not_by_the_rows_a_chunk_holds(forms, tmp_path, ext):
    """A ``coords`` list of three numbers a row beside WKB points of other values: the list is the coordinates,
    whatever chunk a point comes in, whichever points are kept, with or without --flag and --space (a reviewer
    found a writer choosing per masked batch: the output changed with --chunk-size and --flag)."""
    points, listed = lists_beside_wkb(forms, tmp_path, lambda p: [list(r + 1000) for r in p])
    variants = ({}, {"chunk_size": 100}, {"space": 0.3}) + (({"flag": "keep"},) if ext != "las" else ())
    outputs = []
    for i, options in enumerate(variants):  # (LAS output takes --flag from LAS inputs only)
        out = tmp_path / f"o{i}.{ext}"
        extra = {"geometry": True} if ext == "parquet" else {}
        with _quiet():
            prism_stream.sample(str(tmp_path / "in.parquet"), str(out), ratio=0.3, seed=7, **options, **extra)
        if ext == "parquet":
            from prism_stream.evaluate.cloud import wkb_points

            table = pq.read_table(out)
            got = wkb_points(table.column("geometry").combine_chunks())
            assert np.array_equal(got, np.stack(table.column("coords").to_pylist()))
        else:
            got = read_back(out)
        if "flag" in options:
            assert np.array_equal(got, listed if ext != "las" else got)  # every point, with its own coordinates
            got = got[read_flag(out)]
        if "space" not in options:
            outputs.append(got)
        nearest = np.abs(got[:, None, :] - listed[None, :, :]).max(axis=2).min(axis=1)
        assert nearest.max() < 1e-3, options  # the list's values (LAS: on its grid), never the WKB points
    assert all(np.array_equal(o, outputs[0]) for o in outputs[1:])


def _quiet():
    import contextlib
    import warnings

    @contextlib.contextmanager
    def quiet():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    return quiet()


def read_flag(path) -> np.ndarray:
    source = open_source(str(path), 0)
    try:
        batches = [c.to_arrow() for c in source.point_chunks(1 << 20)]
    finally:
        source.close()
    return np.concatenate([b.column(b.schema.get_field_index("keep")).to_numpy(zero_copy_only=False)
                           for b in batches]).astype(bool)


def test_which_column_holds_the_coordinates_by_type():
    """x, y, z first; then a list of numbers named like coordinates (fixed-size of three, or of any length: how
    DuckDB writes FLOAT[3]), in its names' order; then WKB points (binary or large binary); a list of text, or
    a fixed-size list of another length, is none."""
    from prism_stream.formats.columns import kept_coordinates

    f3 = pa.list_(pa.float64(), 3)
    cases = [
        ({"x": pa.float64(), "y": pa.float64(), "z": pa.float64(), "position": f3}, ["x", "y", "z"]),
        ({"xyz": pa.list_(pa.float64()), "position": f3, "wkb": pa.binary()}, ["xyz"]),
        ({"geometry": pa.binary(), "position": f3}, ["position"]),
        ({"points": pa.list_(pa.float64(), 2), "coords": pa.list_(pa.float32())}, ["coords"]),
        ({"points": pa.list_(pa.string()), "geom": pa.binary(), "wkb": pa.binary()}, ["wkb"]),
        ({"points": pa.list_(pa.float64(), 2), "geometry": pa.large_binary()}, ["geometry"]),
        ({"points": pa.list_(pa.string())}, []),
    ]
    for fields, held in cases:
        assert kept_coordinates(pa.schema(list(fields.items()))) == held, fields


def test_two_dimensional_wkb_points_are_read_alike_by_space_and_the_writers(tmp_path):
    """2D WKB points (as geopandas writes them; large binary too): the writers read them with z = 0 and --space
    refused them ("not WKB Point Z"); one reader of WKB points serves both now (a reviewer's find)."""
    rng = np.random.default_rng(8)
    xy = rng.random((N, 2)) * 10
    colors = {"red": rng.integers(0, 9, N).astype(np.uint8) * 20, "green": (np.arange(N) % 200).astype(np.uint8),
              "blue": np.zeros(N, np.uint8)}
    flat = {"x": xy[:, 0], "y": xy[:, 1], "z": np.zeros(N)}
    pq.write_table(pa.table({**flat, **colors}), tmp_path / "flat.parquet")
    two_d = [b"\x01" + np.array([1], "<u4").tobytes() + p.astype("<f8").tobytes() for p in xy]
    pq.write_table(pa.table({"geometry": pa.array(two_d, pa.large_binary()), **colors}), tmp_path / "2d.parquet")
    for name in ("flat", "2d"):
        prism_stream.sample(str(tmp_path / f"{name}.parquet"), str(tmp_path / f"{name}.xyz"), ratio=0.3, seed=3,
                            space=0.5)
    assert np.array_equal(read_back(tmp_path / "2d.xyz"), read_back(tmp_path / "flat.xyz"))


def test_the_geoparquet_primary_column_is_the_points_whatever_its_name(tmp_path):
    """GeoParquet naming ``pts`` its primary column, beside a ``geometry`` of other shapes: the writers took
    ``geometry`` (and refused it) and --space found no coordinates; both read ``pts`` now (a reviewer's find)."""
    import json

    rng = np.random.default_rng(9)
    xyz = rng.random((N, 3))
    colors = {"red": rng.integers(0, 9, N).astype(np.uint8) * 20, "green": (np.arange(N) % 200).astype(np.uint8),
              "blue": np.zeros(N, np.uint8)}
    polygon = b"\x01" + np.array([3], "<u4").tobytes() + np.zeros(2, "<u4").tobytes()  # an empty polygon
    table = pa.table({"pts": wkb(xyz), "geometry": pa.array([polygon] * N), **colors})
    geo = {"version": "1.0.0", "primary_column": "pts",
           "columns": {"pts": {"encoding": "WKB", "geometry_types": ["Point Z"]},
                       "geometry": {"encoding": "WKB", "geometry_types": ["Polygon"]}}}
    pq.write_table(table.replace_schema_metadata({b"geo": json.dumps(geo).encode()}), tmp_path / "in.parquet")
    pq.write_table(pa.table({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], **colors}), tmp_path / "xyz.parquet")
    for name in ("in", "xyz"):
        with _quiet():
            prism_stream.sample(str(tmp_path / f"{name}.parquet"), str(tmp_path / f"{name}.xyz"), ratio=0.3,
                                seed=3, space=0.5)
    assert np.array_equal(read_back(tmp_path / "in.xyz"), read_back(tmp_path / "xyz.xyz"))


def test_wkb_rows_of_any_byte_order_and_dimension_read_alike_in_every_chunk(tmp_path):
    """WKB points mixing byte orders, 2D and Z, ISO and EWKB with or without an SRID (PostGIS writes one), in one
    row group: a chunk that held rows of two kinds was refused ("mixed or invalid WKB byte orders"), so the run
    failed or not with --chunk-size (a hostile tester's find). Each row is read by its own header now."""
    import struct

    rng = np.random.default_rng(10)
    xyz = rng.random((N, 3)) * 100
    forms = [lambda p: struct.pack("<BIddd", 1, 1001, *p), lambda p: struct.pack(">BIddd", 0, 1001, *p),
             lambda p: struct.pack("<BIIddd", 1, 0xA0000001, 4326, *p),
             lambda p: struct.pack("<BIddd", 1, 0x80000001, *p),
             lambda p: struct.pack(">BIIddd", 0, 0xA0000001, 2154, *p)]
    rows = [forms[0](p) if i < N // 2 else forms[i % len(forms)](p) for i, p in enumerate(xyz)]
    colors = {"red": rng.integers(0, 9, N).astype(np.uint8) * 20, "green": (np.arange(N) % 200).astype(np.uint8),
              "blue": np.zeros(N, np.uint8)}
    pq.write_table(pa.table({"wkb": pa.array(rows), **colors}), tmp_path / "in.parquet")
    pq.write_table(pa.table({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], **colors}), tmp_path / "xyz.parquet")
    prism_stream.sample(str(tmp_path / "xyz.parquet"), str(tmp_path / "want.xyz"), ratio=0.3, seed=4, space=0.5)
    want = read_back(tmp_path / "want.xyz")
    for size in (700, 1500, 1 << 20):
        out = tmp_path / f"o{size}.xyz"
        with _quiet():
            prism_stream.sample(str(tmp_path / "in.parquet"), str(out), ratio=0.3, seed=4, space=0.5,
                                chunk_size=size)
        assert np.array_equal(read_back(out), want), size
    flat = [struct.pack("<BIdd", 1, 1, *p[:2]) for p in xyz]  # 2D: z = 0
    from prism_stream.formats.geo import wkb_xyz

    got = np.column_stack(wkb_xyz(pa.array(flat[:3] + rows[-3:]), "wkb", "f"))
    assert np.array_equal(got[:3], np.column_stack([xyz[:3, :2], np.zeros(3)])) and np.array_equal(got[3:], xyz[-3:])


@pytest.mark.parametrize("ext", ["las", "xyz", "ply"])
def test_coordinates_by_type_alike_for_every_reader_and_refused_before_pass_one(tmp_path, monkeypatch, ext):
    """A text ``x`` beside numeric X, Y, Z: the writers took the text (XYZ wrote it as coordinates, LAS failed
    with an internal error) while --space refused; the numeric columns are the coordinates for all of them now.
    Text x, y, z alone, or a GeoParquet primary column of integers, are refused before a point is decoded,
    saying why (a hostile tester's finds)."""
    import json

    from prism_stream.formats import parquet as parquet_format

    rng = np.random.default_rng(11)
    xyz = rng.random((N, 3))
    colors = {"red": rng.integers(0, 9, N).astype(np.uint8) * 20, "green": (np.arange(N) % 200).astype(np.uint8),
              "blue": np.zeros(N, np.uint8)}
    pq.write_table(pa.table({"X": xyz[:, 0], "Y": xyz[:, 1], "Z": xyz[:, 2], "x": pa.array(["note"] * N),
                             **colors}), tmp_path / "mixed.parquet")
    pq.write_table(pa.table({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], **colors}), tmp_path / "xyz.parquet")
    for name in ("mixed", "xyz"):
        with _quiet():
            prism_stream.sample(str(tmp_path / f"{name}.parquet"), str(tmp_path / f"{name}.{ext}"), ratio=0.3,
                                seed=4, space=0.5)
    assert np.array_equal(read_back(tmp_path / f"mixed.{ext}"), read_back(tmp_path / f"xyz.{ext}"))
    pq.write_table(pa.table({"x": pa.array(["1"] * N), "y": pa.array(["2"] * N), "z": pa.array(["3"] * N),
                             **colors}), tmp_path / "text.parquet")
    geo = {"version": "1.0.0", "primary_column": "shape", "columns": {"shape": {"encoding": "WKB"}}}
    pq.write_table(pa.table({"shape": np.arange(N), **colors}).replace_schema_metadata(
        {b"geo": json.dumps(geo).encode()}), tmp_path / "intgeo.parquet")
    if ext == "ply":  # PLY writes vertices without coordinates, and says so (below)
        return
    monkeypatch.setattr(parquet_format.ParquetSource, "_batches", lambda *a, **k: (_ for _ in ()).throw(
        AssertionError("a point was decoded")))
    for name, why in (("text", "its column 'x' holds string, not numbers"), ("intgeo", "the input has shape")):
        with pytest.raises(UsageError, match=f"output needs the points' coordinates: .*; {why}"):
            prism_stream.sample(str(tmp_path / f"{name}.parquet"), str(tmp_path / f"o.{ext}"), ratio=0.3)
        assert not (tmp_path / f"o.{ext}").exists()


def test_geometry_from_a_primary_column_of_another_name_and_invalid_geo_metadata(tmp_path, capsys):
    """--geometry over GeoParquet whose primary column is ``shape``: it was refused after both passes, naming
    the staged file; GeoParquet metadata whose primary_column is a list was an internal error (exit 70) in
    sample, eval and info; it is metadata no reader can use, ignored as invalid JSON is (a hostile tester's
    finds)."""
    import json

    from conftest import cli
    from prism_stream.evaluate.cloud import wkb_points

    rng = np.random.default_rng(12)
    xyz = rng.random((N, 3))
    colors = {"red": rng.integers(0, 9, N).astype(np.uint8) * 20, "green": (np.arange(N) % 200).astype(np.uint8),
              "blue": np.zeros(N, np.uint8)}
    table = pa.table({"shape": wkb(xyz), "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], **colors})
    geo = {"version": "1.0.0", "primary_column": "shape", "columns": {"shape": {"encoding": "WKB"}}}
    pq.write_table(table.drop_columns(["x", "y", "z"]).replace_schema_metadata({b"geo": json.dumps(geo).encode()}),
                   tmp_path / "shape.parquet")
    with _quiet():
        prism_stream.sample(str(tmp_path / "shape.parquet"), str(tmp_path / "g.parquet"), ratio=0.3, geometry=True)
    got = pq.read_table(tmp_path / "g.parquet")
    assert np.array_equal(wkb_points(got.column("geometry").combine_chunks()),
                          wkb_points(got.column("shape").combine_chunks()))
    geo["primary_column"] = ["shape"]
    pq.write_table(table.replace_schema_metadata({b"geo": json.dumps(geo).encode()}), tmp_path / "bad.parquet")
    code, _, err = cli(capsys, str(tmp_path / "bad.parquet"), str(tmp_path / "o.xyz"), "--ratio", "0.3", "--quiet")
    assert code == 0 and "internal error" not in err, err
    code, _, err = cli(capsys, "info", str(tmp_path / "bad.parquet"))
    assert code == 0 and "internal error" not in err and "error" not in err, err


@pytest.mark.parametrize("ext", ["xyz", "ply", "las"])
def test_a_null_inside_a_coordinate_list_is_refused_as_a_null_row_is(tmp_path, ext):
    """``[x, null, z]`` in a coordinate list: written as NaN without a word (a hostile tester's find); a point
    without all its coordinates is refused, as a null row of the list is, by the writers and by --space."""
    rng = np.random.default_rng(13)
    rows = [list(p) for p in rng.random((N, 3))]
    rows[5] = [1.0, None, 2.0]
    colors = {"red": rng.integers(0, 9, N).astype(np.uint8), "green": np.zeros(N, np.uint8),
              "blue": np.zeros(N, np.uint8)}
    pq.write_table(pa.table({"position": pa.array(rows, pa.list_(pa.float64(), 3)), **colors}),
                   tmp_path / "in.parquet")
    for options in ({"ratio": 1.0}, {"ratio": 0.5, "space": 0.3}):
        with _quiet(), pytest.raises(PrismError, match="'position' (holds 1 nulls: points with no coordinates"
                                                       "|holds null rows or values)"):
            prism_stream.sample(str(tmp_path / "in.parquet"), str(tmp_path / f"o.{ext}"), **options)
        assert not (tmp_path / f"o.{ext}").exists()


def test_eval_refuses_an_input_without_usable_coordinates_before_it_samples(tmp_path):
    """eval's distance metrics over an input whose coordinate column is text: refused naming its copy of a
    sample, after every method had run (a hostile tester's find); refused naming the input, before any runs."""
    from prism_stream.evaluate import run as eval_run

    rng = np.random.default_rng(14)
    src = tmp_path / "text.parquet"
    pq.write_table(pa.table({"x": pa.array(["1"] * N), "y": np.zeros(N), "z": np.zeros(N),
                             "red": rng.integers(0, 9, N).astype(np.uint8), "green": np.zeros(N, np.uint8),
                             "blue": np.zeros(N, np.uint8)}), src)
    ran = []
    real = eval_run.prism_sample
    eval_run.prism_sample = lambda *a, **k: ran.append(1) or real(*a, **k)
    try:
        with pytest.raises(PrismError, match="text.parquet: the coordinate column 'x' holds string, not numbers"):
            eval_run.evaluate([str(src)], methods=("prism", "random"), ratios=(0.1,))
    finally:
        eval_run.prism_sample = real
    assert ran == []


def test_info_check_and_keep_drop_take_the_coordinates_the_run_reads(tmp_path, capsys):
    """A text ``x`` beside numeric X, Y, Z: info and check ended in an internal error (each took x its own way)
    and --drop x was refused as a coordinate; check warned of EWKB points with an SRID that a run reads, and
    failed on a primary column of integers (a reviewer's finds)."""
    import json
    import struct

    from conftest import cli

    rng = np.random.default_rng(15)
    xyz = rng.random((N, 3))
    colors = {"red": rng.integers(0, 9, N).astype(np.uint8), "green": np.zeros(N, np.uint8),
              "blue": np.zeros(N, np.uint8)}
    ewkb = pa.array([struct.pack("<BIIddd", 1, 0xA0000001, 4326, *p) for p in xyz])
    geo = {"version": "1.0.0", "primary_column": "geometry", "columns": {"geometry": {"encoding": "WKB"}}}
    table = pa.table({"geometry": ewkb, "X": xyz[:, 0], "Y": xyz[:, 1], "Z": xyz[:, 2], "x": pa.array(["t"] * N),
                      **colors})
    src = tmp_path / "text_x.parquet"
    pq.write_table(table.replace_schema_metadata({b"geo": json.dumps(geo).encode()}), src)
    code, out, err = cli(capsys, "info", str(src))
    assert code == 0 and "internal error" not in err, err
    code, out, err = cli(capsys, "check", str(src))
    assert code == 0 and "internal error" not in err and "not WKB points" not in out + err, out + err
    prism_stream.sample(str(src), str(tmp_path / "d.parquet"), ratio=0.3, drop=("x",))
    assert "x" not in pq.read_schema(tmp_path / "d.parquet").names
    geo["primary_column"] = "shape"
    geo["columns"] = {"shape": {"encoding": "WKB"}}
    pq.write_table(pa.table({"shape": np.arange(N), **colors}).replace_schema_metadata(
        {b"geo": json.dumps(geo).encode()}), tmp_path / "int.parquet")
    code, out, err = cli(capsys, "check", str(tmp_path / "int.parquet"))
    assert "GeoParquet primary column 'shape' holds int64, not WKB" in out + err and "internal" not in err


def test_wkb_columns_of_empty_rows_and_check_of_2d_beside_3d_points(tmp_path, capsys):
    """A block of null or empty WKB rows was an internal error (a reshape of rows of no bytes), check said 2D
    points beside points with Z differ from the x, y, z columns, and info read bounds from the wrong columns
    behind a struct (a fourth reviewer's finds)."""
    import json
    import struct

    from conftest import cli

    n = 70_000
    xyz = np.random.default_rng(16).random((n, 3))
    rows = [None] * (1 << 16) + [struct.pack("<BIddd", 1, 1001, *p) if i % 2 else struct.pack("<BIdd", 1, 1, *p[:2])
                                 for i, p in enumerate(xyz[1 << 16:])]
    z = xyz[:, 2].copy()
    z[1 << 16:][0::2] = 0  # the 2D rows' z column says 0, which no WKB point contradicts
    geo = {"version": "1.0.0", "primary_column": "geometry", "columns": {"geometry": {"encoding": "WKB"}}}
    table = pa.table({"geometry": pa.array(rows, pa.binary()), "x": xyz[:, 0], "y": xyz[:, 1], "z": z})
    pq.write_table(table.replace_schema_metadata({b"geo": json.dumps(geo).encode()}), tmp_path / "g.parquet")
    code, out, err = cli(capsys, "check", str(tmp_path / "g.parquet"))
    assert code == 0 and "differ" not in out + err and "All-NaN" not in err and "internal" not in err, out + err
    from prism_stream.formats.geo import wkb_rows

    got, valid, _, why = wkb_rows(pa.array([b""] * 5 + [None]))
    assert not valid.any() and why[:5] == [why[0]] * 5 and "shorter than a WKB header" in why[0]
    pq.write_table(pa.table({"s": pa.array([{"a": 1, "b": 2}] * 5), "x": np.arange(5.0), "y": np.arange(5.0) + 10,
                             "z": np.arange(5.0) + 100, "red": np.zeros(5, np.uint8), "green": np.zeros(5, np.uint8),
                             "blue": np.zeros(5, np.uint8)}), tmp_path / "s.parquet")
    code, out, err = cli(capsys, "info", str(tmp_path / "s.parquet"), "--json")
    assert code == 0
    assert json.loads(out)["files"][0]["bounds"] == {"min": [0.0, 10.0, 100.0], "max": [4.0, 14.0, 104.0]}


def test_ply_output_of_an_input_without_coordinates_says_so(tmp_path):
    """A cloud of colors alone (or x, y without z) written as PLY: vertices without those properties, said in
    a note (it was silent)."""
    src = tmp_path / "colors.parquet"
    pq.write_table(pa.table({"x": np.arange(100.0), "y": np.zeros(100), "red": np.arange(100, dtype=np.uint8),
                             "green": np.zeros(100, np.uint8), "blue": np.zeros(100, np.uint8)}), src)
    with pytest.warns(UserWarning, match="the input has no z coordinate .*its vertices have no z property"):
        prism_stream.sample(str(src), str(tmp_path / "o.ply"), ratio=0.5)
    header = (tmp_path / "o.ply").read_bytes().split(b"end_header")[0]
    assert b"property double x" in header and b"property double y" in header and b" z\n" not in header
    pq.write_table(pa.table({"red": np.arange(100, dtype=np.uint8), "green": np.zeros(100, np.uint8),
                             "blue": np.zeros(100, np.uint8)}), src)
    with pytest.warns(UserWarning, match="the input has no x, y, z coordinates .*no x, y, z properties"):
        prism_stream.sample(str(src), str(tmp_path / "p.ply"), ratio=0.5, overwrite=False)
