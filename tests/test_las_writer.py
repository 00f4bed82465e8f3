"""The LAS/LAZ writers keep the file a LAS reader expects (issue 13).

From LAS inputs (``las.LasSink``): the first input's header (version, point
format, scales, offsets, system and software names), its VLRs and EVLRs
(COPC's octree records excepted), its extra-bytes dimensions with their
types and descriptions, and every kept record byte for byte; the header's
point count, points by return and bounds are the kept points'. Exactly one
provenance VLR, this run's, even when the input was itself written by
prism-stream (for PLY too: one provenance comment).

From other inputs (``lasbuild.ConvertedLasSink``): coordinates from an
``xyz`` vector column; the int32 edge of a grid carried from a LAS source;
a column stored in a standard dimension of another type named; extra-bytes
names of 1 to 32 bytes; the chosen grid is the finest power of two that
holds the extent.

Expectations come from the input file (read with laspy) and the oracle's
kept rows (tests/oracle.py), never from prism_stream.
"""

from __future__ import annotations

import json
import math
import os
import warnings

import laspy
import numpy as np
import plyfile
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from laspy.vlrs.vlrlist import VLRList

import prism_stream
from prism_stream import PrismWarning
from prism_stream.errors import UnsupportedFormat, UsageError
from prism_stream.formats import extrabytes
from prism_stream.formats import las as las_format
from prism_stream.formats.las import read_provenance

import oracle
from conftest import edge_file, random_colors, write_las, write_parquet

N = 600
RATIO = 0.3
SEED = 5


def provenance_vlrs(las) -> list[dict]:
    return [json.loads(bytes(v.record_data)) for v in las.header.vlrs
            if v.user_id == "prism-stream" and v.record_id == 1]


def vlr_facts(vlrs) -> list[tuple]:
    return [(v.user_id, v.record_id, v.description, bytes(v.record_data_bytes())) for v in vlrs]


def run(src, out, **options):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = prism_stream.sample(str(src), str(out), **options)
    return summary, [str(w.message) for w in caught if issubclass(w.category, PrismWarning)]


@pytest.fixture(scope="module")
def las14(tmp_path_factory):
    """LAS 1.4, point format 7: its own grid and names, an extra-bytes dimension, an app VLR and EVLR, returns."""
    path = tmp_path_factory.mktemp("las14") / "in.las"
    rgb = random_colors(N, seed=4, palette=50, depth=16)
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = np.array([0.01, 0.001, 0.25])
    header.offsets = np.array([500.0, -20.0, 3.0])
    header.system_identifier = "test system"
    header.generating_software = "test software"
    header.add_extra_dim(laspy.ExtraBytesParams(name="ident", type=np.uint32, description="record id"))
    header.vlrs.append(laspy.VLR("some-app", 7, "an app's own VLR", b"vlr payload"))
    las = laspy.LasData(header)
    i = np.arange(N)
    las.x = i * 0.01 + 500.0
    las.y = (i % 97) * 0.001 - 20.0
    las.z = (i % 13) * 0.25 + 3.0
    las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    las.return_number = (i % 3 + 1).astype(np.uint8)
    las.number_of_returns = np.full(N, 3, np.uint8)
    las.classification = (i % 7).astype(np.uint8)
    las.gps_time = i * 0.5
    las.ident = (i * 11 + 1).astype(np.uint32)
    las.evlrs = VLRList([laspy.VLR("some-app", 8, "an app's own EVLR", b"evlr payload " * 20)])
    las.write(str(path))
    return path


