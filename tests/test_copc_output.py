"""A ``.copc.laz`` output is a valid COPC file holding exactly the sample (issue 15).

Every output is read by two COPC readers: laspy's ``CopcReader`` (the
hierarchy walked from the root, every node's chunk decompressed; it shares
laspy's header code with the writer) and copclib's ``FileReader``, a C++
implementation that shares nothing with it and is stricter (it checks the
header's size, for one). The
expected points are the input's records at the rows the independent oracle
(tests/oracle.py) keeps; nothing here asks prism_stream what it kept.

The octree's promises, checked on trees forced deep by a small node cap:
every point in exactly one node, inside that node's cube; every node's
parent in the hierarchy; a node that is not split holds at most the cap;
the root holds about the cap, spread over the whole extent (a uniform
thinning: the level of detail a viewer draws first).
"""

from __future__ import annotations

import os
import subprocess
import warnings

import copclib
import laspy
import numpy as np
import pyproj
import pytest

import prism_stream
from prism_stream import PrismWarning
from prism_stream.errors import OutputError
from prism_stream.formats import copc as copc_format
from prism_stream.formats.las import read_provenance

import oracle
from conftest import edge_file, prism_stream_command, read_las, real_file, user_env, write_las

SEED = 3


def run(src, out, **options):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = prism_stream.sample(str(src), str(out), seed=SEED, **options)
    return summary, [str(w.message) for w in caught if issubclass(w.category, PrismWarning)]


def copc_points(path):
    """Every point of the file, found through its hierarchy (laspy's COPC reader); copclib opens it too
    and finds as many points in its nodes."""
    with laspy.CopcReader.open(str(path)) as reader:
        points, header, info = reader.query(), reader.header, reader.copc_info
    other = copclib.FileReader(str(path))
    assert sum(node.point_count for node in other.GetAllNodes()) == len(points)
    assert other.ValidateSpatialBounds()  # every node's points inside the box copclib derives for it
    if len(points):  # a box query over the lower-left quarter finds the points there, no fewer
        lo, hi = np.asarray(header.mins), np.asarray(header.maxs)
        mid = (lo + hi) / 2
        box = copclib.Box(float(lo[0]), float(lo[1]), float(lo[2]), float(mid[0]), float(mid[1]), float(hi[2]))
        x, y = np.asarray(points.x), np.asarray(points.y)
        assert len(other.GetPointsWithinBox(box)) == np.count_nonzero((x <= mid[0]) & (y <= mid[1]))
    return points, header, info


def table(points, names) -> np.ndarray:
    """The points' values of ``names``, one row each, sorted: a multiset to compare."""
    cols = [np.asarray(points[n]).astype(np.float64) for n in names]
    rows = np.stack(cols, axis=1) if cols else np.zeros((len(points), 0))
    return rows[np.lexsort(rows.T[::-1])] if len(rows) else rows


def expected_rows(src, **options):
    """The input's points the oracle keeps."""
    las = read_las(src)
    kept = oracle.sample([(las.red, las.green, las.blue)], seed=SEED, **options).kept[0]
    return las, las.points[kept]


COMPARED = ["X", "Y", "Z", "intensity", "return_number", "number_of_returns", "classification", "user_data",
            "point_source_id", "red", "green", "blue"]


@pytest.mark.parametrize("folder,name,ratio", [("real", "pdal__autzen_trim.las", 0.05),
                                               ("real", "potree__lion_takanawa.copc.laz", 0.1),
                                               ("edge", "loadersgl__pdrf8-1.4.laz", 0.5),
                                               ("real", "pdal__las_with_several_extra_byte_bloc.laz", 0.01)])
