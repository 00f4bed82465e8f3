"""Every writer's output of every real cloud read back by readers this project did not write (issue 31).

The readers pip brings: the LASzip C++ decoder (PyPI ``laszip``), copclib (copc-lib's C++ reader),
laspy's COPC reader with a window query against brute force, geopandas for GeoParquet, plyfile.
Each check compares what the reader finds with the run's own summary and with the same sample in
another writer's output: counts, bounds, colors, CRS, extra-bytes names and statistics; not only
that the file opens. The readers that need more than pip (the npm ``copc`` reader of web viewers,
Open3D, PDAL) are run by ``bench/interop.py``.
"""

from __future__ import annotations

import functools
import warnings

import copclib
import geopandas
import laspy
import laszip
import numpy as np
import plyfile
import pyarrow.parquet as pq
import pyproj
import pytest

import prism_stream
from prism_stream.formats import extrabytes
from prism_stream.formats.validate import validate

from conftest import read_las, real_file

SEED = 31
WRITERS = ["las", "laz", "copc.laz", "parquet", "geo.parquet", "ply"]
# every real cloud in every writer, a sample of 1,500 points each: CRSs as GeoTIFF keys and WKT (and an
# unreadable WKT, warsaw's), extra bytes in two records with a no-data value (IGN), float normals and
# photogrammetry PLYs and a PCD converted to LAS 1.4 format 7, a waveform format 10 tile written as COPC
# format 8, a COPC input
CASES = {name.split("__", 1)[1].split(".", 1)[0]: (name, {"count": 1500}, WRITERS) for name in (
    "pdal__autzen_trim.las", "pdal__las_with_several_extra_byte_bloc.laz", "potree__lion_takanawa.copc.laz",
    "laspy__fullwave.laz", "pdal__warsaw_small.las", "odm__option-0000.ply", "open3d__frag_115.ply",
    "pcl__office1.pcd")}
OUTPUTS = [(case, ext) for case, (_, _, exts) in CASES.items() for ext in exts]


class Written(dict):
    """The outputs of CASES, each written the first time a test asks for it: (case, ext) -> (path, summary).
    (Lazily: under pytest-xdist each worker writes only the outputs its tests read.)"""

    def __init__(self, folder):
        super().__init__()
        self.folder = folder

    def __missing__(self, key):
        case, ext = key
        name, options, _ = CASES[case]
        path = self.folder / f"{case}.{ext}"
        extra = {"geometry": True} if ext == "geo.parquet" else {}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            summary = prism_stream.sample(str(real_file(name)), str(path), seed=SEED, **options, **extra)
        self[key] = (path, summary)
        return self[key]


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    return Written(tmp_path_factory.mktemp("interop"))


@functools.lru_cache(maxsize=None)
def source_crs(case: str):
    """The input's CRS as the writers take it: WKT first, else the GeoTIFF keys (a WKT pyproj cannot read is
    dropped), None without one."""
    name = CASES[case][0]
    if not name.endswith((".las", ".laz")):
        return None
    with laspy.open(str(real_file(name))) as reader:
        header = reader.header
    for prefer_wkt in (True, False):
        try:
            return header.parse_crs(prefer_wkt=prefer_wkt)
        except Exception:  # noqa: BLE001 - an unreadable record: the other kind, or none
            continue
    return None


def rgb_rows(r, g, b) -> np.ndarray:
    """Colors as sorted rows (a multiset), in 16-bit LAS units."""
    rows = np.stack([np.asarray(c).astype(np.int64) for c in (r, g, b)], axis=1)
    return rows[np.lexsort(rows.T[::-1])]


def color_names(names) -> list[str]:
    """The color columns a Parquet output has: the input's names (a PLY's diffuse_red..., say)."""
    for prefix in ("", "diffuse_"):
        if {f"{prefix}red", f"{prefix}green", f"{prefix}blue"} <= set(names):
            return [f"{prefix}{c}" for c in ("red", "green", "blue")]
    raise AssertionError(f"no color columns in {names}")


