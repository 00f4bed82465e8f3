"""PRISM ranks (`prism-stream rank`): the points of rank < T are exactly the sample for T.

Three independent checks:
- the oracle's ranks, computed from the definition (rank = S(j-1) + the bin's
  place in B_j), against the engine's column, on random clouds;
- on every real cloud and several seeds, the rows of rank < T against a
  separate `--count T` run, row for row, for many T;
- `--order rank` files: their rows are the input-order file's rows sorted by
  rank, in every output format.
"""

from __future__ import annotations

import warnings

import laspy
import numpy as np
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import oracle
from conftest import random_colors, real_file, write_las, write_parquet
from prism_stream import sample
from prism_stream.engines import ranking
from prism_stream.errors import UsageError

RANK = "prism_rank"


def ranked(inputs, out, **opts):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # one-bin and format notes are not what these tests are about
        return sample(inputs, str(out), rank=RANK, **opts)


def rank_column(path) -> np.ndarray:
    path = str(path)
    if path.endswith(".parquet"):
        return pq.read_table(path, columns=[RANK]).column(0).to_numpy()
    if path.endswith((".las", ".laz")):
        return np.asarray(laspy.read(path)[RANK]).astype(np.int64)
    import plyfile

    return np.asarray(plyfile.PlyData.read(path)["vertex"][RANK]).astype(np.int64)


def provenance_of(path) -> dict:
    from prism_stream.formats import las, parquet, ply

    path = str(path)
    module = parquet if path.endswith(".parquet") else ply if path.endswith(".ply") else las
    return module.read_provenance(path)


# -- the oracle: ranks from their definition ----------------------------------------------

@st.composite
def clouds(draw):
    sources = []
    for _ in range(draw(st.integers(1, 3))):
        n = draw(st.integers(1, 300))
        sources.append(random_colors(n, seed=draw(st.integers(0, 2**32 - 1)), palette=draw(st.integers(1, 40)),
                                     depth=draw(st.sampled_from([8, 16]))))
    return sources


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_ranks_are_the_oracles(tmp_path_factory, monkeypatch, data):
    sources = data.draw(clouds())
    n = sum(len(s) for s in sources)
    opts = dict(color_space=data.draw(st.sampled_from(["rgb", "chroma"])),
                quant_bits=data.draw(st.sampled_from([0, 3, 6])), seed=data.draw(st.integers(0, (1 << 64) - 1)),
                chunk_size=data.draw(st.sampled_from([5, 64, 1 << 20])),
                reads=data.draw(st.sampled_from(["auto", "two"])))
    top = data.draw(st.one_of(st.none(), st.integers(1, n)))
    if data.draw(st.booleans()):
        monkeypatch.setattr(ranking, "IN_MEMORY", 0)  # DuckDB's window functions instead of numpy's sorts
    folder = tmp_path_factory.mktemp("r")
    paths = [str(write_las(folder / f"s{i}.las", c, seed=i)) for i, c in enumerate(sources)]
    want = np.concatenate(oracle.ranks([(c[:, 0], c[:, 1], c[:, 2]) for c in sources], color_space=opts["color_space"],
                                       bits=opts["quant_bits"], seed=opts["seed"]))
    assert np.array_equal(np.sort(want), np.arange(n))  # a permutation: one point enters at each T
    out = folder / "out.parquet"
    summary = ranked(paths, out, **opts, **({"count": top} if top else {"ratio": 1.0}))
    expected = want[want < (top or n)]  # input order, the points of rank < T_max
    assert np.array_equal(rank_column(out), expected)
    assert summary.plan["rank"]["method"] == ("duckdb" if ranking.IN_MEMORY == 0 else "numpy")


def test_oracle_ranks_nest_like_the_oracles_samples():
    """The oracle's two definitions agree: rank < T picks the oracle's own exact sample for every T."""
    sources = [tuple(c.T) for c in (random_colors(150, seed=3, palette=12), random_colors(90, seed=4, palette=30))]
    for seed in (0, 11, (1 << 64) - 1):
        r = np.concatenate(oracle.ranks(sources, seed=seed))
        for t in range(1, len(r) + 1):
            want = oracle.sample(sources, count=t, seed=seed)
            got = np.flatnonzero(r < t)
            assert np.array_equal(got, np.concatenate([want.kept[0], want.kept[1] + 150])), (seed, t)


# -- every real cloud: the rows of rank < T are the --count T sample ---------------------------

REAL_CLOUDS = ["pdal__autzen_trim.las", "pdal__warsaw_small.las", "laspy__fullwave.laz", "odm__option-0000.ply",
               "open3d__frag_115.ply", "pcl__office1.pcd", "pdal__las_with_several_extra_byte_bloc.laz"]