def test_copc_holds_exactly_the_sample(tmp_path, folder, name, ratio):
    src = real_file(name) if folder == "real" else edge_file(name)
    out = tmp_path / "sample.copc.laz"
    summary, _ = run(src, out, ratio=ratio)
    las, kept = expected_rows(src, ratio=ratio)
    points, header, info = copc_points(out)
    assert len(points) == header.point_count == summary.kept == len(kept)
    names = [n for n in COMPARED + list(las.point_format.extra_dimension_names)
             if n in set(las.point_format.dimension_names)]
    if "gps_time" in set(las.point_format.dimension_names):
        names.append("gps_time")
    assert np.array_equal(table(points, names), table(kept, names))
    assert header.point_format.id in (6, 7, 8)
    assert list(header.point_format.extra_dimension_names) == list(las.point_format.extra_dimension_names)
    # the second reader, node by node
    reader = copclib.FileReader(str(out))
    assert sum(node.point_count for node in reader.GetAllNodes()) == len(kept)
    # the header's summary is the points'
    xyz = np.stack([np.asarray(points.x), np.asarray(points.y), np.asarray(points.z)], axis=1)
    assert np.allclose(header.mins, xyz.min(axis=0)) and np.allclose(header.maxs, xyz.max(axis=0))
    by_return = np.bincount(np.asarray(points.return_number), minlength=16)[1:16]
    assert list(header.number_of_points_by_return) == list(by_return)


def test_legacy_fields_reach_their_las_14_places(tmp_path):
    """Point format 3 becomes 7: scan angle in 0.006 degree steps, the classification flags kept
    (Autzen's are all 0, so they are set here at random)."""
    las = laspy.read(str(real_file("pdal__autzen_trim.las")))
    rng = np.random.default_rng(4)
    for flag in ("synthetic", "key_point", "withheld"):
        las.points[flag] = rng.integers(0, 2, len(las.points)).astype(np.uint8)
    src = tmp_path / "flags.las"
    las.write(str(src))
    out = tmp_path / "a.copc.laz"
    _, notes = run(src, out, ratio=0.2)
    _, kept = expected_rows(src, ratio=0.2)
    points, header, _ = copc_points(out)
    assert header.point_format.id == 7
    assert any("point format 3 written as 7" in n for n in notes)
    degrees = np.asarray(kept.scan_angle_rank, dtype=np.float64)
    assert np.array_equal(table(points, ["X", "Y", "Z", "scan_angle"])[:, 3],
                          table({"X": kept.X, "Y": kept.Y, "Z": kept.Z, "scan_angle": np.round(degrees / 0.006)},
                                ["X", "Y", "Z", "scan_angle"])[:, 3])
    for flag in ("synthetic", "key_point", "withheld"):
        assert 0 < np.count_nonzero(np.asarray(points[flag])) < len(points)
        assert np.array_equal(table(points, ["X", "Y", "Z", flag]), table(kept, ["X", "Y", "Z", flag]))


def test_waveform_formats_say_what_copc_cannot_hold(tmp_path):
    src = edge_file("loadersgl__pdrf10-1.4.las")
    out = tmp_path / "w.copc.laz"
    _, notes = run(src, out, ratio=0.5)
    points, header, _ = copc_points(out)
    assert header.point_format.id == 8
    note = next(n for n in notes if "point format 10 written as 8" in n)
    assert "wavepacket_index" in note and str(out) in note


def test_waveform_descriptors_go_with_the_waveform(tmp_path):
    src = real_file("laspy__fullwave.laz")  # format 10, a wave packet descriptor VLR (LASF_Spec 100)
    out = tmp_path / "w.copc.laz"
    _, notes = run(src, out, ratio=0.5)
    with laspy.open(out) as r:
        assert not any(v.user_id == "LASF_Spec" and 99 < v.record_id < 355 for v in r.header.vlrs)
    assert any("the waveform packet descriptors go with them" in n for n in notes)


def test_bytes_after_the_header_are_not_carried(tmp_path):
    """A writer's undocumented bytes after the header would move COPC's info VLR off its place (copclib
    refuses such a file): not written, and said."""
    las = laspy.read(str(real_file("pdal__autzen_trim.las")))
    las.header.extra_header_bytes = b"abcd"
    src = tmp_path / "extra.las"
    las.write(str(src))
    with laspy.open(src) as r:
        assert r.header.extra_header_bytes == b"abcd"
    out = tmp_path / "e.copc.laz"
    _, notes = run(src, out, ratio=0.05)
    points, _, _ = copc_points(out)
    assert len(points) == 5_500
    assert any("4 undocumented bytes after the input's header or VLRs not written" in n for n in notes)


