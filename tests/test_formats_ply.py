"""PLY in and out: the kept vertices are the oracle's, and every property survives bit for bit.

PLY files are read independently with plyfile (generated ones are written
with it too, so the engine's parser never checks itself). The oracle
(tests/oracle.py, SPEC 1-5 in memory) says which vertices a run keeps.
"""

from __future__ import annotations

import json
import warnings

import laspy
import numpy as np
import plyfile
import pyarrow.parquet as pq
import pytest

import prism_stream
import prism_stream.formats
from prism_stream.errors import CorruptInput, UnsupportedFormat
from prism_stream.formats.ply import read_provenance

import oracle
from conftest import real_file, edge_file

RATIO = 0.3


def write_ply(path, vertex: np.ndarray, encoding: str = "binary_little_endian", faces_first: bool = False,
              ragged: bool = True):
    """A PLY with ``vertex`` records and a face element (of varying list lengths if ``ragged``)."""
    n = max(1, len(vertex))
    lengths = (np.arange(5) % 3 + 3) if ragged else np.full(5, 3)
    face = np.empty(5, dtype=[("vertex_indices", object)])
    face["vertex_indices"] = [np.arange(k, dtype=np.int32) % n for k in lengths]
    elements = [plyfile.PlyElement.describe(vertex, "vertex"),
                plyfile.PlyElement.describe(face, "face", len_types={"vertex_indices": "u1"})]
    if faces_first:
        elements.reverse()
    byte_order = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "="}[encoding]
    plyfile.PlyData(elements, text=encoding == "ascii", byte_order=byte_order,
                    comments=["written by the test"]).write(str(path))
    return path


def cloud(n: int, color_type: str = "u1", names=("red", "green", "blue"), seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rec = np.zeros(n, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("nx", "f4"), (names[0], color_type),
                             (names[1], color_type), (names[2], color_type), ("label", "i4"), ("w", "f8")])
    rec["x"] = rng.uniform(-1e3, 1e3, n)
    rec["y"] = rng.uniform(5e5, 5.1e5, n)
    rec["z"] = rng.normal(0, 10, n)
    rec["nx"] = rng.uniform(-1, 1, n)
    palette = rng.integers(0, 256, size=(60, 3))
    pick = palette[rng.integers(0, 60, size=n) % (1 + rng.integers(1, 60, size=n))]
    if color_type == "f4":
        rec[names[0]], rec[names[1]], rec[names[2]] = (pick.T / 255.0).astype(np.float32)
    elif color_type == "u2":
        rec[names[0]], rec[names[1]], rec[names[2]] = pick.T.astype(np.uint16) * 257
    elif color_type == "i1":
        rec[names[0]], rec[names[1]], rec[names[2]] = pick.T.astype(np.uint8).view(np.int8)
    else:
        rec[names[0]], rec[names[1]], rec[names[2]] = pick.T
    rec["label"] = np.arange(n)
    rec["w"] = rng.normal(size=n)
    return rec


def read_vertex(path) -> np.ndarray:
    return plyfile.PlyData.read(str(path))["vertex"].data


