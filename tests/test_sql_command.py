"""`prism-stream sql QUERY OUT`: a query's result sampled as the file command samples a file.

The result is one source whose record indices are its row positions, so a
query that returns a file's rows in order gives the file command's output
row for row, with the same JSON summary; a filtered query gives what the
file command gives on the filtered rows written to a file.
"""

from __future__ import annotations

import json
import warnings

import duckdb
import numpy as np
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream.engines.sql import sample_query

import oracle
from conftest import cli, random_colors, real_file, write_parquet

SUMMARY_FIELDS = ("points", "bins", "target", "kept", "rule", "k", "extra", "seed", "options")


@pytest.fixture(scope="module")
def autzen(tmp_path_factory):
    """The Autzen cloud as Parquet, converted by prism-stream (k large keeps every point)."""
    dest = tmp_path_factory.mktemp("sql") / "autzen.parquet"
    prism_stream.sample(str(real_file("pdal__autzen_trim.las")), str(dest), k=10**12)
    return dest


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """A generated cloud with 16-bit colors (v << 8) in several row groups."""
    rgb = random_colors(40000, seed=11, palette=3000, depth=16)
    n = len(rgb)
    dest = tmp_path_factory.mktemp("sql") / "gen.parquet"
    return write_parquet(dest, {"x": np.random.default_rng(1).random(n), "classification": np.arange(n) % 5,
                                "red": rgb[:, 0].astype(np.uint16), "green": rgb[:, 1].astype(np.uint16),
                                "blue": rgb[:, 2].astype(np.uint16)}, row_group_size=7000)


def same_rows(a, b) -> bool:
    a, b = pq.read_table(a), pq.read_table(b)
    return a.num_rows == b.num_rows and a.cast(b.schema).equals(b)


@pytest.mark.parametrize("options", [["--ratio", "0.01"], ["--ratio", "0.25", "--mode", "paper"], ["--k", "2"],
                                     ["--count", "777", "--color-space", "chroma", "--quant-bits", "1", "--seed", "9"]])
def test_sql_equals_the_file_command(capsys, tmp_path, autzen, generated, options):
    for source in (autzen, generated):
        code, out, _ = cli(capsys, "sample", str(source), str(tmp_path / "file.parquet"), *options, "--json",
                           "--overwrite", "--chunk-size", "9000")
        assert code == 0
        by_file = json.loads(out)
        code, out, _ = cli(capsys, "sql", f"SELECT * FROM read_parquet('{source}')", str(tmp_path / "sql.parquet"),
                           *options, "--json", "--overwrite", "--chunk-size", "5000")
        assert code == 0
        by_sql = json.loads(out)
        assert same_rows(tmp_path / "sql.parquet", tmp_path / "file.parquet"), source
        assert {f: by_sql[f] for f in SUMMARY_FIELDS} == {f: by_file[f] for f in SUMMARY_FIELDS}
        assert by_sql["sources"][0]["color_depth"] == by_file["sources"][0]["color_depth"]


def test_filtered_query_equals_the_file_command_on_the_filtered_rows(tmp_path, generated):
    query = f"SELECT * FROM read_parquet('{generated}') WHERE classification <> 3"
    con = duckdb.connect()
    con.execute(f"COPY ({query}) TO '{tmp_path / 'filtered.parquet'}'")
    con.close()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prism_stream.sample(str(tmp_path / "filtered.parquet"), str(tmp_path / "file.parquet"), ratio=0.02)
        for how in ("rerun", "spool"):
            sample_query(query, str(tmp_path / f"{how}.parquet"), ratio=0.02, materialize=how, chunk_size=3000)
            assert same_rows(tmp_path / f"{how}.parquet", tmp_path / "file.parquet"), how