def test_a_copc_input_gives_a_copc_output_without_the_plain_laz_note(tmp_path):
    out = tmp_path / "lion.copc.laz"
    _, notes = run(real_file("potree__lion_takanawa.copc.laz"), out, ratio=0.1)
    copc_points(out)
    assert not any("plain LAZ" in n or "COPC VLRs" in n for n in notes), notes


def test_a_crs_in_an_evlr_is_written_once(tmp_path):
    """LAS 1.4 may hold its WKT in an EVLR: one WKT record in the output, no note of a conversion."""
    import pyproj

    src = write_las(tmp_path / "w.las", np.random.default_rng(2).integers(0, 256, (2_000, 3)), point_format=7,
                    version="1.4")
    las = laspy.read(str(src))
    wkt = laspy.vlrs.known.WktCoordinateSystemVlr(pyproj.CRS.from_epsg(2992).to_wkt())
    las.header.vlrs = [v for v in las.header.vlrs if v.user_id != "LASF_Projection"]
    las.evlrs = laspy.vlrs.vlrlist.VLRList([wkt])
    las.header.global_encoding.wkt = True
    las.write(str(src))
    assert laspy.read(str(src)).header.parse_crs() == pyproj.CRS.from_epsg(2992)
    out = tmp_path / "w.copc.laz"
    _, notes = run(src, out, ratio=0.2)
    with laspy.open(out) as r:
        header = r.header
        records = [type(v).__name__ for v in [*header.vlrs, *(header.evlrs or [])] if v.user_id == "LASF_Projection"]
    assert records == ["WktCoordinateSystemVlr"]
    assert header.parse_crs() == pyproj.CRS.from_epsg(2992)
    assert not any("CRS" in n for n in notes), notes


def test_crs_is_kept_as_wkt(tmp_path):
    """Autzen carries its CRS twice (GeoTIFF keys and WKT): one WKT record is written."""
    src = real_file("pdal__autzen_trim.las")
    out = tmp_path / "a.copc.laz"
    _, notes = run(src, out, ratio=0.05)
    with laspy.open(out) as r:
        header = r.header
    assert header.global_encoding.wkt
    assert crs_records(header) == ([], ["WktCoordinateSystemVlr"])
    assert header.parse_crs() == laspy.read(str(src)).header.parse_crs()
    assert not any("CRS" in n for n in notes)
    # copclib reads it (it read a WKT VLR 6 bytes off and refused the file: issue 31)
    reader = copclib.FileReader(str(out))
    assert pyproj.CRS.from_wkt(reader.copc_config.wkt) == header.parse_crs()


def crs_records(header) -> tuple[list, list]:
    """The CRS records' types, among the VLRs and among the EVLRs: COPC's WKT is an EVLR, as copc-lib writes it."""
    return ([type(v).__name__ for v in header.vlrs if v.user_id == "LASF_Projection"],
            [type(v).__name__ for v in header.evlrs or [] if v.user_id == "LASF_Projection"])


def test_geotiff_keys_become_wkt(tmp_path):
    import pyproj

    src = write_las(tmp_path / "keys.las", np.random.default_rng(1).integers(0, 256, (2_000, 3)))
    las = laspy.read(str(src))
    las.header.add_crs(pyproj.CRS.from_epsg(2992))  # LAS 1.2: GeoTIFF keys
    las.write(str(src))
    assert [type(v).__name__ for v in laspy.read(str(src)).header.vlrs][0] == "GeoKeyDirectoryVlr"
    out = tmp_path / "k.copc.laz"
    _, notes = run(src, out, ratio=0.1)
    with laspy.open(out) as r:
        header = r.header
    assert crs_records(header) == ([], ["WktCoordinateSystemVlr"])
    assert header.parse_crs() == pyproj.CRS.from_epsg(2992)
    assert any("CRS stored as WKT, converted from the input's GeoTIFF keys" in n for n in notes)