@pytest.mark.parametrize("ext", ["las", "laz"])
def test_las_to_las_keeps_the_header_records_vlrs_and_evlrs(tmp_path, las14, ext):
    src = laspy.read(str(las14))
    out = tmp_path / f"out.{ext}"
    summary, _ = run(las14, out, ratio=RATIO, seed=SEED)
    rows = oracle.sample([(src.red, src.green, src.blue)], ratio=RATIO, seed=SEED).kept[0]
    got = laspy.read(str(out))
    h, g = src.header, got.header

    assert (str(g.version), g.point_format.id) == ("1.4", 7)
    assert np.array_equal(g.scales, h.scales) and np.array_equal(g.offsets, h.offsets)
    # the output names its writer (LAS "EXTRACTION": points taken from other files); the input's are in the provenance
    assert (g.system_identifier, g.generating_software) == ("EXTRACTION", f"prism-stream {prism_stream.__version__}")
    told = read_provenance(str(out))["input_software"]
    assert [(t["system_identifier"], t["generating_software"]) for t in told] == [("test system", "test software")]
    ident = next(d for d in extrabytes.descriptors(g) if d.format_name() == "ident")
    assert (ident.min[0], ident.max[0]) == (got.ident.min(), got.ident.max())  # true, not laspy's first element
    assert got.points.array.tobytes() == src.points.array[rows].tobytes(), "kept records differ from the input's"

    # counts and bounds are the kept points'
    assert g.point_count == len(rows) == summary.kept
    kept_returns = np.asarray(src.return_number)[rows]
    assert list(g.number_of_points_by_return) == [int(np.sum(kept_returns == r)) for r in range(1, 16)]
    xyz = np.stack([np.asarray(src.x), np.asarray(src.y), np.asarray(src.z)], axis=1)[rows]
    assert np.allclose(g.mins, xyz.min(axis=0)) and np.allclose(g.maxs, xyz.max(axis=0))

    # the extra-bytes dimension: its type and description
    dims = {d.name: d for d in got.point_format.extra_dimensions}
    assert dims["ident"].dtype == np.uint32 and dims["ident"].description.rstrip("\0") == "record id"
    assert np.array_equal(np.asarray(got.ident), np.asarray(src.ident)[rows])

    # the input's VLRs and this run's provenance; the EVLR as it was (the extra-bytes VLR is checked above:
    # laspy places it and writes the kept values' range in it)
    def own(vlrs):
        return [v for v in vlrs if v.user_id != "prism-stream" and (v.user_id, v.record_id) != ("LASF_Spec", 4)]

    assert [(v.user_id, v.record_id) for v in g.vlrs if v.user_id == "LASF_Spec"] == [("LASF_Spec", 4)]
    assert vlr_facts(own(g.vlrs)) == vlr_facts(own(h.vlrs)) != []
    assert vlr_facts(got.evlrs) == vlr_facts(src.evlrs)
    [prov] = provenance_vlrs(got)
    assert (prov["points"], prov["kept"], prov["seed"]) == (N, len(rows), SEED)


@pytest.mark.parametrize("ext", ["las", "ply"])
def test_sampling_an_output_again_gives_one_provenance_this_runs(tmp_path, ext):
    """A prism-stream output carries its run's provenance; sampled again, the new output carries only the new run's."""
    src = write_las(tmp_path / "in.las", random_colors(N, seed=2, palette=40), point_format=3)
    first = tmp_path / f"first.{ext}"
    run(src, first, ratio=0.5, seed=1)
    again = tmp_path / f"again.{ext}"
    summary, _ = run(first, again, ratio=0.5, seed=2)
    if ext == "las":
        provs = provenance_vlrs(laspy.read(str(again)))
        mine = las_format.read_provenance(str(again))
    else:
        from prism_stream.formats import ply

        comments = plyfile.PlyData.read(str(again)).comments
        provs = [json.loads(ply.provenance_text(comments))] * sum(c.startswith("prism-stream {") for c in comments)
        mine = ply.read_provenance(str(again))
    assert len(provs) == 1, f"{len(provs)} provenance records"
    assert provs[0]["seed"] == 2 and provs[0]["points"] == summary.points == math.floor(0.5 * N + 0.5)
    assert mine == provs[0]


def test_copc_records_are_not_written_to_a_plain_laz(tmp_path):
    src = edge_file("pdal__1.2-with-color.copc.laz")
    out = tmp_path / "out.laz"
    run(src, out, ratio=0.5)
    got = laspy.read(str(out))
    records = [v.user_id for v in [*got.header.vlrs, *(got.evlrs or [])]]
    assert "copc" not in records
    inp = laspy.read(str(src))
    kept = [(v.user_id, v.record_id) for v in [*inp.header.vlrs, *(inp.evlrs or [])] if v.user_id != "copc"]
    assert [(v.user_id, v.record_id) for v in got.header.vlrs if v.user_id != "prism-stream"] + \
        [(v.user_id, v.record_id) for v in (got.evlrs or [])] == kept