def color_names_of(vertex: np.ndarray) -> tuple:
    """The names of the three vertex properties that hold the color."""
    for trio in (("red", "green", "blue"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
        if all(n in vertex.dtype.names for n in trio):
            return trio
    raise AssertionError("no colors")


def colors_of(vertex: np.ndarray):
    chans = [np.asarray(vertex[n]) for n in color_names_of(vertex)]
    # a signed channel holds an unsigned color: two's complement gives it back
    return tuple(c.view(c.dtype.str.replace("i", "u")) if c.dtype.kind == "i" else c for c in chans)


def expected_rows(vertex, **options) -> np.ndarray:
    return oracle.sample([colors_of(vertex)], **options).kept[0]


def same_bits(a, b) -> bool:
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    return a.dtype.itemsize == b.dtype.itemsize and a.shape == b.shape and a.tobytes() == b.tobytes()


def generated(tmp_path, kind: str):
    if kind == "binary_le_faces_first":
        return write_ply(tmp_path / "a.ply", cloud(3000), "binary_little_endian", faces_first=True)
    if kind == "binary_be_faces_first_uniform":
        return write_ply(tmp_path / "b.ply", cloud(3000), "binary_big_endian", faces_first=True, ragged=False)
    if kind == "ascii_faces_first":
        return write_ply(tmp_path / "c.ply", cloud(800), "ascii", faces_first=True)
    if kind == "ushort_colors":
        return write_ply(tmp_path / "d.ply", cloud(2000, "u2"))
    if kind == "float_colors":
        return write_ply(tmp_path / "e.ply", cloud(2000, "f4"))
    if kind == "signed_char_colors":
        return write_ply(tmp_path / "f.ply", cloud(2000, "i1"), "ascii")
    if kind == "diffuse_names":
        return write_ply(tmp_path / "g.ply", cloud(2000, names=("diffuse_red", "diffuse_green", "diffuse_blue")))
    raise KeyError(kind)


GENERATED = ["binary_le_faces_first", "binary_be_faces_first_uniform", "ascii_faces_first", "ushort_colors",
             "float_colors", "signed_char_colors", "diffuse_names"]
SHARED = [("real", "open3d__frag_115.ply"), ("real", "odm__option-0000.ply"),
          ("edge", "draco__test_pos_color_big_endian.ply"), ("edge", "draco__delim_test.ply"),
          ("edge", "pdal__text_extradim.ply")]


def source_path(tmp_path, case):
    if isinstance(case, tuple):
        return real_file(case[1]) if case[0] == "real" else edge_file(case[1])
    return generated(tmp_path, case)


@pytest.mark.parametrize("case", GENERATED + SHARED, ids=str)
def test_ply_to_parquet_keeps_the_oracles_rows_bit_for_bit(tmp_path, case, quiet):
    src = source_path(tmp_path, case)
    vertex = read_vertex(src)
    out = tmp_path / "out.parquet"
    summary = prism_stream.sample(str(src), str(out), ratio=RATIO, seed=3)
    rows = expected_rows(vertex, ratio=RATIO, seed=3)
    table = pq.read_table(out)
    assert summary.points == len(vertex)
    assert table.column_names == list(vertex.dtype.names)
    assert table.num_rows == len(rows)
    colors = set(prism_stream.formats.open_source(str(src), 0).color_fields)
    for name in vertex.dtype.names:
        want = np.asarray(vertex[name])[rows]
        want = want.astype(want.dtype.newbyteorder("="))
        if name in colors and want.dtype.kind == "i":  # a signed color channel: the unsigned value it was binned by
            want = want.view(want.dtype.str.replace("i", "u"))
        got = table.column(name).to_numpy()
        assert got.dtype == want.dtype, name
        assert same_bits(got, want), name


@pytest.mark.parametrize("case", GENERATED + SHARED, ids=str)
def test_ply_to_ply_keeps_every_property(tmp_path, case, quiet):
    src = source_path(tmp_path, case)
    vertex = read_vertex(src)
    out = tmp_path / "out.ply"
    prism_stream.sample(str(src), str(out), ratio=RATIO)
    rows = expected_rows(vertex, ratio=RATIO)
    data = plyfile.PlyData.read(str(out))
    assert data.text is False and data.byte_order == "<"
    got = data["vertex"].data
    assert len(got) == len(rows)
    decision = oracle.color_depth(colors_of(vertex))
    (r, g, b), _ = oracle.to_8bit(colors_of(vertex))
    for name, want in zip(("red", "green", "blue"), (r, g, b)):
        assert got[name].dtype == np.uint8
        assert np.array_equal(got[name], np.asarray(want)[rows]), (name, decision)
    # the color properties come out as uint8 red/green/blue (checked above); every other property is kept
    color_names = set(color_names_of(vertex))
    missing = [n for n in vertex.dtype.names if n not in color_names and n not in got.dtype.names]
    assert not missing, f"input vertex properties missing from the PLY output: {missing}"
    for name in vertex.dtype.names:
        if name in color_names or name in ("red", "green", "blue"):
            continue
        want = np.asarray(vertex[name])[rows]
        assert same_bits(got[name], want.astype(want.dtype.newbyteorder("<"))), name
    provenance = read_provenance(str(out))
    assert provenance["kept"] == len(rows) and provenance["points"] == len(vertex)


def test_ply_to_las_keeps_float32_coordinates_and_colors(tmp_path):
    src = generated(tmp_path, "binary_le_faces_first")
    vertex = read_vertex(src)
    out = tmp_path / "out.las"
    prism_stream.sample(str(src), str(out), ratio=RATIO)
    rows = expected_rows(vertex, ratio=RATIO)
    las = laspy.read(str(out))
    assert las.header.point_format.id == 7
    for i, axis in enumerate("xyz"):
        # the default grid is no coarser than the float32 spacing at the largest magnitude (the input's
        # coarsest step), so every coordinate is within half of that step
        want = vertex[axis][rows]
        got = np.asarray(las[axis])
        scale = las.header.scales[i]
        assert scale <= np.spacing(np.abs(vertex[axis]).max())
        assert np.abs(got - want).max() <= scale / 2 + 4 * np.spacing(np.abs(got).max()), axis
    for c in ("red", "green", "blue"):
        assert np.array_equal(np.asarray(las[c]), vertex[c][rows].astype(np.uint16) << 8)
    for extra in ("nx", "label", "w"):
        assert same_bits(np.asarray(las[extra]), vertex[extra][rows]), extra


def test_parquet_to_las_fits_the_extent_and_keeps_columns(tmp_path):
    import pyarrow as pa

    rng = np.random.default_rng(5)
    n = 5000
    table = pa.table({
        "x": rng.uniform(6.6e5, 6.7e5, n), "y": rng.uniform(5.64e6, 5.65e6, n), "z": rng.uniform(0, 300, n),
        "red": rng.integers(0, 256, n).astype(np.uint8), "green": rng.integers(0, 256, n).astype(np.uint8),
        "blue": rng.integers(0, 4, n).astype(np.uint8), "intensity": rng.integers(0, 65535, n).astype(np.uint16),
        "range_m": rng.normal(size=n).astype(np.float32), "text": np.array(["a"] * n),
    })
    src = tmp_path / "in.parquet"
    pq.write_table(table, src)
    out = tmp_path / "out.laz"
    prism_stream.sample(str(src), str(out), ratio=RATIO)
    rows = oracle.sample([tuple(table.column(c).to_numpy() for c in ("red", "green", "blue"))], ratio=RATIO).kept[0]
    las = laspy.read(str(out))
    for i, axis in enumerate("xyz"):
        want = table.column(axis).to_numpy()[rows]
        assert np.abs(np.asarray(las[axis]) - want).max() <= las.header.scales[i] / 2 + 4 * np.spacing(want.max())
        assert las.header.scales[i] <= (want.max() - want.min()) / 2 ** 20  # a millionth of the extent
    assert np.array_equal(las.intensity, table.column("intensity").to_numpy()[rows])
    assert same_bits(np.asarray(las["range_m"]), table.column("range_m").to_numpy()[rows])
    assert np.array_equal(np.asarray(las.red) >> 8, table.column("red").to_numpy()[rows])


def test_las_to_parquet_to_las_gives_back_the_integers(tmp_path):
    from conftest import random_colors, write_las

    src = write_las(tmp_path / "in.las", random_colors(3000, depth=16), point_format=3)
    mid = tmp_path / "mid.parquet"
    prism_stream.sample(str(src), str(mid), ratio=1.0)
    out = tmp_path / "back.las"
    prism_stream.sample(str(mid), str(out), ratio=1.0)
    a, b = laspy.read(str(src)), laspy.read(str(out))
    assert np.array_equal(a.header.scales, b.header.scales) and np.array_equal(a.header.offsets, b.header.offsets)
    for dim in ("X", "Y", "Z", "red", "green", "blue", "intensity", "gps_time", "classification"):
        assert np.array_equal(np.asarray(a[dim]), np.asarray(b[dim])), dim


def test_chunk_size_does_not_change_an_ascii_ply_sample(tmp_path):
    src = generated(tmp_path, "ascii_faces_first")
    prism_stream.sample(str(src), str(tmp_path / "a.parquet"), ratio=RATIO, chunk_size=7)
    prism_stream.sample(str(src), str(tmp_path / "b.parquet"), ratio=RATIO)
    assert pq.read_table(tmp_path / "a.parquet").equals(pq.read_table(tmp_path / "b.parquet"))


def test_list_property_on_the_vertex_is_refused(tmp_path):
    path = tmp_path / "lists.ply"
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty uchar red\n"
                     b"property uchar green\nproperty uchar blue\nproperty list uchar float extra\nend_header\n"
                     b"1 2 3 4 2 0.5 0.5\n")
    with pytest.raises(UnsupportedFormat, match="list properties"):
        prism_stream.sample(str(path), str(tmp_path / "o.parquet"), ratio=0.5)


@pytest.mark.parametrize("version", [b"\x001.0", b"2.0", b"1"])
def test_a_version_other_than_1_0_is_refused(tmp_path, version):
    """1.0 is PLY's only version; plyfile and RPly refuse any other (a fuzzed NUL before it was read)."""
    path = tmp_path / "v.ply"
    path.write_bytes(b"ply\nformat ascii " + version + b"\nelement vertex 1\nproperty float x\nproperty uchar red\n"
                     b"property uchar green\nproperty uchar blue\nend_header\n1 2 3 4\n")
    with pytest.raises(CorruptInput, match=r"PLY version .* \(1.0 is the only one\)"):
        prism_stream.sample(str(path), str(tmp_path / "o.parquet"), ratio=0.5)
    assert not (tmp_path / "o.parquet").exists()


def test_truncated_binary_ply_is_refused(tmp_path):
    src = generated(tmp_path, "binary_le_faces_first")
    cut = tmp_path / "cut.ply"
    cut.write_bytes(src.read_bytes()[:-100])
    with pytest.raises(CorruptInput, match="declares 3000 vertices"):
        prism_stream.sample(str(cut), str(tmp_path / "o.parquet"), ratio=0.5)
    assert not (tmp_path / "o.parquet").exists()


def test_out_of_range_char_text_is_refused(tmp_path):
    path = tmp_path / "bad.ply"
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty char red\n"
                     b"property uchar green\nproperty uchar blue\nend_header\n1 300 4 5\n")
    with pytest.raises(CorruptInput, match="not a char"):
        prism_stream.sample(str(path), str(tmp_path / "o.parquet"), ratio=0.5)


