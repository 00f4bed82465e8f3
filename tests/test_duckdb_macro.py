"""PRISM inside DuckDB keeps exactly the rows the streaming engine keeps.

``prism_stream.sql.register(con)`` adds scalar functions (bin key,
priorities, quotas) and the ``prism_sample`` / ``prism_sample_parquet``
table macros; for the same input, options and seed the macro's rows equal
the file command's, row for row and in input order.
"""

from __future__ import annotations

import warnings

import duckdb
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream.sql import functions as prism_duckdb
from prism_stream.core import kernels
from prism_stream.core.quotas import Options, solve
from prism_stream.core.histogram import Histogram

from conftest import random_colors, real_las_files, write_parquet

OPTION_SETS = [
    dict(ratio=0.01),
    dict(ratio=0.2, mode="paper"),
    dict(k=3),
    dict(count=500, color_space="chroma", quant_bits=2, seed=42),
]


@pytest.fixture
def con():
    c = prism_duckdb.register(duckdb.connect())
    yield c
    c.close()


@pytest.fixture(scope="module")
def real_parquet(tmp_path_factory):
    """The real LAS/LAZ clouds converted to Parquet by prism-stream itself (k large keeps every point)."""
    folder = tmp_path_factory.mktemp("real_parquet")
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for las in real_las_files():
            dest = folder / (las.name.split(".")[0] + ".parquet")
            prism_stream.sample(str(las), str(dest), k=10**12)
            out[las.name] = dest
    assert out, "no real LAS/LAZ clouds in tests/data/real"
    return out


def engine_rows(inputs, tmp_path, **options) -> pa.Table:
    out = tmp_path / "engine.parquet"
    if out.exists():
        out.unlink()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prism_stream.sample(inputs, str(out), **options)
    return pq.read_table(out)


def macro_rows(con, call: str, **options) -> pa.Table:
    args = "".join(f", {k} := {v!r}" for k, v in options.items())
    return con.sql(f"SELECT * FROM {call[:-1]}{args})").to_arrow_table()


def same_rows(got: pa.Table, want: pa.Table) -> bool:
    """Equal rows in equal order, over the engine's columns (nullability aside)."""
    return got.num_rows == want.num_rows and got.select(want.column_names).cast(want.schema).equals(want)


def test_scalar_functions_give_the_spec_vectors(con):
    ids = [0, 1, 2, 12345, (1 << 40) | 7]
    rows = con.execute("SELECT prism_priority(i, 0), prism_priority(i, 42) FROM unnest(?::UBIGINT[]) t(i)",
                       [ids]).fetchall()
    assert [r[0] for r in rows] == [0xa706dd2f4d197e6f, 0x08b4fda8c892b50e, 0xd7cc9674ff5ffa39,
                                    0x7a52563b68feef07, 0xb3c704b86519a95d]
    assert [r[1] for r in rows] == [0x57e1faba65107204, 0xf34fe9248c9342e5, 0x725395388690ae46,
                                    0xcbf6b25960247d3b, 0x6fa0caf539d18c87]
    colors = [(0, 0, 0), (255, 255, 255), (10, 20, 30), (200, 100, 50), (1, 0, 0), (128, 128, 127)]
    con.execute("CREATE TABLE c AS SELECT * FROM (VALUES " + ", ".join(f"({i}, {r}, {g}, {b})" for i, (r, g, b)
                                                                        in enumerate(colors)) + ") t(i, r, g, b)")

    def keys(space, bits, shift=0, scale=1):
        return [r[0] for r in con.execute(f"SELECT prism_bin_key(r * {scale}, g * {scale}, b * {scale}, {shift}, "
                                          f"'{space}', {bits}) FROM c ORDER BY i").fetchall()]

    assert keys("rgb", 0) == [0, 16777215, 660510, 13132850, 65536, 8421503]
    assert keys("rgb", 4) == [0, 4095, 17, 3171, 0, 2183]
    assert keys("chroma", 0) == [0, 5592405, 2839936, 9586980, 16711680, 5592405]
    assert keys("chroma", 1) == [0, 693546, 349504, 1200658, 2080768, 693546]
    # 16-bit storage (v * 256 and v * 257) maps back with v >> 8
    assert keys("rgb", 0, shift=8, scale=256) == keys("rgb", 0, shift=8, scale=257) == keys("rgb", 0)