def test_provenance_is_in_the_output(tmp_path, autzen):
    out = tmp_path / "out.parquet"
    sample_query(f"SELECT * FROM '{autzen}'", str(out), ratio=0.01, seed=3)
    con = duckdb.connect()
    raw = con.execute(f"SELECT value FROM parquet_kv_metadata('{out}') WHERE key = 'prism_stream'").fetchone()[0]
    con.close()
    meta = json.loads(raw)
    assert meta["query"] == f"SELECT * FROM '{autzen}'"
    assert (meta["kept"], meta["target"], meta["seed"]) == (1100, 1100, 3)


def test_a_query_whose_order_changes_between_passes_fails_cleanly(capsys, tmp_path, generated):
    out = tmp_path / "out.parquet"
    code, _, err = cli(capsys, "sql", f"SELECT * FROM '{generated}' ORDER BY random()", str(out), "--ratio", "0.1")
    assert code == 6 and "different rows" in err and err.count("\n") == 1
    assert not out.exists() and not list(tmp_path.iterdir())
    # spooled once, the same query is fine
    code, _, _ = cli(capsys, "sql", f"SELECT * FROM '{generated}' ORDER BY random()", str(out), "--ratio", "0.1",
                     "--materialize", "spool", "--quiet")
    assert code == 0 and pq.read_metadata(out).num_rows == 4000


def test_bad_queries_and_outputs_are_one_line_errors(capsys, tmp_path, autzen):
    out = tmp_path / "out.parquet"
    code, _, err = cli(capsys, "sql", "SELECT * FROM no_such_table", str(out), "--ratio", "0.1")
    assert code == 2 and "no_such_table" in err and err.count("\n") == 1
    code, _, err = cli(capsys, "sql", "SELECT 1 AS x", str(out), "--ratio", "0.1")
    assert code == 5 and "no color column" in err
    code, _, err = cli(capsys, "sql", f"SELECT * FROM '{autzen}'", str(out), "--ratio", "1.5")
    assert code == 2
    code, _, err = cli(capsys, "sql", f"SELECT * FROM '{autzen}'", str(tmp_path / "out.las"), "--ratio", "0.1")
    assert code == 4
    out.write_bytes(b"keep me")
    code, _, err = cli(capsys, "sql", f"SELECT * FROM '{autzen}'", str(out), "--ratio", "0.1")
    assert code == 7 and out.read_bytes() == b"keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.parquet"]


def test_a_database_that_is_a_folder_is_said_so(capsys, tmp_path, autzen):
    """--database names the file DuckDB opens read-only: a folder is the option's mistake (2, found by the
    hostile test's '/'), never 'the query failed' (6)."""
    query = f"SELECT * FROM '{autzen}'"
    code, _, err = cli(capsys, "sql", query, str(tmp_path / "o.parquet"), "--ratio", "0.1", "--database", "/")
    assert code == 2 and err.count("\n") == 1 and "/: --database names a folder" in err, err
    assert not (tmp_path / "o.parquet").exists()


@pytest.fixture(scope="module")
def mixed_depths(tmp_path_factory):
    """Two tiles: the larger stores 8-bit color values, the other 16-bit (v << 8)."""
    folder = tmp_path_factory.mktemp("mixed")
    for name, depth, seed, n in (("a.parquet", 8, 1, 20000), ("b.parquet", 16, 2, 10000)):
        rgb = random_colors(n, seed=seed, palette=300, depth=depth)
        write_parquet(folder / name, {"x": np.arange(len(rgb), dtype=np.float64),
                                      "red": rgb[:, 0].astype(np.uint16), "green": rgb[:, 1].astype(np.uint16),
                                      "blue": rgb[:, 2].astype(np.uint16)})
    return folder


@pytest.mark.parametrize("materialize", ["rerun", "spool"])
def test_a_query_naming_its_files_decides_the_color_depth_per_file(tmp_path, mixed_depths, materialize):
    files = [str(mixed_depths / "a.parquet"), str(mixed_depths / "b.parquet")]
    want = prism_stream.plan(files, ratio=0.1)
    query = f"SELECT * FROM read_parquet('{mixed_depths}/*.parquet', filename = true)"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "one bin holds most of the points"
        got = sample_query(query, str(tmp_path / "o.parquet"), ratio=0.1, materialize=materialize)
    assert (got.points, got.bins, got.k, got.extra, got.kept) == (want.points, want.bins, want.k, want.extra,
                                                                  want.kept)
    table = pq.read_table(tmp_path / "o.parquet")
    assert table.num_rows == want.kept
    assert max(table.column("red").to_pylist()) > 255  # the 16-bit tile's values are written as they are


