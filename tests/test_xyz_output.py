"""XYZ text output (formats/xyzout.py): the writer added as one module and one registry line.

It holds the same sample as every other writer (the points of the Parquet output, in the same order),
reads back in numpy's text reader and in prism-stream's own XYZ reader, carries the provenance, and
refuses or says what text cannot hold."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream.errors import PrismError, UsageError
from prism_stream.formats import WRITERS, open_source
from prism_stream.formats.xyzout import PROVENANCE_LINE, XyzSink, read_provenance

from conftest import cli, real_file

AUTZEN = real_file("pdal__autzen_trim.las")  # 8-bit colors in LAS uint16 fields, intensity and more
FULLWAVE = real_file("laspy__fullwave.laz")  # 16-bit colors


def _sample(inputs, out, **options):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = prism_stream.sample([str(i) for i in inputs], str(out), **options)
    return summary, [str(w.message) for w in caught]


def _text(path) -> np.ndarray:
    return np.loadtxt(path, comments="//", ndmin=2)


@pytest.mark.parametrize("cloud", [AUTZEN, FULLWAVE])
def test_the_same_sample_as_the_parquet_output_in_text_readers_read(cloud, tmp_path):
    xyz, said = _sample([cloud], tmp_path / "s.xyz", count=700, seed=4)
    _sample([cloud], tmp_path / "s.parquet", count=700, seed=4)
    table = pq.read_table(tmp_path / "s.parquet")
    values = _text(tmp_path / "s.xyz")
    assert values.shape[0] == xyz.kept == table.num_rows == 700
    header = (tmp_path / "s.xyz").read_text().splitlines()[0]
    names = header[2:].split(" ")
    assert names[:6] == ["X", "Y", "Z", "R", "G", "B"]
    lower = {n.lower(): n for n in table.column_names}
    for j, axis in enumerate("xyz"):  # the shortest text of each double reads back as the same double
        np.testing.assert_array_equal(values[:, j], table.column(lower[axis]).to_numpy())
    depth = xyz.sources[0]["color_depth"]
    for j, channel in enumerate(("red", "green", "blue")):
        want = table.column(channel).to_numpy().astype(np.int64)
        np.testing.assert_array_equal(values[:, 3 + j], want >> 8 if depth == "16" else want)
    for j, name in enumerate(names[6:], start=6):  # every other column, as a number
        np.testing.assert_array_equal(values[:, j], table.column(name).to_numpy().astype(np.float64))
    assert any("written as 8-bit R G B" in s for s in said)


def test_prism_stream_reads_it_back_and_samples_it_again(tmp_path):
    out = tmp_path / "s.xyz"
    _sample([AUTZEN], out, count=900, seed=2)
    src = open_source(str(out), 0)
    try:
        assert src.count == 900
    finally:
        src.close()
    again, _ = _sample([out], tmp_path / "again.parquet", count=100)
    assert again.points == 900 and again.kept == 100


def test_its_columns_keep_their_names_when_read_back(tmp_path):
    """The header line names the columns after the colors: read back, they keep those names (not field_7...),
    so a sample of a sample has the input's columns."""
    out = tmp_path / "s.xyz"
    _sample([AUTZEN], out, count=300, seed=2)
    names = out.read_text().splitlines()[0][2:].split(" ")
    src = open_source(str(out), 0)
    try:
        assert list(src.names) == ["x", "y", "z", "red", "green", "blue", *names[6:]]
        assert "intensity" in src.names
    finally:
        src.close()
    again, _ = _sample([out], tmp_path / "again.parquet", count=100, seed=1)
    table = pq.read_table(tmp_path / "again.parquet")
    assert again.kept == 100 and set(names[6:]) <= set(table.column_names)