def test_unreadable_geotiff_keys_are_kept_and_said(tmp_path):
    """Autzen's keys alone do not parse (laspy gives no CRS): they are carried as they are, with a note."""
    las = laspy.read(str(real_file("pdal__autzen_trim.las")))
    las.header.vlrs = [v for v in las.header.vlrs if type(v).__name__ != "WktCoordinateSystemVlr"]
    keys = [bytes(v.record_data_bytes()) for v in las.header.vlrs if v.user_id == "LASF_Projection"]
    src = tmp_path / "keys.las"
    las.write(str(src))
    out = tmp_path / "a.copc.laz"
    _, notes = run(src, out, ratio=0.05)
    with laspy.open(out) as r:
        kept = [bytes(v.record_data_bytes()) for v in r.header.vlrs if v.user_id == "LASF_Projection"]
    assert kept == keys
    assert any("could not be read as a CRS, so they are kept as they are" in n for n in notes)


def test_provenance_and_the_inputs_records(tmp_path):
    src = real_file("pdal__autzen_trim.las")
    out = tmp_path / "a.copc.laz"
    run(src, out, ratio=0.05)
    prov = read_provenance(str(out))
    assert prov["seed"] == SEED and prov["kept"] == laspy.open(out).header.point_count
    with laspy.open(out) as r:
        first = r.header.vlrs[0]
        ids = [(v.user_id, v.record_id) for v in r.header.vlrs]
    assert (first.user_id, first.record_id) == ("copc", 1)  # COPC: the info VLR comes first
    assert ("liblas", 2112) in ids  # the input's own VLRs are carried


def test_same_run_same_bytes(tmp_path, monkeypatch):
    src = real_file("pdal__autzen_trim.las")
    for folder in ("one", "two"):
        (tmp_path / folder).mkdir()
        monkeypatch.chdir(tmp_path / folder)
        run(src, "a.copc.laz", ratio=0.3)
    assert (tmp_path / "one" / "a.copc.laz").read_bytes() == (tmp_path / "two" / "a.copc.laz").read_bytes()


def node_cube(info, key):
    d, x, y, z = key
    side = 2 * info.halfsize / (1 << d)
    low = np.asarray(info.center, dtype=np.float64) - info.halfsize
    lo = low + side * np.array([x, y, z])
    return lo, lo + side