def test_a_query_mixing_depths_without_file_names_is_warned_about(tmp_path, mixed_depths):
    query = f"SELECT * FROM read_parquet('{mixed_depths}/*.parquet')"
    # read as one 16-bit source, every point of the 8-bit tile lands in the black bin: two thirds of the cloud
    with pytest.warns(prism_stream.PrismWarning, match="one bin holds 67% of the points"):
        sample_query(query, str(tmp_path / "o.parquet"), ratio=0.1)


def test_a_query_source_reads_a_record_range(tmp_path):
    """Record ranges (start, stop) skip and stop in the result's stream, across batch boundaries."""
    from prism_stream.formats.query import QuerySource, connect

    n = 50
    path = write_parquet(tmp_path / "t.parquet", {"i": np.arange(n), "red": np.arange(n, dtype=np.uint8),
                                                  "green": np.zeros(n, np.uint8), "blue": np.zeros(n, np.uint8)})
    con = connect()
    try:
        src = QuerySource(con, f"SELECT * FROM read_parquet('{path}') ORDER BY i")
        for start, stop in ((0, None), (7, 23), (10, 20), (3, 4), (45, None)):
            chunks = list(src.point_chunks(10, start, stop))
            got = np.concatenate([c.to_arrow().column("i").to_numpy() for c in chunks])
            assert got.tolist() == list(range(start, n if stop is None else stop)), (start, stop)
            assert [c.start for c in chunks] == sorted(c.start for c in chunks) and chunks[0].start == start
            reds = np.concatenate([c.rgb[0] for c in src.color_chunks(10, start, stop)])
            assert reds.tolist() == got.tolist()
    finally:
        con.close()


def test_a_query_over_8_and_16_bit_files_decides_each_file(tmp_path):
    """With read_parquet's filename column, each file's colors are read by its own depth, as the file command
    does; the result is still one source whose record ids are its row positions."""
    rgb8 = random_colors(3000, seed=4, palette=90)
    rgb16 = random_colors(2000, seed=5, palette=90, depth=16)
    files = []
    for name, rgb, first in (("a", rgb8, 0), ("b", rgb16, 3000)):
        files.append(write_parquet(tmp_path / f"{name}.parquet", {
            "x": np.arange(first, first + len(rgb), dtype=np.float64), "red": rgb[:, 0].astype(np.uint16),
            "green": rgb[:, 1].astype(np.uint16), "blue": rgb[:, 2].astype(np.uint16)}))
    listed = ", ".join(f"'{f}'" for f in files)
    query = f"SELECT x, red, green, blue, filename FROM read_parquet([{listed}], filename = true) ORDER BY x"
    summary = sample_query(query, str(tmp_path / "sql.parquet"), ratio=0.1, seed=6)
    assert oracle.sample([tuple(rgb16[:, j] for j in range(3))], ratio=0.1).depths == ["16"]
    as8 = np.concatenate([rgb8, rgb16 >> 8])  # b.parquet by its own (16-bit) rule, a.parquet as it is
    want = oracle.sample([tuple(as8[:, j] for j in range(3))], ratio=0.1, seed=6)
    assert pq.read_table(tmp_path / "sql.parquet").column("x").to_numpy().tolist() == want.kept[0].tolist()
    assert summary.kept == len(want.kept[0])