@pytest.mark.parametrize("text, extra", [
    ("//X Y Z R G B Intensity\n", ["Intensity"]),  # CloudCompare's ASCII export
    ("# x,y,z,red,green,blue,return\n", ["return"]),
    ("X,Y,Z,R,G,B,Intensity\n", ["Intensity"]),  # a first line of names
    ("// scanned 2024\n//X Y Z R G B Intensity\n", ["Intensity"]),  # the last comment before the points
    ("//X Y Z R G B\n", ["field_7"]),  # names one column short: not a header of these lines
    ("//A B C R G B Intensity\n", ["field_7"]),  # not x y z first
    ("//X Y Z R G B red\n", ["field_7"]),  # a name taken: the generated one
    ("//X Y Z R G B Field_7\n", ["field_7"]),  # a generated name, in any case: generated
    ("", ["field_7"]),
    ("\ufeffX Y Z R G B Intensity\n", ["Intensity"]),  # a byte order mark before the names
    ("X Y Z R G B Intensity\n# exported 2024\n", ["Intensity"]),  # a comment after the names
])
def test_the_header_names_the_further_columns(tmp_path, text, extra):
    path = tmp_path / "in.xyz"
    path.write_text(text + "".join(f"{i} 0 1 {i % 7} {i % 5} {i % 3} {i * 10}\n" for i in range(50)))
    src = open_source(str(path), 0)
    try:
        assert src.count == 50 and list(src.names[6:]) == extra
        values = np.concatenate([c.columns[extra[0]] for c in src.point_chunks(7)])
        np.testing.assert_array_equal(values, np.arange(50) * 10.0)
    finally:
        src.close()


@pytest.mark.parametrize("first", ["Point cloud export\n", "X Y Z R G B\n"])
def test_a_first_line_of_words_that_does_not_name_the_columns_is_refused(tmp_path, first):
    path = tmp_path / "in.xyz"
    path.write_text(first + "".join(f"{i} 0 1 {i % 7} {i % 5} {i % 3} {i * 10}\n" for i in range(5)))
    with pytest.raises(PrismError, match="neither a point nor the names of the 7 columns"):
        open_source(str(path), 0)


def test_a_byte_order_mark_before_a_point(tmp_path):
    path = tmp_path / "in.xyz"
    path.write_bytes(b"\xef\xbb\xbf" + "".join(f"{i} 0 1 {i % 7} {i % 5} {i % 3}\n" for i in range(5)).encode())
    src = open_source(str(path), 0)
    try:
        assert src.count == 5
        np.testing.assert_array_equal(np.concatenate([c.columns["x"] for c in src.point_chunks(2)]), np.arange(5.0))
    finally:
        src.close()


def test_provenance_on_the_second_line(tmp_path):
    out = tmp_path / "s.xyz"
    summary, _ = _sample([AUTZEN], out, ratio=0.01, seed=7)
    lines = out.read_text().splitlines()
    assert lines[1].startswith(PROVENANCE_LINE)
    prov = read_provenance(str(out))
    assert prov["seed"] == 7 and prov["kept"] == summary.kept and prov["software"].startswith("prism-stream")
    assert prov == json.loads(lines[1][len(PROVENANCE_LINE):])


def test_flag_and_rank_columns(tmp_path):
    out = tmp_path / "f.xyz"
    summary, _ = _sample([AUTZEN], out, count=500, flag="kept")
    values = _text(out)
    assert out.read_text().splitlines()[0].split(" ")[-1] == "kept"
    assert values.shape[0] == summary.points and int(values[:, -1].sum()) == 500
    ranked = tmp_path / "r.xyz"
    _sample([AUTZEN], ranked, count=500, rank="prism_rank")
    ranks = _text(ranked)[:, -1]
    assert sorted(ranks.astype(int).tolist()) == list(range(500))


def test_directory_mode_and_the_command_line(tmp_path, capsys):
    code, out, err = cli(capsys, AUTZEN, FULLWAVE, f"{tmp_path}/out/", "--format", "xyz", "--ratio", "0.05")
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["laspy__fullwave.xyz", "pdal__autzen_trim.xyz"]


def test_refusals_before_pass_one(tmp_path, capsys):
    code, _, err = cli(capsys, AUTZEN, tmp_path / "g.xyz", "--geometry", "--ratio", "0.1")
    assert code == 2 and "needs Parquet output" in err and len(err.strip().splitlines()) == 1
    code, _, err = cli(capsys, AUTZEN, tmp_path / "c.xyz", "--scale", "0.01", "--ratio", "0.1")
    assert code == 2 and "grid of LAS, LAZ or COPC output" in err
    with pytest.raises(UsageError, match="already has a column"):
        prism_stream.sample(str(AUTZEN), str(tmp_path / "n.xyz"), count=10, rank="intensity")
    assert not list(tmp_path.glob("*.xyz")) and not list(tmp_path.glob(".*"))


def test_a_failed_write_leaves_nothing(tmp_path, monkeypatch):
    def broken(self, *a, **kw):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(XyzSink, "_text", broken)
    with pytest.raises((PrismError, OSError)):
        prism_stream.sample(str(AUTZEN), str(tmp_path / "x.xyz"), count=10)
    assert list(tmp_path.iterdir()) == []