@pytest.mark.parametrize("cap,group,read", [(500, 4_000, 7_001), (3_000, copc_format.GROUP_POINTS, copc_format.READ_POINTS)])
def test_octree_promises(tmp_path, monkeypatch, cap, group, read):
    """``group``, ``read``: points per run of nodes and per chunk read (small: many runs, nodes across chunks)."""
    monkeypatch.setattr(copc_format, "MAX_NODE_POINTS", cap)
    monkeypatch.setattr(copc_format, "GROUP_POINTS", group)
    monkeypatch.setattr(copc_format, "READ_POINTS", read)
    src = real_file("pdal__autzen_trim.las")
    out = tmp_path / "deep.copc.laz"
    run(src, out, ratio=0.5)
    _, header, info = copc_points(out)
    reader = copclib.FileReader(str(out))
    nodes = {(n.key.d, n.key.x, n.key.y, n.key.z): n for n in reader.GetAllNodes()}
    assert (0, 0, 0, 0) in nodes
    assert max(k[0] for k in nodes) >= 2
    fmt = header.point_format
    total = 0
    raws = []
    for key, node in nodes.items():
        d, x, y, z = key
        if d:
            assert (d - 1, x >> 1, y >> 1, z >> 1) in nodes, key
        if node.point_count == 0:
            continue
        raw = np.frombuffer(bytes(reader.GetPointData(node)), dtype=fmt.dtype())
        pts = laspy.ScaleAwarePointRecord(raw.copy(), fmt, header.scales, header.offsets)
        xyz = np.stack([np.asarray(pts.x), np.asarray(pts.y), np.asarray(pts.z)], axis=1)
        lo, hi = node_cube(info, key)
        step = np.asarray(header.scales)
        assert np.all(xyz >= lo - step) and np.all(xyz <= hi + step), key
        children = [(d + 1, 2 * x + i, 2 * y + j, 2 * z + k) for i in (0, 1) for j in (0, 1) for k in (0, 1)]
        if not any(c in nodes for c in children):
            # a node that was never split holds at most the cap (all of its points are fewer); a split node
            # whose threshold reached 1 takes all its ancestors left, n_X (1 - T_parent) <= cap points on
            # average: the draw may pass the cap by a few standard deviations
            assert node.point_count <= cap + 4 * np.sqrt(cap), key
        total += node.point_count
        raws.append(raw)
    assert total == header.point_count
    names = ["X", "Y", "Z", "red", "green", "blue", "gps_time", "intensity"]
    _, kept = expected_rows(src, ratio=0.5)
    assert np.array_equal(table(np.concatenate(raws), names), table(kept, names))  # every sampled point once
    root = nodes[(0, 0, 0, 0)]
    assert 0.8 * cap <= root.point_count <= 1.2 * cap
    raw = np.frombuffer(bytes(reader.GetPointData(root)), dtype=fmt.dtype())
    pts = laspy.ScaleAwarePointRecord(raw.copy(), fmt, header.scales, header.offsets)
    spread = (np.ptp(np.asarray(pts.x)) / (header.maxs[0] - header.mins[0]),
              np.ptp(np.asarray(pts.y)) / (header.maxs[1] - header.mins[1]))
    assert min(spread) > 0.8, spread  # the root is a thinning of the whole cloud, not of one corner


def test_negative_scales(tmp_path):
    """A LAS grid may run backwards (a negative scale): the cube and the header's bounds still hold."""
    las = laspy.read(str(real_file("pdal__autzen_trim.las")))
    x, y, z = np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([-0.01, 0.01, -0.01])
    header.offsets = np.array([637000.0, 849000.0, 400.0])
    out_las = laspy.LasData(header)
    for name, v, axis in (("X", x, 0), ("Y", y, 1), ("Z", z, 2)):  # laspy's x= refuses a negative scale
        out_las[name] = np.round((v - header.offsets[axis]) / header.scales[axis]).astype(np.int32)
    out_las.red, out_las.green, out_las.blue = las.red, las.green, las.blue
    src = tmp_path / "neg.las"
    out_las.write(str(src))
    out = tmp_path / "neg.copc.laz"
    run(src, out, ratio=0.5)
    points, h, _ = copc_points(out)
    xyz = np.stack([np.asarray(points.x), np.asarray(points.y), np.asarray(points.z)], axis=1)
    assert np.allclose(h.mins, xyz.min(axis=0)) and np.allclose(h.maxs, xyz.max(axis=0))
    assert np.all(np.asarray(h.mins) <= np.asarray(h.maxs))


def test_identical_points_are_streamed_in_one_node(tmp_path, monkeypatch):
    """Points no cube can separate (one location) stop the splitting at once and go to one node, written
    chunk by chunk: more points than a run of nodes may hold."""
    monkeypatch.setattr(copc_format, "MAX_NODE_POINTS", 1_000)
    monkeypatch.setattr(copc_format, "GROUP_POINTS", 2_000)
    rgb = np.random.default_rng(5).integers(0, 256, (20_000, 3))
    src = write_las(tmp_path / "same.las", rgb, xyz=np.zeros((20_000, 3)))
    out = tmp_path / "same.copc.laz"
    run(src, out, ratio=0.5)
    points, _, _ = copc_points(out)
    nodes = copclib.FileReader(str(out)).GetAllNodes()
    assert len(points) == 10_000 and len(nodes) == 1 and nodes[0].point_count == 10_000