# each cloud with one of the two seeds (0, and the largest, whose hash words differ most), by turns
@pytest.mark.parametrize("name,seed", [(name, (0, 2**64 - 1)[i % 2]) for i, name in enumerate(REAL_CLOUDS)])
def test_prefixes_are_count_runs_on_real_clouds(name, seed, real_cloud, tmp_path):
    path = str(real_cloud(name))
    out = tmp_path / "ranked.parquet"
    summary = ranked(path, out, seed=seed, ratio=0.3)
    n, top = summary.points, summary.target
    table = pq.read_table(out)
    r = table.column(RANK).to_numpy()
    assert np.array_equal(np.sort(r), np.arange(top))
    rng = np.random.default_rng(seed % 1000)
    for t in sorted({1, 2, summary.bins - 1, summary.bins, summary.bins + 1, top - 1, top,
                     *rng.integers(1, top, 4).tolist()} - {0}):
        if not 1 <= t <= top:
            continue
        want = tmp_path / f"count{t}.parquet"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sample(path, str(want), count=t, seed=seed, overwrite=True)
        got = table.filter(r < t).drop_columns([RANK])
        assert got.equals(pq.read_table(want)), (name, seed, t, n)


def test_full_ranks_cover_every_point(tmp_path):
    path = str(real_file("pdal__autzen_trim.las"))
    summary = ranked(path, tmp_path / "all.parquet")
    assert summary.target == summary.points == 110_000
    r = rank_column(tmp_path / "all.parquet")
    assert np.array_equal(np.sort(r), np.arange(summary.points))
    # the last rank belongs to a point of the largest bin (its last layer holds one bin)
    assert summary.plan["k"] == int(summary.plan["bin_size"]["max"])


# -- progressive files: --order rank ---------------------------------------------------------

@pytest.mark.parametrize("ext", [".parquet", ".las", ".laz", ".ply"])
def test_rank_order_is_the_input_order_file_sorted(ext, tmp_path, monkeypatch):
    from prism_stream.formats import reorder

    monkeypatch.setattr(reorder, "WINDOW_BYTES", 40_000)  # several windows of ranks, so each is a read
    path = str(real_file("pdal__autzen_trim.las"))
    a, b = tmp_path / f"input{ext}", tmp_path / f"rank{ext}"
    ranked(path, a, ratio=0.1, seed=5)
    ranked(path, b, ratio=0.1, seed=5, order="rank")
    ra, rb = rank_column(a), rank_column(b)
    pa_, pb_ = provenance_of(a), provenance_of(b)
    assert (pa_["rank"]["order"], pb_["rank"]["order"]) == ("input", "rank")
    pb_["rank"]["order"] = "input"
    assert pa_ == pb_  # the same run otherwise
    assert np.array_equal(rb, np.arange(len(ra)))
    order = np.argsort(ra)
    if ext == ".parquet":
        assert pq.read_table(b).equals(pq.read_table(a).take(order))
        ma, mb = pq.read_schema(a).metadata, pq.read_schema(b).metadata
        assert ma.keys() == mb.keys() and all(ma[k] == mb[k] for k in ma if k != b"prism_stream")
    elif ext == ".ply":
        import plyfile

        va, vb = plyfile.PlyData.read(str(a)), plyfile.PlyData.read(str(b))
        from prism_stream.formats.ply import _is_provenance

        own = [[c for c in v.comments if not _is_provenance(c)] for v in (va, vb)]
        assert own[0] == own[1]
        assert np.array_equal(vb["vertex"].data, va["vertex"].data[order])
    else:
        la, lb = laspy.read(str(a)), laspy.read(str(b))
        assert np.array_equal(lb.points.array, la.points.array[order])
        assert [(v.user_id, v.record_id) for v in lb.header.vlrs] == [(v.user_id, v.record_id) for v in la.header.vlrs]
        assert lb.header.parse_crs() == la.header.parse_crs() is not None
        assert lb.header.point_count == la.header.point_count
        assert np.allclose(lb.header.mins, la.header.mins) and np.allclose(lb.header.maxs, la.header.maxs)
        # the extra-bytes statistics (the rank's 0 .. T - 1 among them) survive the rewrite, flagged valid
        records = [bytes(v.record_data_bytes()) for v in lb.header.vlrs.get("ExtraBytesVlr")]
        assert records == [bytes(v.record_data_bytes()) for v in la.header.vlrs.get("ExtraBytesVlr")]
        rank_dim = next(d for d in lb.header.vlrs.get("ExtraBytesVlr")[0].extra_bytes_structs
                        if d.format_name() == "prism_rank")
        assert (rank_dim.min[0], rank_dim.max[0]) == (0, len(ra) - 1)