def test_provenance_too_large_for_a_vlr_leaves_out_the_sources(tmp_path):
    """A VLR holds 65,535 bytes: beyond that the per-source list goes, and how many sources there were stays."""
    small = {"kept": 3, "seed": 1, "sources": [{"path": "a.las"}]}
    vlr = las_format.provenance_vlr(small)
    assert json.loads(bytes(vlr.record_data)) == small
    fits = {"kept": 3, "seed": 1, "sources": [{"path": ""}]}
    fits["sources"][0]["path"] = "p" * (65535 - len(json.dumps(fits, sort_keys=True).encode()))
    assert len(json.dumps(fits, sort_keys=True).encode()) == 65535  # exactly what a VLR holds: kept whole
    assert json.loads(bytes(las_format.provenance_vlr(fits).record_data)) == fits
    many = {"kept": 3, "seed": 1, "sources": [{"path": f"tile-{i:05d}.las", "color_depth": "8"} for i in range(3000)]}
    assert len(json.dumps(many)) > 65535
    vlr = las_format.provenance_vlr(many)
    assert json.loads(bytes(vlr.record_data)) == {"kept": 3, "seed": 1, "sources_omitted": 3000}
    assert (vlr.user_id, vlr.record_id) == ("prism-stream", 1)


def test_flag_names_up_to_32_bytes(tmp_path):
    src = write_las(tmp_path / "in.las", random_colors(N, seed=3, palette=30), point_format=3)
    name = "k" * 32
    run(src, tmp_path / "ok.las", ratio=0.5, flag=name)
    got = laspy.read(str(tmp_path / "ok.las"))
    assert got.header.point_count == N and int(np.sum(got[name])) == math.floor(0.5 * N + 0.5)
    with pytest.raises(UsageError, match="32 bytes"):
        run(src, tmp_path / "no.las", ratio=0.5, flag=name + "k")
    assert not (tmp_path / "no.las").exists()


def test_inputs_of_two_point_formats_are_refused(tmp_path):
    a = write_las(tmp_path / "a.las", random_colors(N, seed=1), point_format=3)
    b = write_las(tmp_path / "b.las", random_colors(N, seed=2), point_format=7, version="1.4")
    with pytest.raises(UsageError, match="mix point formats 3 and 7"):
        prism_stream.sample([str(a), str(b)], str(tmp_path / "out.las"), ratio=0.5)
    assert not (tmp_path / "out.las").exists()


# -- LAS built from other formats ------------------------------------------------------------------------

def colors(n=N, seed=6):
    rgb = random_colors(n, seed=seed, palette=30)
    return {"red": rgb[:, 0].astype(np.uint8), "green": rgb[:, 1].astype(np.uint8),
            "blue": rgb[:, 2].astype(np.uint8)}


def test_coordinates_from_one_xyz_vector_column(tmp_path):
    i = np.arange(N, dtype=np.float64)
    xyz = np.stack([i * 0.5, 1000.0 - i, i % 17 + 0.25], axis=1)
    cols = colors()
    table = pa.table({"xyz": pa.FixedSizeListArray.from_arrays(pa.array(xyz.ravel()), 3),
                      **{k: pa.array(v) for k, v in cols.items()}})
    src = write_parquet(tmp_path / "in.parquet", table)
    out = tmp_path / "out.las"
    run(src, out, ratio=RATIO, seed=SEED)
    rows = oracle.sample([(cols["red"], cols["green"], cols["blue"])], ratio=RATIO, seed=SEED).kept[0]
    got = laspy.read(str(out))
    for axis, name in enumerate("xyz"):
        step = got.header.scales[axis]
        assert np.abs(np.asarray(got[name]) - xyz[rows, axis]).max() <= step / 2 * (1 + 1e-9), name
    assert list(got.point_format.extra_dimension_names) == [], "the coordinates were written twice"