@pytest.mark.parametrize("options", OPTION_SETS, ids=lambda o: "-".join(f"{k}={v}" for k, v in o.items()))
def test_macro_equals_the_engine_on_real_clouds(con, real_parquet, tmp_path, options):
    for name, path in real_parquet.items():
        if options is not OPTION_SETS[0] and name.startswith("pdal__las_with_several"):
            continue  # the 700k-point cloud runs under the first option set only, to keep the suite fast
        want = engine_rows(str(path), tmp_path, **options)
        got = macro_rows(con, f"prism_sample_parquet('{path}')", **options)
        assert same_rows(got, want), name


def test_macro_on_a_view_keeps_read_parquet_ids(con, real_parquet, tmp_path):
    path = real_parquet["pdal__autzen_trim.las"]
    con.execute(f"CREATE VIEW points AS SELECT * FROM read_parquet('{path}', filename = true, file_row_number = true)")
    out = tmp_path / "out.parquet"
    con.execute(f"COPY (SELECT * EXCLUDE (filename, file_row_number) FROM prism_sample('points', ratio := 0.01, "
                f"seed := 0)) TO '{out}'")
    assert same_rows(pq.read_table(out), engine_rows(str(path), tmp_path, ratio=0.01, seed=0))


def test_multi_file_glob_decides_color_depth_per_file(con, tmp_path):
    """Sorted path order gives the file ordinals; 8-bit, 16-bit and late-16-bit files are decided each on its own."""
    folder = tmp_path / "tiles"
    folder.mkdir()
    late = random_colors(5000, seed=3)
    late[4000:] <<= 8  # 8-bit-looking for 4,000 rows, then proven 16-bit
    for name, rgb in (("a.parquet", random_colors(4000, seed=1)), ("b.parquet", random_colors(3000, seed=2, depth=16)),
                      ("c.parquet", late)):
        n = len(rgb)
        write_parquet(folder / name, {"x": np.arange(n, dtype=np.float64), "y": np.zeros(n), "z": np.ones(n),
                                      "red": rgb[:, 0].astype(np.uint16), "green": rgb[:, 1].astype(np.uint16),
                                      "blue": rgb[:, 2].astype(np.uint16)}, row_group_size=1500)
    for options in OPTION_SETS:
        want = engine_rows(str(folder / "*.parquet"), tmp_path, **options)
        got = macro_rows(con, f"prism_sample_parquet('{folder}/*.parquet')", **options)
        assert same_rows(got, want), options


def test_float_colors_and_named_columns(con, tmp_path):
    rng = np.random.default_rng(7)
    n = 6000
    table = {"px": rng.normal(size=n), "R": rng.integers(0, 8, n) / 7.0, "G": rng.integers(0, 8, n) / 7.0,
             "B": rng.random(n)}
    path = write_parquet(tmp_path / "float.parquet", table)
    want = engine_rows(str(path), tmp_path, ratio=0.05, seed=9, rgb_columns=("R", "G", "B"))
    got = macro_rows(con, f"prism_sample_parquet('{path}')", ratio=0.05, seed=9, red="R", green="G", blue="B")
    assert same_rows(got, want)


def test_table_with_an_id_column(con, real_parquet, tmp_path):
    """id := 'col' makes the column the point id; record indices as ids give the single-file engine's rows."""
    path = real_parquet["pdal__autzen_trim.las"]
    con.execute(f"CREATE TABLE t AS SELECT file_row_number AS pid, * EXCLUDE (file_row_number) "
                f"FROM read_parquet('{path}', file_row_number = true) ORDER BY random()")
    got = con.sql("SELECT * EXCLUDE (pid) FROM prism_sample('t', ratio := 0.05, seed := 5, id := 'pid')"
                  ).to_arrow_table()
    assert same_rows(got, engine_rows(str(path), tmp_path, ratio=0.05, seed=5))