def test_rank_order_prefix_is_the_count_sample(tmp_path):
    """A progressive file's first T rows are the --count T sample's rows (in rank order instead of input order)."""
    path = str(real_file("pdal__warsaw_small.las"))
    out = tmp_path / "progressive.parquet"
    ranked(path, out, ratio=0.2, seed=3, order="rank")
    table = pq.read_table(out)
    for t in (1, 100, table.num_rows - 1, table.num_rows):
        sample(path, str(tmp_path / "c.parquet"), count=t, seed=3, overwrite=True)
        want = pq.read_table(tmp_path / "c.parquet")
        head = table.slice(0, t)
        # back to input order: the count run's rows, each once
        ids = np.argsort(_positions(head, want))
        assert head.take(ids).drop_columns([RANK]).equals(want)


def _positions(head, want) -> np.ndarray:
    """Where each row of ``head`` is in ``want`` (rows told apart by every column; each must be found once)."""
    index = {row: i for i, row in enumerate(zip(*[c.to_pylist() for c in want.columns]))}
    assert len(index) == want.num_rows
    cols = [head.column(n).to_pylist() for n in want.column_names]
    return np.array([index[row] for row in zip(*cols)])


# -- the same ranks whatever the engine's path ---------------------------------------------

def test_ranks_do_not_depend_on_reads_method_or_chunks(tmp_path, monkeypatch):
    path = str(real_file("pdal__autzen_trim.las"))
    base = tmp_path / "base.parquet"
    ranked(path, base, ratio=0.5, seed=9)
    want = pq.read_table(base)
    variants = [dict(reads="two"), dict(chunk_size=777), dict(threads=1)]
    for i, v in enumerate(variants):
        out = tmp_path / f"v{i}.parquet"
        ranked(path, out, ratio=0.5, seed=9, **v)
        assert pq.read_table(out).equals(want), v
    monkeypatch.setattr(ranking, "IN_MEMORY", 1000)
    out = tmp_path / "duckdb.parquet"
    summary = ranked(path, out, ratio=0.5, seed=9)
    assert summary.plan["rank"]["method"] == "duckdb"
    assert pq.read_table(out).equals(want)


def test_tiles_and_directory_mode_share_one_ranking(tmp_path):
    colors = [random_colors(500, seed=s, palette=25) for s in range(3)]
    tiles = tmp_path / "tiles"
    tiles.mkdir()
    paths = [str(write_las(tiles / f"t{i}.las", c, seed=i)) for i, c in enumerate(colors)]
    one = tmp_path / "one.parquet"
    ranked(paths, one, ratio=0.4, seed=1)
    folder = tmp_path / "out"
    folder.mkdir()
    ranked(str(tiles), str(folder) + "/", ratio=0.4, seed=1, output_format="parquet")
    parts = [rank_column(folder / f"t{i}.parquet") for i in range(3)]
    assert np.array_equal(np.concatenate(parts), rank_column(one))
    want = np.concatenate(oracle.ranks([tuple(c.T) for c in colors], seed=1))
    assert np.array_equal(rank_column(one), want[want < round(0.4 * 1500)])


def test_provenance_says_the_column_and_order(tmp_path):
    from prism_stream.formats.parquet import read_provenance

    out = tmp_path / "r.parquet"
    ranked(str(real_file("pdal__autzen_trim.las")), out, ratio=0.05, order="rank")
    prov = read_provenance(str(out))
    assert prov["rank"] == {"column": RANK, "order": "rank"}
    assert prov["target"] == round(0.05 * 110_000)


# -- refusals --------------------------------------------------------------------------------

@pytest.mark.parametrize("opts", [dict(mode="paper", ratio=0.1), dict(k=3)])
def test_rank_refuses_rules_that_do_not_nest(opts, tmp_path):
    with pytest.raises(UsageError, match="exact mode only"):
        sample(str(real_file("pdal__autzen_trim.las")), str(tmp_path / "r.parquet"), rank=RANK, **opts)
    assert not list(tmp_path.iterdir())


def test_order_rank_needs_ranks(tmp_path):
    with pytest.raises(UsageError, match="needs ranks"):
        sample(str(real_file("pdal__autzen_trim.las")), str(tmp_path / "r.parquet"), ratio=0.1, order="rank")


