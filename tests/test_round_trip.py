"""Round trips: a kept point keeps every attribute, bit for bit, in input order (SPEC 6).

LAS/LAZ: the output's point records are the input's records at the kept
indices, byte for byte, and the header keeps the point format, version,
scales, offsets, VLRs (less the COPC VLR of a COPC input, plus the
provenance VLR), EVLRs, CRS records and extra-bytes dimensions. Parquet: the
schema (types and order) and the input's key-value metadata are kept, and
the rows are the input's rows at the kept indices. LAS to Parquet: x, y, z
are the scaled coordinates, every other dimension is a column of equal values.

Kept indices are recovered from the output itself: the output's records must
be an ordered subsequence of the input's, which is the "input order" promise.
"""

from __future__ import annotations

import copy
import functools
import json
import warnings

import laspy
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream import PrismWarning
from prism_stream.formats import extrabytes
from prism_stream.formats.las import PROVENANCE_USER_ID, _unreadable_wkt

from conftest import edge_file, random_colors, read_las, real_file, write_parquet

# (folder, name): real sensor clouds first, then edge files with extra bytes, NIR, waveforms, COPC
LAS_CLOUDS = [
    ("real", "pdal__autzen_trim.las"),  # LAS 1.2 PF3, GeoTIFF keys
    ("real", "pdal__warsaw_small.las"),  # LAS 1.2 PF3, WKT VLR
    ("real", "pdal__las_with_several_extra_byte_bloc.laz"),  # LAZ 1.4 PF8, two extra-bytes VLRs
    ("real", "laspy__fullwave.laz"),  # LAZ 1.4 PF10, waveform packet descriptor
    ("real", "potree__lion_takanawa.copc.laz"),  # COPC, extra dimension OriginId
    ("edge", "pdal__extrabytes.las"),  # LAS 1.4 PF3 with extra dims, one of them named "Colors"
    ("edge", "loadersgl__pdrf10-1.4.las"),  # PF10: RGB + NIR + waveform, 4 extra bytes
    ("edge", "pdal__1.2-with-color.copc.laz"),  # small COPC
]


def cloud(folder: str, name: str):
    return real_file(name) if folder == "real" else edge_file(name)


@functools.lru_cache(maxsize=4)
def read_shared(path) -> laspy.LasData:
    """A shared (read-only) cloud, decoded once per test session."""
    return read_las(path)


def run(inputs, output, **options) -> prism_stream.Summary:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PrismWarning)
        return prism_stream.sample([str(p) for p in np.atleast_1d(inputs)], str(output), **options)


def records(points: np.ndarray) -> list[bytes]:
    """Each raw point record as bytes."""
    raw = np.ascontiguousarray(points)
    size = raw.dtype.itemsize
    buf = raw.tobytes()
    return [buf[i:i + size] for i in range(0, len(buf), size)]