@pytest.mark.parametrize("kind", ["float64", "float32"])
def test_the_default_grid_is_a_power_of_ten_as_fine_as_the_input(tmp_path, kind):
    """Issue 28, item 9: the default grid was span / 2^32 rounded to a power of two (9.3e-10 on a 2 m model,
    a few metres of range). Now: the largest power of ten not above the input's precision, a millionth
    of the extent, and for float32 no coarser than the float32 spacing at the largest magnitude."""
    i = np.arange(N, dtype=np.float64)
    cols = {"x": 123456.789 + i * 37.1, "y": -5.0 + i * 1e-3, "z": np.full(N, 7.5), "w": 0.3 + i * 1e-3, **colors()}
    if kind == "float32":
        cols = {k: v.astype(np.float32) if k in "xyzw" else v for k, v in cols.items()}
    cols["z"], cols["w"] = cols["w"], cols["z"]  # z: a one-metre extent near zero; w: an extra column
    src = write_parquet(tmp_path / "in.parquet", cols)
    out = tmp_path / "out.las"
    _, said = run(src, out, ratio=1.0)
    got = laspy.read(str(out))
    for axis, name in enumerate("xyz"):
        v, scale, offset = cols[name].astype(np.float64), got.header.scales[axis], got.header.offsets[axis]
        span = v.max() - v.min()
        assert f"{scale:g}" == f"1e{round(math.log10(scale))}" or scale == 10.0 ** round(math.log10(scale)), \
            f"{name}: scale {scale} is not a power of ten"
        precision = span / 2 ** 20
        if kind == "float32":
            precision = min(precision, float(np.spacing(np.float32(np.abs(v).max()))))
        assert scale <= precision < 10 * scale, f"{name}: scale {scale} for a precision of {precision}"
        assert abs(offset / scale - round(offset / scale)) < 1e-6, f"{name}: the offset is not on the grid"
        assert abs(offset - (v.min() + span / 2)) <= span / 2, f"{name}: the offset is outside the extent"
        reach = 2 ** 31 * scale  # each side of the offset
        assert reach >= (200 if kind == "float64" else 6) * span, f"{name}: the grid reaches {reach} for {span}"
        # within half a step (a value halfway between two steps, and float64's own rounding at its magnitude)
        assert np.abs(np.asarray(got[name]) - v).max() <= scale / 2 + 4 * np.spacing(np.abs(v).max()), name
    assert any("coordinates stored as LAS 32-bit integers on a grid of" in m and "--scale" in m for m in said)


def carried_grid_parquet(tmp_path, x_last):
    """A Parquet that says it came from a LAS file on a 1/1000 grid at offset 0 (prism-stream's own metadata)."""
    n = 20
    x = np.arange(n, dtype=np.float64)
    x[-1] = x_last
    table = pa.table({"x": x, "y": np.zeros(n), "z": np.zeros(n), **{k: v[:n] for k, v in colors().items()}})
    facts = {"scales": [0.001] * 3, "offsets": [0.0] * 3, "point_format": 3}
    table = table.replace_schema_metadata({b"prism_stream_source": json.dumps(facts).encode()})
    path = tmp_path / "in.parquet"
    pq.write_table(table, path)
    return path


@pytest.mark.parametrize("steps, fits", [(2 ** 31 - 1, True), (2 ** 31, False), (-(2 ** 31), True),
                                         (-(2 ** 31) - 1, False)])
def test_a_carried_grid_holds_exactly_the_int32_range(tmp_path, steps, fits):
    src = carried_grid_parquet(tmp_path, steps * 0.001)
    out = tmp_path / "out.las"
    if fits:
        run(src, out, ratio=1.0)
        got = laspy.read(str(out))
        assert got.header.scales.tolist() == [0.001] * 3 and int(np.asarray(got.X)[-1]) == steps
    else:
        with pytest.raises(UnsupportedFormat, match="coordinate x does not fit the source's LAS scale and offset"):
            run(src, out, ratio=1.0)
        assert not out.exists()