def test_projected_coordinates_survive_in_ply(tmp_path):
    """LAS -> PLY on the IGN Lambert-93 tile (northings near 6.6e6): x/y/z are PLY doubles, equal to LAS's own."""
    from conftest import real_file

    src = real_file("pdal__las_with_several_extra_byte_bloc.laz")
    out = tmp_path / "out.ply"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prism_stream.sample(str(src), str(out), ratio=0.05, seed=2)
    ref = tmp_path / "ref.parquet"
    prism_stream.sample(str(src), str(ref), ratio=0.05, seed=2)
    want = pq.read_table(ref)
    vertex = plyfile.PlyData.read(str(out))["vertex"]
    for axis in "xyz":
        assert vertex[axis].dtype == np.float64, axis
        assert np.array_equal(vertex[axis], want.column(axis).to_numpy()), axis
    assert want.column("y").to_numpy().min() > 6e6  # the case float32 would collapse (0.5 m steps up there)
    assert len(np.unique(vertex["y"])) == len(np.unique(want.column("y").to_numpy()))


def test_two_ply_inputs_of_one_layout_make_one_ply_and_two_layouts_are_refused(tmp_path, quiet):
    a, b = cloud(300, seed=1), cloud(200, seed=2)
    pa_, pb = write_ply(tmp_path / "a.ply", a), write_ply(tmp_path / "b.ply", b)
    out = tmp_path / "both.ply"
    prism_stream.sample([str(pa_), str(pb)], str(out), ratio=RATIO, seed=4)
    want = oracle.sample([colors_of(a), colors_of(b)], ratio=RATIO, seed=4).kept
    got = read_vertex(out)
    assert np.array_equal(got["label"], np.concatenate([a["label"][want[0]], b["label"][want[1]]]))
    other = write_ply(tmp_path / "c.ply", cloud(100, color_type="u2", seed=3))
    with pytest.raises(UnsupportedFormat, match="differ"):
        prism_stream.sample([str(pa_), str(other)], str(tmp_path / "mixed.ply"), ratio=RATIO)
    assert not (tmp_path / "mixed.ply").exists()