def test_an_already_ranked_input_is_refused_by_name(tmp_path):
    first = tmp_path / "r.parquet"
    ranked(str(real_file("pdal__autzen_trim.las")), first, ratio=0.1)
    with pytest.raises(UsageError, match="already has a 'prism_rank'"):
        ranked(str(first), tmp_path / "again.parquet", ratio=0.5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.parquet"]
    # the way out the message gives: --drop it (refused for a Parquet input while LAS and PLY took it)
    ranked(str(first), tmp_path / "dropped.parquet", ratio=0.5, drop="prism_rank")
    table = pq.read_table(tmp_path / "dropped.parquet")
    assert table.column_names.count("prism_rank") == 1 and table.num_rows > 0


def test_cli_rank(tmp_path):
    import json
    import subprocess

    from conftest import prism_stream_command

    out = tmp_path / "r.laz"
    run = subprocess.run([*prism_stream_command(), "rank", str(real_file("pdal__autzen_trim.las")), str(out),
                          "--max-count", "5000", "--order", "rank", "--seed", "4", "--json"],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    summary = json.loads(run.stdout)
    assert summary["kept"] == 5000 and summary["plan"]["rank"]["order"] == "rank"
    assert np.array_equal(rank_column(out), np.arange(5000))
    bad = subprocess.run([*prism_stream_command(), "rank", str(real_file("pdal__autzen_trim.las")),
                          str(tmp_path / "x.parquet"), "--max-count", "5", "--max-ratio", "0.1"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "not both" in bad.stderr
    assert not (tmp_path / "x.parquet").exists()


def test_parquet_input_keeps_its_columns_and_gains_the_rank(tmp_path):
    colors = random_colors(2000, seed=8, palette=60)
    src = write_parquet(tmp_path / "in.parquet", {"x": np.arange(2000.0), "y": np.zeros(2000), "z": np.ones(2000),
                                                  "red": colors[:, 0].astype(np.uint8),
                                                  "green": colors[:, 1].astype(np.uint8),
                                                  "blue": colors[:, 2].astype(np.uint8),
                                                  "label": np.arange(2000, dtype=np.int32)},
                        row_group_size=300)
    out = tmp_path / "r.parquet"
    ranked(str(src), out, ratio=1.0, seed=2)
    t = pq.read_table(out)
    assert t.column_names == ["x", "y", "z", "red", "green", "blue", "label", RANK]
    assert np.array_equal(t.column("label").to_numpy(), np.arange(2000))  # every point, input order
    want = oracle.ranks([tuple(colors.T)], seed=2)[0]
    assert np.array_equal(t.column(RANK).to_numpy(), want)



def test_the_readme_sql_one_liner_on_a_ranked_file(tmp_path):
    """README: `SELECT * EXCLUDE (prism_rank) FROM 'ranked.parquet' WHERE prism_rank < floor(0.01 * N + 0.5)`."""
    import duckdb

    path = str(real_file("pdal__autzen_trim.las"))
    summary = ranked(path, tmp_path / "ranked.parquet", seed=12)
    for ratio in (0.01, 0.0123, 0.5):
        got = duckdb.connect().sql(f"SELECT * EXCLUDE (prism_rank) FROM '{tmp_path / 'ranked.parquet'}' "
                                   f"WHERE prism_rank < floor({ratio} * {summary.points} + 0.5)").to_arrow_table()
        sample(path, str(tmp_path / "s.parquet"), ratio=ratio, seed=12, overwrite=True)
        want = pq.read_table(tmp_path / "s.parquet")
        assert got.num_rows == want.num_rows
        assert got.cast(want.schema.remove_metadata()).equals(want.cast(want.schema.remove_metadata())), ratio


def test_a_failure_while_ordering_leaves_nothing(tmp_path, monkeypatch):
    """Disk full in the middle of the rank-order rewrite: no output, no bucket or staging file left."""
    from prism_stream.engines import pipeline
    from prism_stream.errors import OutputError
    from prism_stream.formats import reorder

    real = reorder._Buckets.in_order

    def full(self):
        for i, window in enumerate(real(self)):
            if i == 1:
                raise OSError(28, "No space left on device")
            yield window

    monkeypatch.setattr(reorder, "WINDOW_BYTES", 20_000)
    monkeypatch.setattr(reorder._Buckets, "in_order", full)
    out = tmp_path / "progressive.laz"
    with pytest.raises(OutputError, match="No space left") as info:
        ranked(str(real_file("pdal__autzen_trim.las")), out, ratio=0.2, order="rank")
    assert str(info.value).startswith(f"{out}: ")  # the output the user named, not its staging path
    assert list(tmp_path.iterdir()) == []
    assert pipeline.reorder_by is reorder.reorder_by