def kept_indices(full: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """Indices i_0 < i_1 < ... of ``full`` whose records equal ``kept``'s, byte for byte.

    Fails when ``kept`` is not an ordered subsequence of ``full`` (a changed
    attribute, a point that was not in the input, or points out of input order).
    Greedy matching is exact for the subsequence test.
    """
    assert full.dtype == kept.dtype
    a, b = records(full), records(kept)
    out = np.empty(len(b), dtype=np.int64)
    j = 0
    for i, rec in enumerate(a):
        if j < len(b) and rec == b[j]:
            out[j] = i
            j += 1
    assert j == len(b), (f"output record {j} (of {len(b)}) is not an input record after index "
                         f"{out[j - 1] if j else -1}: an attribute changed or input order was lost")
    return out


def vlr_bytes(vlr) -> bytes:
    return vlr.record_data_bytes() if hasattr(vlr, "record_data_bytes") else bytes(vlr.record_data)


def plain_vlrs(vlrs) -> list[tuple]:
    """VLRs as (user, record id, description, bytes), less COPC, provenance and extra-bytes VLRs.

    laspy rewrites the extra-bytes VLR from the point format (merging several
    into one, updating the per-dimension min/max to the written points), so
    those are compared as dimensions instead (``extra_dims``).
    """
    out = []
    for v in vlrs or []:
        if v.user_id in ("copc", PROVENANCE_USER_ID) or isinstance(v, laspy.vlrs.known.ExtraBytesVlr):
            continue
        out.append((v.user_id, v.record_id, v.description, vlr_bytes(v)))
    return out


def extra_dims(header) -> list[tuple]:
    return [(d.name, d.kind, d.num_elements, d.description, None if d.scales is None else list(d.scales),
             None if d.offsets is None else list(d.offsets)) for d in header.point_format.extra_dimensions]


def crs_vlrs(vlrs) -> list[tuple]:
    return [(v.user_id, v.record_id, vlr_bytes(v)) for v in vlrs or [] if v.user_id == "LASF_Projection"]


def assert_header_kept(src: laspy.LasData, out: laspy.LasData) -> None:
    sh, oh = src.header, out.header
    assert oh.point_format.id == sh.point_format.id
    assert oh.point_format.dtype() == sh.point_format.dtype()
    assert str(oh.version) == str(sh.version)
    assert np.array_equal(oh.scales, sh.scales) and np.array_equal(oh.offsets, sh.offsets)
    wkt_bit = 16 if sh.point_format.id >= 6 else 0  # the specification requires it for formats 6 to 10
    assert oh.global_encoding.value == sh.global_encoding.value | wkt_bit
    # the output says prism-stream wrote it; the input's own fields are in the provenance
    assert (oh.system_identifier, oh.generating_software) == ("EXTRACTION", f"prism-stream {prism_stream.__version__}")
    named = copy.deepcopy(sh)
    extrabytes.merge_records(named)  # every extra-bytes record's names, as PDAL reads them
    assert extra_dims(oh) == extra_dims(named)
    assert_extra_stats_true(out)
    # a WKT record pyproj cannot read (warsaw's holds "''") is not copied; every other record is
    readable = [v for v in sh.vlrs if not _unreadable_wkt(v)]
    assert plain_vlrs(oh.vlrs) == plain_vlrs(readable)
    assert crs_vlrs(oh.vlrs) == crs_vlrs(readable)
    assert plain_vlrs(out.evlrs) == plain_vlrs(src.evlrs)
    provenance = [v for v in oh.vlrs if v.user_id == PROVENANCE_USER_ID]
    assert len(provenance) == 1
    told = json.loads(provenance[0].record_data)["input_software"][0]
    assert (told["system_identifier"], told["generating_software"]) == (sh.system_identifier, sh.generating_software)
    assert not any(v.user_id == "copc" for v in [*oh.vlrs, *(out.evlrs or [])])
    # what the header says about the points is about the points written
    assert oh.point_count == len(out.points)
    if len(out.points):
        assert np.allclose(oh.mins, [out.x.min(), out.y.min(), out.z.min()], rtol=0, atol=0.5 * oh.scales.max())
        assert np.allclose(oh.maxs, [out.x.max(), out.y.max(), out.z.max()], rtol=0, atol=0.5 * oh.scales.max())


def assert_extra_stats_true(out: laspy.LasData) -> None:
    """Every extra-bytes descriptor's min/max is the written points' (raw, no-data left out), or not flagged."""
    for d in extrabytes.descriptors(out.header):
        if not 0 < d.data_type <= 30 or not d.options & extrabytes.MIN_MAX:
            continue
        assert len(out.points), f"{d.format_name()}: statistics flagged valid in an empty file"
        values = np.asarray(out.points.array[d.format_name()]).reshape(len(out.points), -1)
        for i in range(d.num_elements()):
            col = values[:, i]
            if d.no_data is not None:
                col = col[col != d.no_data[i]]
            raw_min = np.frombuffer(d._min, dtype=extrabytes._long(d))[i]
            raw_max = np.frombuffer(d._max, dtype=extrabytes._long(d))[i]
            assert (raw_min, raw_max) == (col.min(), col.max()), d.format_name()


def out_extensions(name: str) -> list[str]:
    same = ".laz" if name.endswith(".laz") else ".las"
    other = ".las" if same == ".laz" else ".laz"
    return [same, other]


@pytest.mark.parametrize("folder, name", LAS_CLOUDS)
@pytest.mark.parametrize("change", [False, True], ids=["same-format", "las<->laz"])
def test_keep_everything_is_a_byte_copy(tmp_path, folder, name, change):
    """With k = N every bin is kept whole: the output records are the input records."""
    src_path = cloud(folder, name)
    src = read_shared(src_path)
    out_path = tmp_path / f"all{out_extensions(name)[int(change)]}"
    summary = run(src_path, out_path, k=len(src.points))
    out = laspy.read(out_path)
    assert summary.kept == len(src.points) == len(out.points)
    assert out.points.array.tobytes() == src.points.array.tobytes()
    assert_header_kept(src, out)


SUBSAMPLED = [("real", "pdal__autzen_trim.las", ".las"),
              ("real", "pdal__las_with_several_extra_byte_bloc.laz", ".laz"),
              ("real", "potree__lion_takanawa.copc.laz", ".laz"),
              ("real", "laspy__fullwave.laz", ".laz"),
              ("edge", "pdal__extrabytes.las", ".las")]


@pytest.mark.parametrize("folder, name, ext", SUBSAMPLED)
def test_subsample_keeps_records_whole_and_in_input_order(tmp_path, folder, name, ext):
    src_path = cloud(folder, name)
    src = read_shared(src_path)
    out_path = tmp_path / f"sample{ext}"
    summary = run(src_path, out_path, ratio=0.05, seed=7)
    out = laspy.read(out_path)
    assert 0 < len(out.points) == summary.kept < len(src.points)
    idx = kept_indices(src.points.array, out.points.array)
    assert np.all(np.diff(idx) > 0)
    assert_header_kept(src, out)


def test_two_inputs_concatenate_in_argument_order(tmp_path):
    """Several inputs are one cloud; the output holds the first argument's kept points, then the second's."""
    src = read_shared(real_file("pdal__autzen_trim.las"))
    half = len(src.points) // 2
    first, second = tmp_path / "a_first.las", tmp_path / "b_second.las"
    for path, part in ((first, slice(0, half)), (second, slice(half, None))):
        piece = laspy.LasData(src.header)
        piece.points = src.points[part].copy()
        piece.write(path)
    out_path = tmp_path / "both.las"
    summary = run([second, first], out_path, k=len(src.points))  # not sorted: argument order counts
    out = laspy.read(out_path)
    assert summary.kept == len(src.points)
    assert out.points.array.tobytes() == src.points[half:].array.tobytes() + src.points[:half].array.tobytes()


def test_pathlib_paths_work_like_strings(tmp_path):
    src = real_file("pdal__warsaw_small.las")
    run(src, tmp_path / "as_str.las", ratio=0.5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PrismWarning)
        prism_stream.sample(src, tmp_path / "as_path.las", ratio=0.5)
    a, b = laspy.read(tmp_path / "as_str.las"), laspy.read(tmp_path / "as_path.las")
    assert a.points.array.tobytes() == b.points.array.tobytes()


@pytest.mark.parametrize("ext", [".las", ".laz"])
def test_evlrs_survive(tmp_path, ext):
    """A LAS 1.4 PF7 file with an EVLR (built here: the shared EVLR file has no color)."""
    n = 4000
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = np.array([0.01, 0.01, 0.01])
    header.offsets = np.array([500.0, -20.0, 3.0])
    las = laspy.LasData(header)
    rng = np.random.default_rng(3)
    las.x = rng.uniform(500, 600, n)
    las.y = rng.uniform(-20, 80, n)
    las.z = rng.uniform(3, 13, n)
    rgb = random_colors(n, seed=3, depth=16)
    las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    las.gps_time = np.arange(n, dtype=np.float64)
    las.vlrs.append(laspy.VLR("acme", 1, "a plain VLR", b"kept as is"))
    payload = bytes(range(256)) * 400  # over 65,535 bytes: only an EVLR can hold it
    las.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.VLR("acme", 7, "a large record", payload)])
    src_path = tmp_path / "with_evlr.las"
    las.write(src_path)
    src = laspy.read(src_path)
    assert len(src.evlrs) == 1

    out_path = tmp_path / f"out{ext}"
    run(src_path, out_path, ratio=0.25)
    out = laspy.read(out_path)
    assert [(v.user_id, v.record_id, bytes(v.record_data)) for v in out.evlrs] == [("acme", 7, payload)]
    assert_header_kept(src, out)
    kept_indices(src.points.array, out.points.array)