def test_gps_range_skips_nan(tmp_path):
    las = laspy.read(str(edge_file("loadersgl__pdrf8-1.4.laz")))
    t = np.linspace(1000.0, 2000.0, len(las.points))
    t[::7] = np.nan
    las.gps_time = t
    src = tmp_path / "nan.las"
    las.write(str(src))
    out = tmp_path / "nan.copc.laz"
    run(src, out, ratio=1.0)
    _, _, info = copc_points(out)
    assert (info.gps_min, info.gps_max) == (np.nanmin(t), 2000.0)


@pytest.mark.parametrize("name,fmt", [("gps_time", 2), ("scanner_channel", 3)])
def test_extra_bytes_named_as_a_copc_standard_field_are_refused_first(tmp_path, name, fmt):
    rng = np.random.default_rng(6)
    src = write_las(tmp_path / "clash.las", rng.integers(0, 256, (500, 3)), point_format=fmt,
                    extra={name: rng.random(500)})
    r = subprocess.run([*prism_stream_command(), str(src), str(tmp_path / "c.copc.laz"), "--ratio", "0.5"],
                       capture_output=True, text=True, env=user_env())
    assert r.returncode != 0
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and f"extra-bytes dimension(s) {name} would clash" in lines[0], r.stderr
    assert sorted(os.listdir(tmp_path)) == ["clash.las"]
    r = subprocess.run([*prism_stream_command(), str(src), str(tmp_path / "c.laz"), "--ratio", "0.5"],
                       capture_output=True, text=True, env=user_env())
    assert r.returncode == 0, r.stderr  # the same as plain LAZ is fine


def test_an_extra_nir_stays_an_extra_dimension(tmp_path):
    """Format 3 with an extra-bytes 'nir' becomes format 7 with that extra dimension (not format 8)."""
    rng = np.random.default_rng(7)
    values = rng.integers(0, 1000, 800).astype(np.uint16)
    src = write_las(tmp_path / "nir.las", rng.integers(0, 256, (800, 3)), extra={"nir": values})
    out = tmp_path / "n.copc.laz"
    run(src, out, ratio=1.0)
    points, header, _ = copc_points(out)
    assert header.point_format.id == 7 and list(header.point_format.extra_dimension_names) == ["nir"]
    assert np.array_equal(np.sort(np.asarray(points["nir"])), np.sort(values))


def test_waveform_bits_are_cleared(tmp_path):
    out = tmp_path / "w.copc.laz"
    run(real_file("laspy__fullwave.laz"), out, ratio=0.5)
    with laspy.open(out) as r:
        enc = r.header.global_encoding
        assert not enc.waveform_data_packets_internal and not enc.waveform_data_packets_external


def test_rank_provenance_says_octree_order(tmp_path):
    out = tmp_path / "r.copc.laz"
    prism_stream.rank(str(real_file("pdal__autzen_trim.las")), str(out), ratio=0.1)
    assert read_provenance(str(out))["rank"]["order"] == "octree"


def test_an_empty_sample_is_a_valid_copc(tmp_path):
    src = write_las(tmp_path / "none.las", np.zeros((0, 3), dtype=np.uint16))
    out = tmp_path / "empty.copc.laz"
    run(src, out, ratio=0.5)
    points, header, _ = copc_points(out)
    assert len(points) == header.point_count == 0
    assert sum(n.point_count for n in copclib.FileReader(str(out)).GetAllNodes()) == 0


def test_rank_order_is_refused_before_reading(tmp_path):
    out = tmp_path / "r.copc.laz"
    r = subprocess.run([*prism_stream_command(), "rank", str(real_file("pdal__autzen_trim.las")), str(out),
                        "--order", "rank"], capture_output=True, text=True, env=user_env())
    assert r.returncode == 2, r.stderr
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "COPC orders its points by octree node" in lines[0], r.stderr
    assert not list(tmp_path.iterdir())