def test_prefilter_shortfall_falls_back_exactly(con, real_parquet, tmp_path, monkeypatch):
    """With no slack the threshold prefilter comes up short in many bins; the fallback keeps the result exact."""
    monkeypatch.setattr(prism_duckdb, "SLACK_SIGMAS", 0)
    monkeypatch.setattr(prism_duckdb, "SLACK_POINTS", 0)
    con.execute(prism_duckdb.macro_sql("prism_sample_tight", parquet=True))
    path = real_parquet["pdal__autzen_trim.las"]  # 8-bit values
    table = pq.read_table(path, columns=["red", "green", "blue"])
    for options in (dict(ratio=0.05), dict(k=4, quant_bits=3)):
        assert short_bins(table, **options) > 0  # the fallback path really runs
        want = engine_rows(str(path), tmp_path, **options)
        assert same_rows(macro_rows(con, f"prism_sample_tight('{path}')", **options), want)


def short_bins(table: pa.Table, **options) -> int:
    """Capped bins where fewer than q_b priorities fall under the slack-free threshold q_b / n_b * 2^64."""
    opts = Options(**options)
    rgb = [table.column(c).to_numpy() for c in ("red", "green", "blue")]
    keys = opts.spec.keys(*rgb, 0)
    prio = kernels.priorities(np.uint64(0), len(keys), kernels.seed_mix(opts.seed))
    plan = solve(Histogram.from_keys(keys), opts)
    capped = (plan.quotas > 0) & (plan.quotas < plan.counts)
    t = np.minimum(plan.quotas / plan.counts * 2.0**64, 2.0**64 - 4096).astype(np.uint64)
    bin_of = np.searchsorted(plan.keys, keys)
    below = np.bincount(bin_of, weights=prio <= t[bin_of], minlength=plan.bins)
    return int(np.count_nonzero(capped & (below < plan.quotas)))


def test_bad_options_and_missing_columns_are_errors(con, real_parquet):
    path = real_parquet["pdal__warsaw_small.las"]
    with pytest.raises(duckdb.Error, match="more than the"):
        macro_rows(con, f"prism_sample_parquet('{path}')", count=10**9)
    with pytest.raises(duckdb.Error, match="ratio"):
        macro_rows(con, f"prism_sample_parquet('{path}')", ratio=1.5)
    with pytest.raises(duckdb.Error):
        macro_rows(con, f"prism_sample_parquet('{path}')", ratio=0.1, red="nope")
    con.execute("CREATE TABLE nulls AS SELECT 1 AS pid, NULL::INTEGER AS red, 2 AS green, 3 AS blue")
    with pytest.raises(duckdb.Error, match="no red"):
        con.sql("SELECT * FROM prism_sample('nulls', k := 1, id := 'pid')").fetchall()


# -- prism_rank: every row with its rank; rank < floor(r N + 0.5) is the sample at ratio r ------------

@pytest.mark.parametrize("options", [dict(seed=0), dict(seed=7, color_space="chroma", quant_bits=2)])
def test_rank_macro_equals_the_engines_ranks(con, real_parquet, tmp_path, options):
    for name, path in sorted(real_parquet.items())[:3]:
        want = engine_rows(str(path), tmp_path, rank="prism_rank", **options)
        got = macro_rows(con, f"prism_rank_parquet('{path}')", **options)
        assert same_rows(got, want), name


@pytest.mark.parametrize("ratio", [0.01, 0.137, 0.5])
def test_rank_one_liner_is_the_ratio_sample(con, real_parquet, tmp_path, ratio):
    path = real_parquet["pdal__autzen_trim.las"]
    n = pq.ParquetFile(path).metadata.num_rows
    got = con.sql(f"SELECT * EXCLUDE (prism_rank) FROM prism_rank_parquet('{path}', seed := 3) "
                  f"WHERE prism_rank < floor({ratio} * {n} + 0.5)").to_arrow_table()
    assert same_rows(got, engine_rows(str(path), tmp_path, ratio=ratio, seed=3))


def test_rank_macro_on_a_table_with_an_id_column(con, real_parquet, tmp_path):
    path = real_parquet["pdal__autzen_trim.las"]
    con.execute(f"CREATE TABLE t AS SELECT *, (file_row_number)::UBIGINT AS pid FROM "
                f"read_parquet('{path}', file_row_number = true)")
    got = con.sql("SELECT * EXCLUDE (pid, file_row_number) FROM prism_rank('t', seed := 2, id := 'pid')"
                  ).to_arrow_table()
    assert same_rows(got, engine_rows(str(path), tmp_path, rank="prism_rank", seed=2))