@pytest.fixture
def differing_tiles(tmp_path):
    """Two Parquet tiles of one glob: the second lacks the first's `x` (and has a column of its own); both
    have a struct and a list column, so the footers' nested elements are not mistaken for columns."""
    import pyarrow as pa

    rgb = random_colors(600, seed=3, palette=90)
    folder = tmp_path / "tiles"
    folder.mkdir()
    for name, n0, extra in (("a.parquet", 0, "x"), ("b.parquet", 300, "intensity")):
        n = 300
        cols = {"s": pa.array([{"u": i, "v": [i, i]} for i in range(n)]), "l": pa.array([[i] for i in range(n)]),
                "red": rgb[n0:n0 + n, 0], "green": rgb[n0:n0 + n, 1], "blue": rgb[n0:n0 + n, 2],
                extra: np.arange(n, dtype=np.float64)}
        pq.write_table(pa.table(cols), folder / name)
    return folder


@pytest.mark.parametrize("materialize", ["rerun", "spool"])
def test_a_glob_whose_files_lack_a_returned_column_is_refused_before_pass_one(capsys, tmp_path, monkeypatch,
                                                                               differing_tiles, materialize):
    """Issue 28, item 4: DuckDB failed on the file without `x` only in pass two (exit 6, after pass one)."""
    import prism_stream.engines.sql as sql

    def no_pass(*a, **k):
        raise AssertionError("the run started")

    monkeypatch.setattr(sql, "execute", no_pass)
    monkeypatch.setattr(sql, "spool", no_pass)
    out = tmp_path / "out.parquet"
    code, _, err = cli(capsys, "sql", f"SELECT * FROM read_parquet('{differing_tiles}/*.parquet')", str(out),
                       "--ratio", "0.5", "--materialize", materialize)
    assert code == 2, err
    assert err.count("\n") == 1 and "b.parquet has no column 'x'" in err and "a.parquet" in err
    assert "union_by_name = true" in err and not out.exists()


def test_a_glob_is_read_when_its_files_differ_only_where_the_query_does_not_look(capsys, tmp_path,
                                                                                 differing_tiles):
    glob = f"{differing_tiles}/*.parquet"
    for query in (f"SELECT s, l, red, green, blue FROM read_parquet('{glob}')",
                  f"SELECT * FROM read_parquet('{glob}', union_by_name = true)"):
        out = tmp_path / "out.parquet"
        code, _, err = cli(capsys, "sql", query, str(out), "--ratio", "0.5", "--overwrite", "-q")
        assert code == 0, err
        assert pq.read_metadata(out).num_rows == 300


def test_a_mismatch_the_check_cannot_see_is_still_a_usage_error(capsys, tmp_path, differing_tiles):
    """`x` under another name: DuckDB's own failure in pass two, said as the same one line (exit 2, not 6)."""
    code, _, err = cli(capsys, "sql", f"SELECT red, green, blue, x * 2 AS x2 FROM '{differing_tiles}/*.parquet'",
                       str(tmp_path / "out.parquet"), "--ratio", "0.5")
    assert code == 2 and "schema mismatch in glob" in err and "union_by_name = true" in err
    assert not (tmp_path / "out.parquet").exists()


@pytest.mark.parametrize("wrapped", [OSError, "arrow"])
def test_a_failure_raised_by_the_result_stream_is_said_as_duckdbs(capsys, tmp_path, differing_tiles, monkeypatch,
                                                                   wrapped):
    """DuckDB may meet a glob's later file in a worker thread, while the result streams: the Arrow reader then
    raises DuckDB's failure as its own error (an OSError carrying DuckDB's words; 1 run in 30 of the test
    above), not as duckdb.Error. The exit code and the line are the same, never an internal error."""
    import pyarrow as pa

    import prism_stream.formats.query as engine

    real = engine.arrow_reader

    def through_arrow(con, sql, batch_size):
        if "LIMIT 0" in sql:
            return real(con, sql, batch_size)

        def batches():
            try:
                yield from real(con, sql, batch_size)
            except duckdb.Error as exc:
                raise (OSError if wrapped is OSError else pa.ArrowInvalid)(str(exc)) from None
        return batches()

    monkeypatch.setattr(engine, "arrow_reader", through_arrow)
    code, _, err = cli(capsys, "sql", f"SELECT red, green, blue, x * 2 AS x2 FROM '{differing_tiles}/*.parquet'",
                       str(tmp_path / "out.parquet"), "--ratio", "0.5")
    assert code == 2 and err.count("\n") == 1 and "schema mismatch in glob" in err and "union_by_name" in err, err
    assert not (tmp_path / "out.parquet").exists()