# --- Parquet -------------------------------------------------------------------------------------------------

def generated_table(n: int = 6000) -> pa.Table:
    """A cloud with many column types, field metadata and file key-value metadata."""
    rng = np.random.default_rng(11)
    rgb = random_colors(n, seed=11)
    normal = pa.FixedSizeListArray.from_arrays(pa.array(rng.normal(size=3 * n).astype(np.float32)), 3)
    schema = pa.schema([
        pa.field("point_id", pa.int64()),
        pa.field("x", pa.float64()), pa.field("y", pa.float64()), pa.field("z", pa.float32()),
        pa.field("Red", pa.uint8()), pa.field("Green", pa.uint8()), pa.field("Blue", pa.uint8()),
        pa.field("intensity", pa.uint16(), metadata={b"unit": b"counts"}),
        pa.field("classification", pa.int8()),
        pa.field("ground", pa.bool_()),
        pa.field("when", pa.timestamp("us")),
        pa.field("label", pa.string()),
        pa.field("maybe", pa.float64(), nullable=True),
        pa.field("normal", pa.list_(pa.float32(), 3)),
    ], metadata={b"origin": b"generated for test_round_trip", b"crs": b"EPSG:32633"})
    maybe = rng.normal(size=n)
    columns = [
        np.arange(n, dtype=np.int64),
        rng.uniform(0, 100, n), rng.uniform(0, 100, n), rng.uniform(0, 10, n).astype(np.float32),
        rgb[:, 0].astype(np.uint8), rgb[:, 1].astype(np.uint8), rgb[:, 2].astype(np.uint8),
        rng.integers(0, 65536, n).astype(np.uint16),
        rng.integers(-128, 128, n).astype(np.int8),
        rng.random(n) < 0.3,
        pa.array(np.arange(n).astype("datetime64[us]")),
        pa.array([f"p{i}" for i in range(n)]),
        pa.array(maybe, mask=rng.random(n) < 0.1),
        normal,
    ]
    return pa.Table.from_arrays([c if isinstance(c, (pa.Array, pa.ChunkedArray)) else pa.array(c) for c in columns],
                                schema=schema)