@pytest.mark.parametrize("size", [10, 899, 900, 901, 5_000])
def test_long_provenance_is_split_over_comment_lines_a_reader_takes(size, tmp_path):
    """Open3D's PLY reader (rply) aborts on a header line over 1,023 bytes: the provenance is cut into comment
    lines of at most 900 characters, never next to a space (readers may strip a comment's ends), and read back
    whole; the count's padding stays inside the JSON."""
    from prism_stream.formats import ply

    given = {"command": ["a b " * (size // 8)], "k": "x" * (size // 2), "z": 1}
    text = json.dumps(given, sort_keys=True, separators=(",", ":")).replace(" ", "\\u0020")  # as the writer does
    pieces = ply.provenance_pieces(text)
    assert "".join(pieces) == text and all(0 < len(p) <= ply.PIECE for p in pieces)
    assert all(p == p.strip() for p in pieces)
    assert json.loads(text) == given
    comments = [ply.PROVENANCE_COMMENT + pieces[0], *(ply.CONTINUED + p for p in pieces[1:])]
    assert json.loads(ply.provenance_text(["other", *comments, "more"])) == json.loads(text)


def test_the_writer_splits_its_provenance_and_keeps_the_header_length(tmp_path, monkeypatch):
    """With pieces of 100 characters the writer's provenance takes many comment lines; the header written
    first (count 0) and the one commit() writes over it (the count) have one length, no line ends in a space,
    and the provenance reads back whole."""
    from prism_stream.formats import ply

    monkeypatch.setattr(ply, "PIECE", 100)
    out = tmp_path / "o.ply"
    summary = prism_stream.sample(str(real_file("pdal__warsaw_small.las")), str(out), ratio=0.1, seed=3)
    head = out.read_bytes().split(b"end_header\n")[0].split(b"\n")
    assert sum(line.startswith(b"comment " + ply.CONTINUED.encode()) for line in head) >= 5
    assert all(len(line) <= 100 + 40 and line == line.rstrip() for line in head)
    assert ply.read_provenance(str(out))["seed"] == 3
    assert plyfile.PlyData.read(str(out))["vertex"].count == summary.kept


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_a_signed_color_channel_is_written_as_the_value_it_was_binned_by(tmp_path, encoding):
    """`char blue` -56 is binned as 200 (two's complement, the module's rule); a Parquet output held -56, which
    prism-stream then refused as a negative color, where LAS and PLY outputs wrote 200. Now every output says
    200, and the Parquet output samples again."""
    vertex = np.array([(0.0, 0.0, 0.0, 10, 20, -56), (1.0, 1.0, 1.0, 10, 20, 30), (2.0, 2.0, 2.0, 10, 20, -1)],
                      dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "i1")])
    src = tmp_path / "c.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")], text=encoding == "ascii",
                    byte_order="<" if encoding != "binary_big_endian" else ">").write(str(src))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prism_stream.sample(str(src), str(tmp_path / "o.parquet"), ratio=1.0)
        prism_stream.sample(str(src), str(tmp_path / "o.ply"), ratio=1.0)
        again = prism_stream.sample(str(tmp_path / "o.parquet"), str(tmp_path / "rt.parquet"), ratio=1.0)
    table = pq.read_table(tmp_path / "o.parquet")
    assert str(table.schema.field("blue").type) == "uint8" and table["blue"].to_pylist() == [200, 30, 255]
    assert sorted(plyfile.PlyData.read(str(tmp_path / "o.ply"))["vertex"]["blue"]) == [30, 200, 255]
    assert again.kept == 3