def test_a_missing_file_raised_by_the_result_stream_is_exit_3(capsys, tmp_path, monkeypatch):
    """The stream's error carrying DuckDB's words for a file it cannot find: the README's 3, as duckdb.Error."""
    import prism_stream.formats.query as engine

    def missing(con, sql, batch_size):
        if "LIMIT 0" in sql:
            return engine.arrow_reader.__wrapped__(con, sql, batch_size)
        raise OSError('IO Error: No files found that match the pattern "gone/*.parquet"')

    missing.__wrapped__ = engine.arrow_reader
    monkeypatch.setattr(engine, "arrow_reader", missing)
    src = write_parquet(tmp_path / "c.parquet", {"red": np.arange(50, dtype=np.uint8),
                                                 "green": np.arange(50, dtype=np.uint8),
                                                 "blue": np.arange(50, dtype=np.uint8)})
    code, _, err = cli(capsys, "sql", f"SELECT * FROM '{src}'", str(tmp_path / "out.parquet"), "--ratio", "0.5")
    assert code == 3 and err.count("\n") == 1 and "No files found" in err, err


def test_the_top_level_columns_of_nested_footers(differing_tiles):
    from prism_stream.formats.query import _top_level_columns

    rows = duckdb.execute("SELECT file_name, name, num_children FROM parquet_schema(?)",
                          [[str(differing_tiles / "a.parquet"), str(differing_tiles / "b.parquet")]]).fetchall()
    got = {f.rsplit("/", 1)[1]: cols for f, cols in _top_level_columns(rows)}
    assert got == {"a.parquet": ["s", "l", "red", "green", "blue", "x"],
                   "b.parquet": ["s", "l", "red", "green", "blue", "intensity"]}


def test_a_column_the_query_makes_itself_is_not_read_from_the_glob(capsys, tmp_path, differing_tiles):
    """Review: `1 AS x` returns an `x` no file is read for; the run goes ahead as DuckDB runs it."""
    glob = f"{differing_tiles}/*.parquet"
    for query in (f"SELECT red, green, blue, 1 AS x FROM read_parquet('{glob}')",
                  f"SELECT t.red, t.green, t.blue, u.x FROM read_parquet('{glob}') t, "
                  f"(SELECT 1.5 AS x) u"):
        out = tmp_path / "out.parquet"
        code, _, err = cli(capsys, "sql", query, str(out), "--ratio", "0.5", "--overwrite", "-q")
        assert code == 0, (query, err)
    code, _, err = cli(capsys, "sql", f"SELECT t.x, t.red, t.green, t.blue FROM read_parquet('{glob}') t",
                       str(tmp_path / "o2.parquet"), "--ratio", "0.5")
    assert code == 2 and "b.parquet has no column 'x'" in err


def test_an_extension_duckdb_cannot_download_is_the_stores_exit_in_one_whole_line():
    """A remote path in a query needs DuckDB's httpfs extension; offline, DuckDB's generic Error says so on
    several lines, the first cut inside a quote (it was exit 6, 'corrupt', cut off there)."""
    import duckdb

    from prism_stream.errors import StorageError
    from prism_stream.formats.query import duckdb_error

    text = ("An error occurred while trying to automatically install the required extension 'httpfs:\n"
            'Failed to download extension "httpfs" at URL "http://extensions.duckdb.org/v2.0.1/linux_amd64/'
            'httpfs.duckdb_extension.gz"\nExtension "httpfs" is an existing extension.\n\nFor more info, visit '
            "https://duckdb.org/docs (ERROR Could not establish connection)\n\nLINE 1: select 1")
    error = duckdb_error(duckdb.Error(text))
    assert type(error) is StorageError and error.exit_code == 10
    assert "httpfs" in str(error) and "Could not establish connection" in str(error) and "\n" not in str(error)