def assert_parquet_schema_kept(src_path, out_path) -> pa.Schema:
    src_schema = pq.ParquetFile(src_path).schema_arrow
    out_schema = pq.ParquetFile(out_path).schema_arrow
    assert out_schema.names == src_schema.names
    for a, b in zip(src_schema, out_schema):
        assert (b.name, b.type, b.nullable, b.metadata) == (a.name, a.type, a.nullable, a.metadata)
    src_meta, out_meta = src_schema.metadata or {}, out_schema.metadata or {}
    for key, value in src_meta.items():
        assert out_meta.get(key) == value, f"metadata {key!r} not kept"
    # GeoParquet: the 'geo' key of the input's file metadata comes along (version 1.1.0, its columns)
    file_meta = pq.ParquetFile(src_path).metadata.metadata or {}
    assert all(k in src_meta or k.startswith(b"prism_stream") or k == b"geo" and k in file_meta for k in out_meta)
    if b"geo" in file_meta:
        src_geo, out_geo = json.loads(file_meta[b"geo"]), json.loads(out_meta[b"geo"])
        assert out_geo["columns"] == src_geo["columns"] and out_geo["primary_column"] == src_geo["primary_column"]
    return out_schema


def test_parquet_keep_everything_is_the_same_table(tmp_path):
    src_path = write_parquet(tmp_path / "in.parquet", generated_table(), row_group_size=1000)
    out_path = tmp_path / "out.parquet"
    run(src_path, out_path, k=10**9, rgb_columns=("Red", "Green", "Blue"))
    assert_parquet_schema_kept(src_path, out_path)
    assert pq.read_table(out_path).equals(pq.read_table(src_path))