def test_a_column_stored_in_a_standard_dimension_of_another_type_is_named(tmp_path):
    n = 50
    cols = {"x": np.arange(n, dtype=np.float64), "y": np.zeros(n), "z": np.zeros(n),
            "intensity": np.arange(n, dtype=np.uint32),  # LAS intensity is uint16
            "return_number": np.ones(n, dtype=np.int64),  # a 4-bit field
            "classification": np.full(n, 2, dtype=np.uint8),  # LAS's own type: nothing to say
            "number_of_returns": np.ones(n, dtype=np.uint8),  # unsigned in a bit field: nothing to say
            **{k: v[:n] for k, v in colors().items()}}
    src = write_parquet(tmp_path / "in.parquet", cols)
    out = tmp_path / "out.las"
    _, notes = run(src, out, ratio=1.0)
    said = {name: [m for m in notes if f"column '{name}'" in m] for name in
            ("intensity", "return_number", "classification", "number_of_returns")}
    assert len(said["intensity"]) == 1 and "LAS dimension intensity (uint16)" in said["intensity"][0], notes
    assert len(said["return_number"]) == 1 and "a bit field" in said["return_number"][0], notes
    assert not said["classification"] and not said["number_of_returns"], notes
    got = laspy.read(str(out))
    assert np.array_equal(np.asarray(got.intensity), cols["intensity"])
    assert np.array_equal(np.asarray(got.return_number), cols["return_number"])


def test_extra_bytes_names_hold_1_to_32_bytes(tmp_path):
    n = 50
    table = pa.table({"x": np.arange(n, dtype=np.float64), "y": np.zeros(n), "z": np.zeros(n),
                      **{k: v[:n] for k, v in colors().items()},
                      "": np.arange(n, dtype=np.int16), "a" * 32: np.arange(n, dtype=np.int16),
                      "b" * 33: np.arange(n, dtype=np.int16)})
    src = write_parquet(tmp_path / "in.parquet", table)
    out = tmp_path / "out.las"
    _, notes = run(src, out, ratio=1.0)
    got = laspy.read(str(out))
    extra = list(got.point_format.extra_dimension_names)
    assert extra == ["a" * 32]
    for name in ("", "b" * 33):
        said = [m for m in notes if f"column {name!r} (int16) dropped" in m]
        assert len(said) == 1 and "1 to 32 bytes" in said[0], notes


def test_a_vector_column_is_not_split_onto_names_already_taken(tmp_path):
    """A 3-vector ``n`` becomes n_0, n_1, n_2 unless a column already has one of those names: then it is dropped."""
    n = 40
    vec = pa.FixedSizeListArray.from_arrays(pa.array(np.arange(3 * n, dtype=np.float32)), 3)
    table = pa.table({"x": np.arange(n, dtype=np.float64), "y": np.zeros(n), "z": np.zeros(n),
                      **{k: v[:n] for k, v in colors().items()}, "n": vec, "n_1": np.arange(n, dtype=np.int16),
                      "m": vec})
    src = write_parquet(tmp_path / "in.parquet", table)
    out = tmp_path / "out.las"
    _, notes = run(src, out, ratio=1.0)
    got = laspy.read(str(out))
    assert sorted(got.point_format.extra_dimension_names) == ["m_0", "m_1", "m_2", "n_1"]
    assert np.array_equal(np.asarray(got["n_1"]), np.arange(n, dtype=np.int16))
    assert len([m for m in notes if "column 'n' " in m and "dropped" in m]) == 1, notes


def test_a_value_a_dimension_cannot_hold_is_quoted_first_one_first(tmp_path):
    n = 40
    cls = np.full(n, 2, dtype=np.int32)
    cls[5], cls[30] = 300, 999  # LAS 1.4 classification is uint8: the first that does not fit is 300
    cols = {"x": np.arange(n, dtype=np.float64), "y": np.zeros(n), "z": np.zeros(n), "classification": cls,
            **{k: v[:n] for k, v in colors().items()}}
    src = write_parquet(tmp_path / "in.parquet", cols)
    out = tmp_path / "out.las"
    with pytest.raises(UnsupportedFormat) as refused:
        run(src, out, ratio=1.0)
    assert str(refused.value).startswith(f"{out}: column 'classification' holds the value 300, which LAS dimension")
    assert not out.exists()