def parquet_colors(written, case: str) -> np.ndarray:
    path = written[case, "parquet"][0]
    names = color_names(pq.read_schema(path).names)
    table = pq.read_table(path, columns=names)
    return rgb_rows(*(table.column(c).to_numpy() for c in names))


def las_outputs():
    return [(c, e) for c, e in OUTPUTS if e in ("las", "laz", "copc.laz")]


@pytest.mark.parametrize("case, ext", las_outputs())
def test_laszip_decodes_what_laspy_decodes(written, case, ext):
    """LASzip's own decoder (C++) reads the header and every record as laspy (lazrs) does."""
    path, summary = written[case, ext]
    with open(path, "rb") as f:
        unzipper = laszip.LasUnZipper(f)
        h = unzipper.header
        n = int(h.extended_number_of_point_records or h.number_of_point_records)
        buffer = bytearray(n * h.point_data_record_length)
        unzipper.decompress_into(buffer)
    las = laspy.read(str(path))
    assert n == len(las.points) == summary.kept
    assert h.point_data_format == las.header.point_format.id
    assert bytes(buffer) == las.points.array.tobytes()
    assert np.allclose([h.min_x, h.min_y, h.min_z], las.header.mins) and np.allclose(
        [h.max_x, h.max_y, h.max_z], las.header.maxs)
    for axis, name in enumerate("xyz"):
        values = np.asarray(las[name])
        step = las.header.scales[axis] / 2
        assert las.header.mins[axis] - step <= values.min() and values.max() <= las.header.maxs[axis] + step
    assert h.generating_software.rstrip("\0").startswith("prism-stream")


@pytest.mark.parametrize("case, ext", las_outputs())
def test_las_header_says_what_the_points_are(written, case, ext):
    """Extra-bytes names as the input's records give them, statistics true, the WKT bit for formats 6-10,
    the CRS the input's, colors the same sample as the Parquet output's."""
    path, summary = written[case, ext]
    las = read_las(path)
    h = las.header
    name = CASES[case][0]
    source = laspy.open(str(real_file(name))) if name.endswith((".las", ".laz")) else None
    if source is not None:
        with source:
            named = source.header
            extrabytes.merge_records(named)
            assert list(h.point_format.extra_dimension_names) == list(named.point_format.extra_dimension_names)
    descriptors = extrabytes.descriptors(h)
    assert [d.format_name() for d in descriptors] == list(h.point_format.extra_dimension_names)
    for d in descriptors:
        if not 0 < d.data_type <= 30:
            continue
        assert d.options & extrabytes.MIN_MAX == extrabytes.MIN_MAX, d.format_name()
        values = np.asarray(las.points.array[d.format_name()]).reshape(len(las.points), -1)
        for i in range(d.num_elements()):
            col = values[:, i]
            if d.no_data is not None:
                col = col[col != d.no_data[i]]
            assert (d.min[i], d.max[i]) == pytest.approx((col.min(), col.max())), d.format_name()
    if h.point_format.id >= 6:
        assert h.global_encoding.wkt
    crs = source_crs(case)
    if crs is not None:
        assert h.parse_crs() == crs
    expected = parquet_colors(written, case)
    if not name.endswith((".las", ".laz")) and expected.max() <= 255:  # 8-bit colors into LAS: * 256
        expected = expected * 256
    assert np.array_equal(rgb_rows(las.red, las.green, las.blue), expected)
    assert len(las.points) == summary.kept