def test_parquet_subsample_rows_are_input_rows_in_order(tmp_path):
    table = generated_table()
    src_path = write_parquet(tmp_path / "in.parquet", table, row_group_size=1000)
    out_path = tmp_path / "out.parquet"
    summary = run(src_path, out_path, ratio=0.1, seed=5, rgb_columns=("Red", "Green", "Blue"), chunk_size=777)
    assert_parquet_schema_kept(src_path, out_path)
    out = pq.read_table(out_path)
    ids = out.column("point_id").to_numpy()
    assert len(ids) == summary.kept > 0
    assert np.all(np.diff(ids) > 0), "rows are not in input order"
    assert out.equals(table.take(pa.array(ids)).replace_schema_metadata(out.schema.metadata))


def test_geoparquet_from_pdal_round_trips(tmp_path):
    """PDAL's GeoParquet: xyz as fixed_size_list, WKB geometry, 'geo' metadata; no id column to lean on."""
    src_path = edge_file("pdal__1.2-with-color.parquet")
    src = pq.read_table(src_path)
    out_all = tmp_path / "all.parquet"
    run(src_path, out_all, k=src.num_rows)
    assert_parquet_schema_kept(src_path, out_all)
    assert pq.read_table(out_all).equals(src)

    out_some = tmp_path / "some.parquet"
    summary = run(src_path, out_some, ratio=0.2)
    assert_parquet_schema_kept(src_path, out_some)
    rows = pq.read_table(out_some).to_pylist()
    assert len(rows) == summary.kept > 0
    src_rows = src.to_pylist()
    j = 0
    for row in src_rows:
        if j < len(rows) and row == rows[j]:
            j += 1
    assert j == len(rows), "output rows are not the input's rows in input order"


# --- LAS to Parquet ------------------------------------------------------------------------------------------

def column_values(table: pa.Table, name: str) -> np.ndarray:
    col = table.column(name).combine_chunks()
    if pa.types.is_fixed_size_list(col.type):
        return col.flatten().to_numpy(zero_copy_only=False).reshape(len(col), col.type.list_size)
    return col.to_numpy(zero_copy_only=False)


def assert_columns_are_dimensions(table: pa.Table, points: laspy.ScaleAwarePointRecord) -> None:
    dims = list(points.point_format.dimension_names)
    expected = [d.lower() if d in ("X", "Y", "Z") else d for d in dims]
    assert table.column_names == expected
    for dim in dims:
        if dim in ("X", "Y", "Z"):
            got = column_values(table, dim.lower())
            assert got.dtype == np.float64
            assert np.array_equal(got, np.asarray(getattr(points, dim.lower()), dtype=np.float64))
        else:
            want = np.asarray(points[dim])
            got = column_values(table, dim)
            assert np.array_equal(got, want.astype(got.dtype)) and np.array_equal(got.astype(want.dtype), want), dim


@pytest.mark.parametrize("folder, name", [("real", "pdal__autzen_trim.las"),
                                          ("real", "pdal__las_with_several_extra_byte_bloc.laz"),
                                          ("real", "laspy__fullwave.laz"),
                                          ("edge", "pdal__extrabytes.las")])
def test_las_to_parquet_keeps_every_dimension(tmp_path, folder, name):
    src_path = cloud(folder, name)
    src = read_shared(src_path)
    out_all = tmp_path / "all.parquet"
    run(src_path, out_all, k=len(src.points))
    assert_columns_are_dimensions(pq.read_table(out_all), src.points)

    # a real subsample: the Parquet rows are the dimensions of the records the LAS output keeps
    as_las, as_parquet = tmp_path / "some.las", tmp_path / "some.parquet"
    run(src_path, as_las, ratio=0.1, seed=3)
    run(src_path, as_parquet, ratio=0.1, seed=3)
    idx = kept_indices(src.points.array, laspy.read(as_las).points.array)
    assert_columns_are_dimensions(pq.read_table(as_parquet), src.points[idx])

    source_meta = pq.ParquetFile(as_parquet).schema_arrow.metadata or {}
    assert b"prism_stream_source" in source_meta
