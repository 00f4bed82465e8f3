"""`prism-stream check` (issue 31): every problem in the files prism-stream 5097f86 wrote (tests/data/written/)
is found, each other check is held to a file broken on purpose (a header field patched, a descriptor's
statistics rewritten, GeoParquet metadata changed), and clean files pass."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
import struct

import laspy
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from prism_stream.formats.validate import validate
from prism_stream_cli.main import run

from conftest import DATA, EDGE, REAL, cli

WRITTEN = DATA / "written"


def has(messages: list, *words: str) -> bool:
    """One message holds every word."""
    return any(all(w in m for w in words) for m in messages)


# ---------------------------------------------------------------------------- the files 5097f86 wrote


def test_extra_bytes_stats_and_lost_name(capsys):
    path = WRITTEN / "extra_bytes_stats.laz"
    r = validate(path)
    assert has(r.errors, "'Deviation'", "min = max = 3840", "flagged valid", "values run 768..4096"), r.errors
    assert has(r.errors, "'ExtraBytes'", "min = max = 6", "flagged valid"), r.errors
    assert has(r.warnings, "'ExtraBytes'", "name", "lost"), r.warnings
    code, out, err = cli(capsys, "check", path)
    assert code == 1 and err == ""
    assert f"{path}: error: descriptor 'Deviation': min = max = 3840 flagged valid" in out
    assert all(re.match(rf"{re.escape(str(path))}: (error|warning): ", line) for line in out.splitlines())


def test_the_input_with_two_extra_bytes_records():
    """Where the lost name comes from: the input holds two LASF_Spec/4 VLRs, the second one naming
    'confidence', which laspy and most readers leave unnamed."""
    r = validate(REAL / "pdal__las_with_several_extra_byte_bloc.laz")
    assert has(r.errors, "2 extra-bytes records", "'confidence'", "unnamed"), r.errors
    # its own statistics (min 0, max 65535 flagged valid) hold the data, looser: a warning
    assert has(r.warnings, "'Deviation'", "min 0, max 65535", "looser", "values run 256..4352"), r.warnings
    assert not has(r.errors, "'Deviation'")


def test_copc_stats_min_above_max_and_beyond_2_53():
    r = validate(WRITTEN / "extra_bytes_stats.copc.laz")
    assert r.format == "copc"
    assert has(r.errors, "'Deviation'", "min 18446744073709551615 > max 0", "flagged valid"), r.errors
    assert has(r.errors, "'Deviation'", "beyond +-2^53", "Cannot convert bigint to number"), r.errors
    assert has(r.errors, "'ExtraBytes'", "> max 0"), r.errors


def test_copc_wkt_vlr():
    import copclib

    path = WRITTEN / "wkt_vlr.copc.laz"
    r = validate(path)
    assert has(r.errors, "WKT record as a VLR", "copclib", "EVLR"), r.errors
    # the claim, held to copclib itself: it reads the WKT VLR 6 bytes past its start, into the point data
    with pytest.raises(UnicodeDecodeError):
        copclib.FileReader(str(path)).copc_config.wkt
    assert has(r.warnings, "generating software is 'PDAL 1.0.0")


def test_point_format_7_without_the_wkt_bit():
    r = validate(WRITTEN / "no_wkt_bit.las")
    assert has(r.errors, "point format 7 without the WKT bit"), r.errors


def test_ply_header_padded(capsys):
    path = WRITTEN / "padded_header.ply"
    r = validate(path)
    assert r.errors == []
    assert has(r.warnings, "end in whitespace", "element vertex 20", "trailing whitespaces in the header")
    assert cli(capsys, "check", path)[0] == 0  # a warning: the file reads right
    code, out, _ = cli(capsys, "check", "--strict", path)
    assert code == 1 and f"{path}: warning: " in out


def test_generating_software_copied(capsys):
    path = WRITTEN / "copied_software.laz"
    r = validate(path)
    assert r.errors == []
    assert has(r.warnings, "prism-stream provenance", "generating software is 'PDAL 1.0.0 (9e8465)'")
    assert cli(capsys, "check", path)[0] == 0
    assert cli(capsys, "check", path, "--strict")[0] == 1


def test_invalid_wkt_copied():
    r = validate(WRITTEN / "invalid_wkt.las")
    assert has(r.errors, "WKT record", "does not parse as a CRS", "this is not WKT at all"), r.errors


def test_written_checksums():
    """written/ has its own sha256 block in tests/data/README.md (test_data_files holds the first one to
    real/ and edge/): every file listed, unmodified, and no other."""
    blocks = re.findall(r"^```sha256\n(.*?)^```", (DATA / "README.md").read_text(), re.S | re.M)
    listed = {}
    for block in blocks:
        for line in block.splitlines():
            digest, name = line.split("  ", 1)
            if name.startswith("written/"):
                listed[name] = digest
    assert set(listed) == {f"written/{p.name}" for p in WRITTEN.iterdir()}
    for name, digest in listed.items():
        assert hashlib.sha256((DATA / name).read_bytes()).hexdigest() == digest, name


# ---------------------------------------------------------------------------------------- clean files


@pytest.mark.parametrize("name", ["pdal__autzen_trim.las", "laspy__fullwave.laz", "potree__lion_takanawa.copc.laz",
                                  "odm__option-0000.ply", "open3d__frag_115.ply"])
def test_valid_real_inputs_pass(capsys, name):
    code, out, err = cli(capsys, "check", REAL / name)
    assert (code, out, err) == (0, "", "")


def test_real_inputs_that_are_not_valid():
    """The two other LAS inputs of real/ have problems of their own: the one above (two extra-bytes records),
    and a WKT record holding two quote characters (laspy's parse_crs raises on it)."""
    r = validate(REAL / "pdal__warsaw_small.las")
    assert r.errors == ["WKT record (VLR 1, LASF_Projection/2112) does not parse as a CRS: Invalid WKT string: ''"]


@pytest.fixture(scope="module")
def fresh_parquet(tmp_path_factory):
    """Outputs of the current code in the formats that are already right: Parquet with and without a WKB
    geometry column."""
    folder = tmp_path_factory.mktemp("fresh")
    outs = {}
    for name, extra in (("plain", ()), ("geo", ("--geometry",))):
        out = folder / f"{name}.parquet"
        with pytest.raises(SystemExit) as exc:
            run([str(REAL / "pdal__autzen_trim.las"), str(out), "--count", "200", "-q", *extra])
        assert exc.value.code in (0, None)
        outs[name] = out
    return outs


def test_fresh_parquet_outputs_pass(capsys, fresh_parquet):
    code, out, err = cli(capsys, "check", fresh_parquet["plain"], fresh_parquet["geo"])
    assert (code, out, err) == (0, "", "")
    code, out, _ = cli(capsys, "check", "--json", fresh_parquet["geo"])
    assert code == 0
    assert json.loads(out) == [{"path": str(fresh_parquet["geo"]), "format": "parquet", "errors": [],
                                "warnings": []}]


def test_empty_files_pass():
    assert validate(EDGE / "pdal__no-points.las").errors == []


# ------------------------------------------------------------------------ each LAS check, on purpose


def patch(path, offset: int, fmt: str, *values):
    with open(path, "r+b") as f:
        f.seek(offset)
        f.write(struct.pack(fmt, *values))


def read(path, offset: int, fmt: str):
    with open(path, "rb") as f:
        f.seek(offset)
        return struct.unpack(fmt, f.read(struct.calcsize(fmt)))


def test_header_bounds(tmp_path):
    path = tmp_path / "b.las"
    shutil.copy(REAL / "pdal__autzen_trim.las", path)
    assert validate(path).errors == validate(path).warnings == []
    max_x, min_x = read(path, 179, "<2d")
    patch(path, 179, "<d", max_x - 0.02)  # two steps of 0.01 short of the data
    assert has(validate(path).errors, "header bounds do not hold every point", "x runs")
    patch(path, 179, "<d", max_x - 0.004)  # the data within half a step past the header: rounding
    assert validate(path).errors == []
    patch(path, 179, "<d", max_x + 0.009)  # looser by less than a step: no warning
    assert validate(path).errors == [] and validate(path).warnings == []
    patch(path, 179, "<2d", max_x, min_x - 0.5)  # 50 steps below the data: looser
    r = validate(path)
    assert r.errors == [] and has(r.warnings, "header bounds looser than the data", "x runs")


def test_points_by_return(tmp_path):
    path = tmp_path / "r.las"
    shutil.copy(REAL / "pdal__autzen_trim.las", path)
    first, second = read(path, 111, "<2I")
    patch(path, 111, "<2I", first - 1, second + 1)
    assert has(validate(path).errors, "points by return in the header", "differ from the data")


def test_legacy_point_count(tmp_path):
    path = tmp_path / "c.las"
    shutil.copy(EDGE / "laspy__test1_4.las", path)
    assert not has(validate(path).errors, "legacy")
    count = read(path, 247, "<Q")[0]
    patch(path, 107, "<I", count + 1)
    assert has(validate(path).errors, f"legacy point count {count + 1} differs from the point count {count}")


def test_undescribed_extra_bytes():
    r = validate(EDGE / "laspy__unregistered_extra_bytes.las")
    assert has(r.errors, "extra bytes 0..3", "have no descriptor"), r.errors


def _las_with_extra(path, values: np.ndarray) -> int:
    """A LAS 1.4 format 7 file whose extra-bytes dimension 'v' (uint16) holds ``values``; returns where its
    descriptor starts."""
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.global_encoding.wkt = True
    header.add_extra_dim(laspy.ExtraBytesParams("v", "u2"))
    las = laspy.LasData(header)
    n = len(values)
    las.x = las.y = las.z = np.arange(n, dtype=np.float64)
    las.return_number = las.number_of_returns = np.ones(n, np.uint8)
    las.v = values
    las.write(str(path))
    raw = path.read_bytes()
    return raw.index(b"LASF_Spec") - 2 + 54


def _stats(path, at: int, options: int, no_data: int = 0, lo: int = 0, hi: int = 0) -> None:
    patch(path, at + 3, "<B", options)
    patch(path, at + 40, "<Q", no_data)
    patch(path, at + 64, "<Q", lo)
    patch(path, at + 88, "<Q", hi)


def test_descriptor_statistics(tmp_path):
    path = tmp_path / "s.las"
    at = _las_with_extra(path, np.array([10, 15, 20, 65535, 65535], np.uint16))
    _stats(path, at, 0b111, 65535, 10, 20)  # no_data 65535 left out: exact
    r = validate(path)
    assert r.errors == [] and r.warnings == [], r
    _stats(path, at, 0b110, 0, 10, 20)  # no no_data: 65535 counts
    assert has(validate(path).errors, "descriptor 'v': min 10, max 20 flagged valid", "values run 10..65535")
    _stats(path, at, 0b111, 65535, 10, 15)
    assert has(validate(path).errors, "'v'", "values run 10..20")
    _stats(path, at, 0b111, 65535, 12, 12)
    assert has(validate(path).errors, "'v': min = max = 12 flagged valid")
    _stats(path, at, 0b111, 65535, 5, 30)
    r = validate(path)
    assert r.errors == [] and has(r.warnings, "'v'", "looser than the data")
    _stats(path, at, 0b111, 65535, 30, 5)
    assert has(validate(path).errors, "'v': min 30 > max 5 flagged valid")
    _stats(path, at, 0b110, 0, 2 ** 60, 2 ** 60)
    assert has(validate(path).errors, "'v'", f"min {2 ** 60}, max {2 ** 60} flagged valid is beyond +-2^53")
    _stats(path, at, 0b000, 0, 12, 12)  # not flagged: not checked
    assert validate(path).errors == []


def test_empty_file_statistics_not_checked(tmp_path):
    path = tmp_path / "e.las"
    at = _las_with_extra(path, np.array([], np.uint16))
    _stats(path, at, 0b110, 0, 12, 12)
    assert validate(path).errors == []


def _vlrs(raw: bytes) -> list[tuple[int, int]]:
    header_size, _, nvlr = struct.unpack_from("<HII", raw, 94)
    out, pos = [], header_size
    for _ in range(nvlr):
        length = struct.unpack_from("<H", raw, pos + 20)[0]
        out.append((pos, 54 + length))
        pos += 54 + length
    return out


def test_copc_info_first(tmp_path):
    path = tmp_path / "o.copc.laz"
    raw = (EDGE / "pdal__1.2-with-color.copc.laz").read_bytes()
    (a, la), (b, lb) = _vlrs(raw)[:2]
    path.write_bytes(raw[:a] + raw[b:b + lb] + raw[a:a + la] + raw[b + lb:])  # laszip VLR first, then copc
    assert has(validate(path).errors, "COPC info VLR (copc/1) is VLR 2", "first, at byte 375")
    assert not has(validate(EDGE / "pdal__1.2-with-color.copc.laz").errors, "COPC info")


def test_copc_hierarchy_count(tmp_path):
    path = tmp_path / "h.copc.laz"
    shutil.copy(WRITTEN / "wkt_vlr.copc.laz", path)
    assert not has(validate(path).errors, "hierarchy")
    raw = path.read_bytes()
    root = struct.unpack_from("<Q", raw, 375 + 54 + 40)[0]  # the info VLR's root_hier_offset
    count = read(path, root + 28, "<i")[0]
    patch(path, root + 28, "<i", count + 3)
    assert has(validate(path).errors, f"hierarchy's nodes hold {count + 3} points", "header declares")


def test_copc_without_info(tmp_path):
    path = tmp_path / "plain.copc.laz"
    shutil.copy(WRITTEN / "copied_software.laz", path)
    assert has(validate(path).errors, "no COPC info VLR")


# ------------------------------------------------------------------------------------------------ PLY


def test_ply_counts_against_the_bytes(tmp_path):
    raw = (WRITTEN / "padded_header.ply").read_bytes()
    path = tmp_path / "n.ply"
    path.write_bytes(raw.replace(b"element vertex 20 ", b"element vertex 21 ", 1))
    assert has(validate(path).errors, "element vertex 21", "follow the header")
    path.write_bytes(raw[:-4])
    assert has(validate(path).errors, "element vertex 20", "follow the header")


# -------------------------------------------------------------------------------------------- Parquet


def _regeo(src, dest, change=None, table_change=None):
    table = pq.read_table(src)
    meta = dict(table.schema.metadata)
    geo = json.loads(meta[b"geo"])
    if change:
        geo = change(geo)
    meta[b"geo"] = geo if isinstance(geo, bytes) else json.dumps(geo).encode()
    if table_change:
        table = table_change(table)
    pq.write_table(table.replace_schema_metadata(meta), dest)
    return validate(dest)


def test_geoparquet_checks(tmp_path, fresh_parquet):
    src = fresh_parquet["geo"]
    dest = tmp_path / "g.parquet"
    geo = json.loads(pq.read_schema(src).metadata[b"geo"])
    primary = geo["primary_column"]
    assert _regeo(src, dest).errors == []

    assert has(_regeo(src, dest, lambda g: b"{not json").errors, "'geo' metadata is not JSON")
    assert has(_regeo(src, dest, lambda g: {**g, "primary_column": "nowhere"}).errors,
               "primary column 'nowhere' is not a column")

    def encoding(g):
        g["columns"][primary]["encoding"] = "WKT"
        return g
    assert has(_regeo(src, dest, encoding).errors, "encoding 'WKT', not 'WKB'")

    def crs(g):
        g["columns"][primary]["crs"] = {"type": "GeographicCRS", "name": "nothing"}
        return g
    assert has(_regeo(src, dest, crs).errors, "CRS", "does not parse as PROJJSON")

    x = pq.read_table(src, columns=["x"]).column("x").to_numpy()
    y = pq.read_table(src, columns=["y"]).column("y").to_numpy()

    def bbox(lo_x):
        def change(g):
            g["columns"][primary]["bbox"] = [lo_x, float(y.min()), float(x.max()), float(y.max())]
            return g
        return change
    assert _regeo(src, dest, bbox(float(x.min()))).errors == []
    assert has(_regeo(src, dest, bbox(float(x.min()) + 1)).errors, "bbox", "does not hold the data")

    def moved(table):
        i = table.schema.get_field_index("x")
        return table.set_column(i, "x", pa.array(table.column("x").to_numpy() + 0.5))
    assert has(_regeo(src, dest, table_change=moved).errors, f"WKB points of {primary!r} differ",
               f"at {len(x)} of {len(x)} rows")


# ----------------------------------------------------------------------------------- the command line


def test_missing_and_truncated_files(capsys, tmp_path):
    code, out, err = cli(capsys, "check", tmp_path / "nothere.laz")
    assert code == 3 and out == ""
    assert err.splitlines() == [f"prism-stream: error: {tmp_path / 'nothere.laz'}: no such file"]

    cut = tmp_path / "cut.las"
    cut.write_bytes((WRITTEN / "no_wkt_bit.las").read_bytes()[:3000])
    code, out, err = cli(capsys, "check", cut)
    assert code == 6 and out == ""
    assert len(err.splitlines()) == 1 and err.startswith(f"prism-stream: error: {cut}: ")

    cut = tmp_path / "cut.laz"
    cut.write_bytes((WRITTEN / "copied_software.laz").read_bytes()[:3300])
    code, out, err = cli(capsys, "check", cut)
    assert code == 6 and out == "" and len(err.splitlines()) == 1

    # with other files: those are still checked and reported
    code, out, err = cli(capsys, "check", WRITTEN / "padded_header.ply", tmp_path / "nothere.laz")
    assert code == 3 and "padded_header.ply: warning: " in out and len(err.splitlines()) == 1


def test_json(capsys):
    code, out, err = cli(capsys, "check", "--json", WRITTEN / "no_wkt_bit.las", WRITTEN / "padded_header.ply")
    assert code == 1 and err == ""
    data = json.loads(out)
    assert [d["format"] for d in data] == ["las", "ply"]
    assert set(data[0]) == {"path", "format", "errors", "warnings"}
    assert has(data[0]["errors"], "WKT bit") and data[1]["errors"] == [] and data[1]["warnings"]


def test_help_names_the_checks_and_codes(capsys):
    code, out, _ = cli(capsys, "check", "--help")
    assert code == 0
    for words in ("extra-bytes descriptors", "WKT", "COPC", "PLY", "GeoParquet", "Exit codes", "--strict"):
        assert words in out


@pytest.mark.parametrize("at,value,words", [
    (131, 0.0, ("x scale is 0",)), (139, float("nan"), ("y scale nan",)), (131 + 40, float("inf"), ("z scale",))])
def test_a_header_grid_no_reader_decodes_is_refused(capsys, tmp_path, at, value, words):
    """A scale of 0 (every x the offset) passed `check` and was sampled to x = 0; a NaN scale was an internal
    error in `check` and sampled to NaN. Both are an error of `check` and a one-line refusal of a run, exit 6,
    before pass one."""
    data = bytearray((REAL / "pdal__autzen_trim.las").read_bytes())
    struct.pack_into("<d", data, at, value)
    bad = tmp_path / "bad.las"
    bad.write_bytes(bytes(data))
    code, out, err = cli(capsys, "check", bad)
    assert code == 1 and all(w in out + err for w in words) and "internal error" not in out + err, out + err
    code, _, err = cli(capsys, bad, tmp_path / "o.parquet", "--ratio", "0.1")
    assert code == 6 and all(w in err for w in words) and err.count("\n") == 1, err
    assert not (tmp_path / "o.parquet").exists()


@pytest.mark.parametrize("declared", [64_400, 70_000, 64_300])
def test_a_vertex_count_that_does_not_match_the_data_before_the_faces(capsys, tmp_path, declared):
    """frag_115 is a mesh: 64,365 vertices, then 127,229 faces. A vertex count that is too high read the faces'
    bytes as points (x up to 1.7e38) while `check` said nothing: only the walk of the faces' lists after the
    declared vertices shows the count is wrong. Too low a count leaves vertex bytes where faces are read."""
    data = (REAL / "open3d__frag_115.ply").read_bytes().replace(b"element vertex 64365\n",
                                                                   f"element vertex {declared}\n".encode(), 1)
    bad = tmp_path / "bad.ply"
    bad.write_bytes(data)
    code, out, err = cli(capsys, "check", bad)
    assert code == 1 and "element counts do not match the data" in out, out + err
    code, _, err = cli(capsys, bad, tmp_path / "o.parquet", "--ratio", "0.1")
    assert code == 6 and "vertex count does not match the data" in err and err.count("\n") == 1, err
    assert not (tmp_path / "o.parquet").exists()
    code, out, err = cli(capsys, "check", REAL / "open3d__frag_115.ply")
    assert code == 0 and not out.strip(), out + err


def test_a_parquet_file_whose_pages_do_not_decode_is_exit_6(capsys, tmp_path):
    """check read only a Parquet file's metadata: a garbled data page passed (exit 0) where a run fails half-way
    with exit 6. Every page is decoded now, a batch at a time."""
    src = tmp_path / "ok.parquet"
    n = 20_000
    pq.write_table(pa.table({"x": np.arange(n, dtype="f8"), "red": np.arange(n, dtype="u2") % 256}), src,
                   compression="zstd", row_group_size=5_000)
    raw = bytearray(src.read_bytes())
    raw[len(raw) // 3:len(raw) // 3 + 2_000] = bytes(2_000)  # zeros over a stretch of pages
    bad = tmp_path / "garbled.parquet"
    bad.write_bytes(bytes(raw))
    code, out, err = cli(capsys, "check", src)
    assert code == 0 and not out.strip(), out + err
    code, out, err = cli(capsys, "check", bad)
    assert code == 6 and "garbled.parquet: cannot read the Parquet file" in err and err.count("\n") == 1, out + err


def test_an_ascii_ply_cut_short_is_an_error(capsys, tmp_path):
    """An ASCII PLY holds one record a line: fewer (or more) data lines than its counts say is an error (it passed
    check, and a run refused it)."""
    lines = ["ply", "format ascii 1.0", "element vertex 4", "property float x", "property float y",
             "property float z", "property uchar red", "property uchar green", "property uchar blue", "end_header"]
    rows = [f"{i} {i} {i} 10 20 30" for i in range(4)]
    good, cut = tmp_path / "good.ply", tmp_path / "cut.ply"
    good.write_text("\n".join(lines + rows) + "\n")
    cut.write_text("\n".join(lines + rows[:3]) + "\n")
    assert cli(capsys, "check", good)[0] == 0
    code, out, _ = cli(capsys, "check", cut)
    assert code == 1 and "declares 4 records (vertex 4), the file holds 3 lines of data" in out