@pytest.mark.parametrize("case", [c for c, e in OUTPUTS if e == "copc.laz"])
def test_copc_in_copclib_and_laspy_windows(written, case):
    """copclib opens it (its WKT included) and finds every point; laspy's window query finds exactly the
    points a brute-force scan finds in that window."""
    path, summary = written[case, "copc.laz"]
    las = laspy.read(str(path))
    reader = copclib.FileReader(str(path))
    config = reader.copc_config
    assert config.las_header.point_count == summary.kept
    crs = source_crs(case)
    if crs is not None:
        assert pyproj.CRS.from_wkt(config.wkt) == crs
    assert len(config.extra_bytes_vlr.items) == len(list(las.point_format.extra_dimension_names))
    points = reader.GetAllPoints()
    assert len(points) == summary.kept
    scaled = lambda v, axis: np.round((np.asarray(v) - las.header.offsets[axis]) / las.header.scales[axis])  # noqa: E731
    mine = np.stack([scaled(points.x, 0), scaled(points.y, 1), scaled(points.z, 2)], axis=1)
    theirs = np.stack([np.asarray(las.X), np.asarray(las.Y), np.asarray(las.Z)], axis=1).astype(np.float64)
    assert np.array_equal(mine[np.lexsort(mine.T[::-1])], theirs[np.lexsort(theirs.T[::-1])])
    assert np.array_equal(rgb_rows(points.red, points.green, points.blue), rgb_rows(las.red, las.green, las.blue))

    lo, hi = np.asarray(las.header.mins), np.asarray(las.header.maxs)
    a, b = lo + (hi - lo) * 0.2, lo + (hi - lo) * 0.65
    with laspy.CopcReader.open(str(path)) as copc:
        window = copc.query(laspy.copc.Bounds(mins=a[:2], maxs=b[:2]))
    x, y = np.asarray(las.x), np.asarray(las.y)
    inside = (x >= a[0]) & (x <= b[0]) & (y >= a[1]) & (y <= b[1])
    assert np.count_nonzero(inside) > 0
    got = np.asarray(window.x), np.asarray(window.y)
    got_inside = (got[0] >= a[0]) & (got[0] <= b[0]) & (got[1] >= a[1]) & (got[1] <= b[1])
    # a query returns whole nodes: every point in the window, perhaps some near it
    assert np.count_nonzero(got_inside) == np.count_nonzero(inside)


@pytest.mark.parametrize("case", [c for c, e in OUTPUTS if e == "geo.parquet"])
def test_geoparquet_in_geopandas(written, case):
    path, summary = written[case, "geo.parquet"]
    frame = geopandas.read_parquet(path)
    assert len(frame) == summary.kept
    crs = source_crs(case)
    assert (frame.crs is None) if crs is None else (pyproj.CRS(frame.crs) == crs)
    assert np.array_equal(frame.geometry.x.to_numpy(), frame["x"].to_numpy())
    assert np.array_equal(frame.geometry.y.to_numpy(), frame["y"].to_numpy())
    assert np.array_equal(rgb_rows(*(frame[c] for c in color_names(frame.columns))), parquet_colors(written, case))


@pytest.mark.parametrize("case", [c for c, e in OUTPUTS if e == "ply"])
def test_ply_in_plyfile(written, case):
    """plyfile reads the vertices; no header line ends in whitespace (PCL warns of it)."""
    path, summary = written[case, "ply"]
    ply = plyfile.PlyData.read(str(path))
    vertex = ply["vertex"]
    assert vertex.count == summary.kept
    with open(path, "rb") as f:
        head = f.read(4096).split(b"end_header\n")[0]
    assert all(line == line.rstrip() for line in head.split(b"\n")), head
    expected = parquet_colors(written, case)
    if expected.max() > 255:  # a 16-bit input: PLY holds 8 bits
        expected = rgb_rows(*(expected[:, j] >> 8 for j in range(3)))
    assert np.array_equal(rgb_rows(vertex["red"], vertex["green"], vertex["blue"]), expected)


@pytest.mark.parametrize("case, ext", OUTPUTS)
def test_check_finds_nothing_in_any_output(written, case, ext):
    """`prism-stream check` (the project's validator, for users' files whatever wrote them) passes every output:
    no error and no warning."""
    path, _ = written[case, ext]
    report = validate(path)
    assert (report.errors, report.warnings) == ([], []), path
