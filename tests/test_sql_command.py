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
from prism_stream_cli.main import run

from conftest import random_colors, real_file, write_parquet

SUMMARY_FIELDS = ("points", "bins", "target", "kept", "rule", "k", "extra", "seed", "options")


def cli(capsys, *args):
    with pytest.raises(SystemExit) as exc:
        run(list(args))
    out, err = capsys.readouterr()
    return exc.value.code or 0, out, err


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