def test_ranks_in_copc(tmp_path):
    """Ranks as an extra dimension: rank < T is the sample for T, whatever node a point sits in."""
    src = real_file("pdal__autzen_trim.las")
    out = tmp_path / "r.copc.laz"
    prism_stream.rank(str(src), str(out), seed=SEED)
    points, _, _ = copc_points(out)
    las = laspy.read(str(src))
    ranks = oracle.ranks([(las.red, las.green, las.blue)], seed=SEED)[0]
    expected = table({"X": las.X, "Y": las.Y, "Z": las.Z, "prism_rank": ranks}, ["X", "Y", "Z", "prism_rank"])
    assert np.array_equal(table(points, ["X", "Y", "Z", "prism_rank"]), expected)


def test_a_failed_build_leaves_nothing(tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(copc_format, "build", broken)
    out = tmp_path / "x.copc.laz"
    with pytest.raises(OutputError, match="cannot write the COPC output: No space left on device"):
        prism_stream.sample(str(real_file("pdal__autzen_trim.las")), str(out), ratio=0.05)
    assert not list(tmp_path.iterdir())


def test_a_disk_that_fills_while_lazrs_compresses_is_said_as_such(tmp_path, monkeypatch):
    """The octree's compressed chunks go to the output through lazrs, which reports a refused write only as
    'Failed to call write': the output's file remembers the OSError behind it (it was a guess from the free
    space left, which another process could change in between)."""
    import errno

    from prism_stream.formats import extrabytes

    class Fills:  # the disk fills after 50 kB of the output
        def __init__(self, f):
            self.f, self.n = f, 0

        def write(self, data):
            self.n += len(data)
            if self.n > 50_000:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return self.f.write(data)

        def __getattr__(self, name):
            return getattr(self.f, name)

    real = extrabytes.RecordedFile.__init__
    monkeypatch.setattr(extrabytes.RecordedFile, "__init__",  # the COPC file (r+b), not the staged LAS (wb)
                        lambda self, f: real(self, Fills(f) if "+" in f.mode else f))
    out = tmp_path / "x.copc.laz"
    with pytest.raises(OutputError, match="cannot write the COPC output: No space left on device") as caught:
        prism_stream.sample(str(real_file("pdal__autzen_trim.las")), str(out), ratio=0.5)
    assert str(caught.value).startswith(f"{out}: ") and "Failed to call" not in str(caught.value)
    assert not list(tmp_path.iterdir())


def test_directory_mode_writes_copc_per_file(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for name in ("a", "b"):
        write_las(folder / f"{name}.las", rng.integers(0, 256, (3_000, 3)))
    out = tmp_path / "out"
    r = subprocess.run([*prism_stream_command(), str(folder), str(out) + "/", "--ratio", "0.1", "--format",
                        "COPC.LAZ"], capture_output=True, text=True, env=user_env())  # any case, as output names are matched
    assert r.returncode == 0, r.stderr
    assert sorted(os.listdir(out)) == ["a.copc.laz", "b.copc.laz"]
    assert sum(len(copc_points(out / n)[0]) for n in ("a.copc.laz", "b.copc.laz")) == 600


def test_directory_mode_keeps_copc_inputs_copc(tmp_path):
    """Without --format each output has its input's format: a COPC tile gives a COPC tile."""
    folder = tmp_path / "in"
    folder.mkdir()
    (folder / "lion.copc.laz").write_bytes(real_file("potree__lion_takanawa.copc.laz").read_bytes())
    out = tmp_path / "out"
    r = subprocess.run([*prism_stream_command(), str(folder), str(out) + "/", "--ratio", "0.05"],
                       capture_output=True, text=True, env=user_env())
    assert r.returncode == 0, r.stderr
    assert os.listdir(out) == ["lion.copc.laz"]
    assert len(copc_points(out / "lion.copc.laz")[0]) == round(0.05 * 341_989)


def test_copc_input_to_plain_laz_still_works(tmp_path):
    out = tmp_path / "lion.laz"
    prism_stream.sample(str(real_file("potree__lion_takanawa.copc.laz")), str(out), ratio=0.1)
    with laspy.open(out) as r:
        assert not any(v.user_id == "copc" for v in r.header.vlrs)