def test_it_is_one_registry_line():
    assert WRITERS[".xyz"] is XyzSink


# -- prism-stream check reads it ----------------------------------------------------------------------------------

@pytest.mark.parametrize("cloud", [AUTZEN, FULLWAVE])
def test_check_finds_nothing_in_a_fresh_output(cloud, tmp_path, capsys):
    _sample([cloud], tmp_path / "s.xyz", count=700, flag="keep")  # 16-bit FULLWAVE is written as 8-bit
    assert cli(capsys, "check", tmp_path / "s.xyz", "--strict") == (0, "", "")
    assert cli(capsys, "check", tmp_path, "--json")[1].count('"format": "xyz"') == 1  # a folder's .xyz too


def test_check_finds_what_a_text_reader_would_misread(tmp_path, capsys):
    _sample([AUTZEN], tmp_path / "s.xyz", count=50)
    head, provenance, *points = (tmp_path / "s.xyz").read_text().splitlines()
    bad = tmp_path / "names.xyz"
    bad.write_text("\n".join([head.replace(" R G B", " R G"), provenance, *points]) + "\n")
    code, out, err = cli(capsys, "check", bad)
    assert code == 1 and err == "" and len(out.splitlines()) == 1
    assert out.startswith(f"{bad}: error: the header line names 18 columns (X Y Z R G intensity") and "hold 19" in out

    wide = tmp_path / "wide.xyz"  # 16-bit colors, and a provenance line cut short
    rows = [p.split(" ") for p in points]
    wide.write_text("\n".join([head, provenance[:60]] + [" ".join(r[:3] + ["4000"] + r[4:]) for r in rows]) + "\n")
    code, out, _ = cli(capsys, "check", wide)
    assert code == 0
    assert out.splitlines() == [f"{wide}: warning: colors up to 4000: text readers (CloudCompare among them) take "
                                "R G B as 0..255", f"{wide}: warning: prism-stream provenance line is not JSON"]
    assert cli(capsys, "check", wide, "--strict")[0] == 1

    cut = tmp_path / "cut.xyz"  # what the sampler itself refuses: one line on stderr, exit 6
    cut.write_text("\n".join([head, provenance, *points[:3], " ".join(rows[3][:-1])]) + "\n")
    code, out, err = cli(capsys, "check", cut)
    assert (code, out) == (6, "") and err == f"prism-stream: error: {cut}: point 3 has 18 values, the first has 19\n"


def test_a_column_named_like_a_header_word_is_left_out_with_a_note(tmp_path):
    """x, y, z beside an ``X`` (or an ``r`` beside the colors): the header would name X twice and a reader
    take one for the other, so that column is left out and said (a hostile tester's find)."""
    src = tmp_path / "in.parquet"
    n = 50
    pq.write_table(pa.table({"x": np.arange(n, dtype=np.float64), "y": np.zeros(n), "z": np.ones(n),
                             "X": np.full(n, 7.0),
                             "r": np.full(n, 3, np.int32), "intensity": np.arange(n, dtype=np.uint16),
                             "Intensity": np.zeros(n, np.uint8), "a,b": np.ones(n), "": np.ones(n),
                             "red": np.arange(n, dtype=np.uint8), "green": np.zeros(n, np.uint8),
                             "blue": np.zeros(n, np.uint8)}), src)
    out = tmp_path / "o.xyz"
    with pytest.warns(UserWarning) as caught:
        prism_stream.sample(str(src), str(out), ratio=1.0)
    said = " ".join(str(w.message) for w in caught)
    assert "column 'X' dropped: the header line already names a column X" in said
    assert "column 'Intensity' dropped: the header line already names a column intensity" in said
    assert "column 'a,b' dropped: its name would not fit" in said and "column '' dropped" in said
    assert "column 'r' dropped: the header line already names a column R" in said
    assert out.read_text().splitlines()[0] == "//X Y Z R G B intensity"
    src_back = open_source(str(out), 0)
    try:
        assert list(src_back.names) == ["x", "y", "z", "red", "green", "blue", "intensity"]
        xs = np.concatenate([c.to_arrow().column("x").to_numpy() for c in src_back.point_chunks(1 << 20)])
        assert sorted(xs.tolist()) == list(range(n))  # the x column, not X's 7s
    finally:
        src_back.close()