def test_non_las_inputs_of_two_layouts_are_refused(tmp_path):
    n = 30
    base = {"x": np.arange(n, dtype=np.float64), "y": np.zeros(n), "z": np.zeros(n),
            **{k: v[:n] for k, v in colors().items()}}
    a = write_parquet(tmp_path / "a.parquet", base)
    b = write_parquet(tmp_path / "b.parquet", {**base, "more": np.arange(n, dtype=np.int16)})
    out = tmp_path / "out.las"
    with pytest.raises(UnsupportedFormat) as refused:
        prism_stream.sample([str(a), str(b)], str(out), ratio=0.5)
    assert str(refused.value).startswith(f"{b}: its attributes differ from a.parquet's")
    assert not out.exists()


def _tile(path, xyz, scale, offset):
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([scale] * 3)
    header.offsets = np.array([offset] * 3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    rgb = np.random.default_rng(len(xyz)).integers(0, 256, (len(xyz), 3))
    las.red, las.green, las.blue = rgb.T
    las.write(str(path))
    return path


def test_an_input_off_the_first_inputs_grid_is_refused_before_reading(tmp_path):
    """One LAS output writes every input on the first one's grid: a file far from it would be clamped to
    the 32-bit edge (silently, by laspy's rescaling): refused, naming the file."""
    rng = np.random.default_rng(1)
    a = _tile(tmp_path / "a.las", rng.uniform(4e9, 4e9 + 100, (500, 3)), 0.01, 4e9)
    b = _tile(tmp_path / "b.las", rng.uniform(0, 100, (500, 3)), 0.01, 0.0)
    with pytest.raises(UsageError, match=r"b\.las.*do not fit the LAS grid of a\.las"):
        prism_stream.sample([str(a), str(b)], str(tmp_path / "out.las"), ratio=0.5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.las", "b.las"]
    prism_stream.sample([str(a), str(b)], str(tmp_path / "out.parquet"), ratio=0.5)  # Parquet keeps both


def test_a_coarser_grid_is_said(tmp_path):
    rng = np.random.default_rng(2)
    a = _tile(tmp_path / "a.las", rng.uniform(0, 100, (500, 3)), 0.01, 0.0)
    b = _tile(tmp_path / "b.las", rng.uniform(0, 100, (500, 3)), 0.001, 0.0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        prism_stream.sample([str(a), str(b)], str(tmp_path / "out.las"), ratio=0.5)
    assert any("points of b.las written on the grid of a.las" in str(w.message) for w in caught)


@pytest.mark.parametrize("ext", [".las", ".laz", ".copc.laz"])
def test_a_coordinate_las_cannot_hold_is_a_usage_error_on_every_las_writer(tmp_path, ext):
    """NaN and infinite coordinates (valid in Parquet and PLY) in the selected points: exit 2, one line naming the
    input and what to write instead, no output (it was exit 4, 'not a point cloud format')."""
    from prism_stream.errors import UsageError

    n = 1_000
    x, y = np.arange(n, dtype=np.float64), np.zeros(n)
    x[5], y[7] = np.nan, np.inf
    src = tmp_path / "nan.parquet"
    pq.write_table(pa.table({"x": x, "y": y, "z": np.zeros(n), "red": (np.arange(n) % 256).astype(np.uint8),
                             "green": np.zeros(n, np.uint8), "blue": np.zeros(n, np.uint8)}), src)
    out = tmp_path / f"out{ext}"
    with pytest.raises(UsageError, match="which LAS, LAZ and COPC cannot store; write Parquet or PLY") as caught:
        prism_stream.sample(str(src), str(out), ratio=1.0)
    assert caught.value.exit_code == 2 and str(caught.value).startswith(str(src))
    assert os.listdir(tmp_path) == ["nan.parquet"]
    prism_stream.sample(str(src), str(tmp_path / "out.ply"), ratio=1.0)  # PLY holds them
