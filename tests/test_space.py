"""``--space A`` (SPEC 9): a share of the target placed by an octree's rarest coarse colors, merged with PRISM.

The oracle is ``oracle.space_sample``: every level's cells of every point by ``np.unique``, the merge place
by place, written from SPEC 9's text; the engine tracks one level and merges chunk winners
(``core/space.py``). They must agree row for row, for every way a run reads its input.
"""

from __future__ import annotations

import json

import laspy
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import oracle
from conftest import cli, real_file, write_parquet
from prism_stream import rank, sample
from prism_stream.core import space
from prism_stream.core.kernels import priorities_of_np, seed_mix
from prism_stream.engines import spatial
from prism_stream.errors import CorruptInput
from prism_stream.evaluate import Cloud

AUTZEN = "pdal__autzen_trim.las"


def _engine_order(xyz, rarity, ids, seed, t, chunk):
    prio = priorities_of_np(ids, seed_mix(seed))
    scan = space.SpatialScan(t)
    for a in range(0, len(ids), chunk):
        scan.add(xyz[a:a + chunk], rarity[a:a + chunk], prio[a:a + chunk], ids[a:a + chunk])
    return scan.order(seed)


@st.composite
def clouds(draw):
    n = draw(st.integers(1, 600))
    kind = draw(st.sampled_from(["normal", "utm", "grid", "tiny", "line", "origin"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    if kind == "normal":  # both signs, any scale
        xyz = rng.normal(size=(n, 3)) * 10.0 ** draw(st.integers(-4, 7))
    elif kind == "utm":  # far from 0, on a 1 cm grid
        xyz = np.round(rng.uniform(0, 300, size=(n, 3)), 2) + np.array([500_000.0, 4_000_000.0, 100.0])
    elif kind == "grid":  # few places, many copies (cells that never split)
        xyz = rng.integers(-3, 3, size=(n, 3)).astype(np.float64)
    elif kind == "tiny":  # far below 1, where the cells are past 2^-20
        xyz = rng.uniform(-1e-9, 1e-9, size=(n, 3))
    elif kind == "line":  # on a line: one axis only
        xyz = np.zeros((n, 3))
        xyz[:, 0] = rng.uniform(-5, 5, n)
    else:  # a first run of points at (0, 0, 0) (records of no return), then a small box needing fine cells
        xyz = rng.uniform(0, 10.0 ** draw(st.integers(-2, 2)), size=(n, 3))
        xyz[:draw(st.integers(0, n))] = 0.0
    rarity = rng.integers(1, draw(st.integers(2, 60)), n).astype(np.uint64)
    ids = np.uint64(draw(st.integers(0, 5)) << 40) + np.arange(n, dtype=np.uint64)
    seed = draw(st.integers(0, 2**64 - 1))
    t = draw(st.integers(1, n))
    return xyz, rarity, ids, seed, t


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cloud=clouds(), chunk=st.sampled_from([1, 3, 17, 100, 1 << 20]))
def test_the_spatial_order_is_the_oracles_for_any_chunking(cloud, chunk):
    xyz, rarity, ids, seed, t = cloud
    want = ids[oracle.spatial_order(xyz, rarity, oracle.priority(ids, seed), t, seed)]
    assert np.array_equal(_engine_order(xyz, rarity, ids, seed, t, chunk), want)


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cloud=clouds(), data=st.data())
def test_scans_of_parts_folded_in_any_order_give_the_oracles_order(cloud, data):
    """A cluster's units scan their own points and the driver folds the scans (``SpatialScan.absorb``): any
    cut into parts (empty ones too), any chunking of each, any order and shape of the folds."""
    xyz, rarity, ids, seed, t = cloud
    want = ids[oracle.spatial_order(xyz, rarity, oracle.priority(ids, seed), t, seed)]
    n = len(ids)
    cuts = sorted(data.draw(st.lists(st.integers(0, n), max_size=6)))
    bounds = [0, *cuts, n]
    prio = priorities_of_np(ids, seed_mix(seed))
    scans = []
    for a, b in zip(bounds, bounds[1:]):
        scan = space.SpatialScan(t)
        chunk = data.draw(st.sampled_from([1, 5, 64, 1 << 20]))
        for c in range(a, b, chunk):
            d = min(b, c + chunk)
            scan.add(xyz[c:d], rarity[c:d], prio[c:d], ids[c:d])
        scans.append(scan.settled())
    order = data.draw(st.permutations(range(len(scans))))
    while len(order) > 1:  # pairs folded in a drawn order: a chain, a tree, or anything between
        i = data.draw(st.integers(0, len(order) - 2))
        scans[order[i]].absorb(scans[order[i + 1]])
        folded = scans[order[i]]
        assert folded.state is None or len(folded.state[0]) <= folded.cap  # the memory bound holds past a fold
        order = [*order[:i + 1], *order[i + 2:]]
    assert np.array_equal(scans[order[0]].order(seed), want)


def test_only_scans_of_one_target_fold():
    with pytest.raises(ValueError):
        space.SpatialScan(3).absorb(space.SpatialScan(4))


def test_the_order_lists_one_point_of_each_occupied_cell_level_by_level():
    """SPEC 9's promises, checked without the oracle: after level e the order holds exactly one point of every
    occupied cell of level e, and that point is its cell's smallest (rarity, priority)."""
    rng = np.random.default_rng(5)
    xyz = rng.uniform(0, 64, size=(4000, 3))  # e_top = 6: every index 0 there, some 1 at level 5
    rarity = rng.integers(1, 30, len(xyz)).astype(np.uint64)
    ids = np.arange(len(xyz), dtype=np.uint64)
    prio = oracle.priority(ids, 7)
    order = _engine_order(xyz, rarity, ids, 7, 3000, 1000).astype(np.int64)
    assert len(np.unique(order)) == len(order)
    levels = 0
    for e in range(6, -10, -1):
        cells = np.floor(xyz / 2.0 ** e).astype(np.int64)
        uniq, cell = np.unique(cells, axis=0, return_inverse=True)
        cell = cell.ravel()
        if len(uniq) > len(order):
            assert len(uniq) >= 3000  # the order stopped at the first level with T occupied cells
            break
        listed = order[:len(uniq)]
        assert len(np.unique(cell[listed])) == len(uniq)  # one point of each cell
        best = np.lexsort((prio, rarity, cell))
        winner = best[np.r_[True, cell[best][1:] != cell[best][:-1]]]
        assert set(listed.tolist()) == set(winner.tolist())  # and it is the cell's rarest, then smallest priority
        levels += 1
    assert levels >= 3


def test_the_merge_interleaves_by_share_and_skips_what_the_other_took():
    spatial_ids = np.array([10, 11, 12, 13, 14, 15], np.uint64)
    prism_ids = np.array([11, 20, 21, 22, 23, 24], np.uint64)
    # A = 0.5: share(t) = 0, 1, 1, 2, 2, 3, 3: places 0, 2 and 4 are spatial; 11 is PRISM's before it is spatial's
    got, filled = space.merge(spatial_ids, prism_ids, 500_000, 6)
    assert got.tolist() == [10, 11, 12, 20, 13, 21] and filled == 3
    one, filled_one = space.merge(spatial_ids[:2], prism_ids, 1_000_000, 5)  # the spatial order runs out
    assert one.tolist() == [10, 11, 20, 21, 22] and filled_one == 2
    none, filled_none = space.merge(spatial_ids, prism_ids, 0, 4)
    assert none.tolist() == [11, 20, 21, 22] and filled_none == 0


def test_share_rounds_halves_up_in_integers():
    assert [space.share(500_000, t) for t in range(6)] == [0, 1, 1, 2, 2, 3]
    assert space.share(1_000_000, 7) == 7 and space.share(0, 10**12) == 0
    assert space.share(333_333, 3) == 1 and space.share(1, 499_999) == 0 and space.share(1, 500_000) == 1
    assert space.parse_share("0.25") == 250_000 and space.parse_share("1") == 10**6
    assert space.parse_share(".5") == 500_000
    for bad in ("1.5", "-0.1", "abc", "nan", "1e-1", "0.1234567", "", "inf", "1.0000000", "0.50000000", ".",
                "\u0660.\u0665", "+0.5", "1_0", "0x1"):
        with pytest.raises(ValueError):
            space.parse_share(bad)
        with pytest.raises(oracle.OracleUsageError):
            oracle.space_share(bad)
    for good in ("0", "1", ".5", "1.", " 0.25 ", "0.000001", "1.000000", "0.999999"):
        assert space.parse_share(good) == oracle.space_share(good)


# -- the engine, against the oracle --------------------------------------------------------------------------

def _cloud(path):
    """Coordinates and raw colors of a file, through the readers (the sampling is what is checked)."""
    with Cloud(str(path)) as c:
        xyz, rgb = [], []
        for ch in c.chunks():
            xyz.append(ch.xyz)
            rgb.append([np.asarray(v) for v in ch.raw.rgb])
    return np.concatenate(xyz), tuple(np.concatenate([r[i] for r in rgb]) for i in range(3))


@pytest.fixture(scope="module")
def autzen():
    return _cloud(real_file(AUTZEN))


def _xyz_rows(path) -> np.ndarray:
    t = pq.read_table(path)
    return np.column_stack([t.column(c).to_numpy() for c in ("x", "y", "z")])


@pytest.mark.parametrize("reads,chunk_size,held", [
    ("auto", 1 << 20, True),   # held in memory: no read for the spatial order
    ("auto", 7_000, False),    # streamed: pass one, the spatial read, pass two
    ("two", 1 << 20, False),
])
@pytest.mark.parametrize("share", ["0.5", "1"])
def test_the_run_is_the_oracles_sample(autzen, reads, chunk_size, held, share, monkeypatch, tmp_path):
    xyz, rgb = autzen
    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", "1000000" if held else "0")  # conftest: 0 (streamed)
    out = tmp_path / "out.parquet"
    s = sample(str(real_file(AUTZEN)), str(out), ratio=0.05, space=share, reads=reads, chunk_size=chunk_size)
    kept = oracle.space_sample([rgb], [xyz], space=share, ratio=0.05)[0]
    assert s.kept == len(kept) == 5_500
    assert np.array_equal(_xyz_rows(out), xyz[kept])  # the same points, in input order
    assert s.plan["space"]["share"] == share and s.plan["space"]["spatial_points"] == space.share(
        space.parse_share(share), 5_500)
    assert ("space" in s.seconds) and s.plan["reads"] == (1 if held else 3)
    meta = json.loads(pq.read_schema(out).metadata[b"prism_stream"])
    assert meta["options"]["space"] == share


@pytest.mark.parametrize("name,options", [
    ("open3d__frag_115.ply", dict(ratio=0.1, space="0.8")),
    ("laspy__fullwave.laz", dict(count=700, space="0.25", quant_bits=2, seed=2**64 - 1)),
    ("pcl__office1.pcd", dict(ratio=0.01, space="0.9", color_space="chroma")),
    ("potree__lion_takanawa.copc.laz", dict(count=3000, space="0.6", quant_bits=5, seed=11)),
])
def test_every_format_is_the_oracles_sample(name, options, tmp_path):
    xyz, rgb = _cloud(real_file(name))
    out = tmp_path / "out.parquet"
    s = sample(str(real_file(name)), str(out), chunk_size=20_000, **options)
    kept = oracle.space_sample([rgb], [xyz], bits=options.pop("quant_bits", 0), **options)[0]
    assert s.kept == len(kept)
    assert np.array_equal(_xyz_rows(out), xyz[kept])


def test_two_files_are_one_cloud_and_las_records_are_kept_whole(autzen, tmp_path):
    las = laspy.read(str(real_file(AUTZEN)))
    a, b = tmp_path / "a.las", tmp_path / "b.las"
    for path, part in ((a, slice(0, 40_000)), (b, slice(40_000, None))):
        piece = laspy.LasData(las.header)
        piece.points = las.points[part]
        piece.write(str(path))
    out = tmp_path / "out.las"
    sample([str(a), str(b)], str(out), count=2_000, space="0.7", seed=3, chunk_size=9_000)
    xyz, rgb = autzen
    ka, kb = oracle.space_sample([tuple(c[:40_000] for c in rgb), tuple(c[40_000:] for c in rgb)],
                                 [xyz[:40_000], xyz[40_000:]], space="0.7", count=2_000, seed=3)
    want = np.concatenate([ka, 40_000 + kb])
    got = laspy.read(str(out))
    assert np.array_equal(np.asarray(got.points.array), np.asarray(las.points.array[want]))


def test_space_zero_is_prism_and_samples_nest(tmp_path):
    src = str(real_file(AUTZEN))
    plain, zero = tmp_path / "p.parquet", tmp_path / "z.parquet"
    sample(src, str(plain), ratio=0.02)
    s = sample(src, str(zero), ratio=0.02, space="0.000")
    assert pq.read_table(plain).equals(pq.read_table(zero)) and "space" not in s.options
    assert pq.read_schema(plain).metadata == pq.read_schema(zero).metadata
    rows = []
    for t in (1, 2, 3, 50, 51, 400, 1_000):
        out = tmp_path / f"n{t}.parquet"
        sample(src, str(out), count=t, space="0.4")
        rows.append({tuple(r) for r in _xyz_rows(out)})
    assert all(len(r) == t for r, t in zip(rows, (1, 2, 3, 50, 51, 400, 1_000)))
    assert all(a <= b for a, b in zip(rows, rows[1:]))  # the sample for T is in the sample for every larger T


def test_rank_with_a_share_gives_the_merge_places(autzen, tmp_path):
    out = tmp_path / "ranked.parquet"
    rank(str(real_file(AUTZEN)), str(out), ratio=0.02, space="0.5")
    t = pq.read_table(out)
    ranks = t.column("prism_rank").to_numpy()
    assert sorted(ranks.tolist()) == list(range(2_200))
    xyz, rgb = autzen
    rows = np.column_stack([t.column(c).to_numpy() for c in ("x", "y", "z")])
    for t_small in (1, 37, 1_100):
        kept = oracle.space_sample([rgb], [xyz], space="0.5", count=t_small)[0]
        assert {tuple(r) for r in rows[ranks < t_small]} == {tuple(r) for r in xyz[kept]}


# -- refusals ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("args,words", [
    (["--k", "3", "--space", "0.5"], "--space needs a target"),
    (["--ratio", "0.1", "--mode", "paper", "--space", "0.5"], "--space needs a target"),
    (["--ratio", "0.1", "--quant-step", "2", "--space", "0.5"], "--quant-step"),
    (["--ratio", "0.1", "--space", "1.5"], "at most 1"),
    (["--ratio", "0.1", "--space", "half"], "from 0 to 1"),
    (["--ratio", "0.1", "--space", "0.1234567"], "six digits"),
])
def test_bad_options_are_one_line_before_any_read(capsys, tmp_path, args, words):
    out = tmp_path / "out.parquet"
    code, _, err = cli(capsys, str(real_file(AUTZEN)), str(out), *args)
    assert code == 2 and words in err and len(err.strip().splitlines()) == 1
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_the_help_says_where_the_points_go_to_disk_and_the_dask_limit():
    """Past the scan's budget a run keeps its points on disk, whatever the target: --help says where that
    starts and what it costs; no engine refuses a large target from the header (the local run is
    test_space_disk's, the cluster's test_dask_engine's)."""
    most = space.largest_target(spatial.BUDGET)
    assert space.state_bytes(most) <= spatial.BUDGET < space.state_bytes(most + 1)
    assert not space.on_disk(most) and space.on_disk(most + 1)
    from prism_stream.run.request import Request
    import dataclasses

    helps = {f.name: f.metadata["help"] for f in dataclasses.fields(Request)}
    assert f"a target past {most:,} points sends every point" in helps["space"]
    assert space.disk_bytes(1) == 105 and "105 bytes a point" in helps["space"]
    assert "with --dask, the output's staging folder" in helps["space"]
    assert not hasattr(spatial, "TARGET_MOST") and not hasattr(spatial, "refuse")
    # a scan on disk tracks the budget's cells while its level may have T of them (nothing routed then), few past
    assert spatial.disk_cap(most + 1) == spatial.disk_cap(spatial.CAP) == spatial.CAP > spatial.PAST_CAP
    assert spatial.disk_cap(spatial.CAP + 1) == spatial.PAST_CAP


@pytest.fixture(scope="module")
def autzen_parquet(tmp_path_factory):
    """The Autzen cloud as Parquet, every point in input order (k large keeps them all)."""
    dest = tmp_path_factory.mktemp("space_sql") / "autzen.parquet"
    sample(str(real_file(AUTZEN)), str(dest), k=10**12)
    return dest


@pytest.mark.parametrize("materialize,reads", [("rerun", "auto"), ("rerun", "two"), ("spool", "auto")])
def test_a_querys_sample_is_the_oracles(autzen, autzen_parquet, materialize, reads, tmp_path):
    from prism_stream.engines.sql import sample_query

    xyz, rgb = autzen
    out = tmp_path / "out.parquet"
    s = sample_query(f"SELECT * FROM read_parquet('{autzen_parquet}')", str(out), ratio=0.05, space="0.6",
                     materialize=materialize, reads=reads, chunk_size=6_000, seed=5, rank="r")
    kept = oracle.space_sample([rgb], [xyz], space="0.6", ratio=0.05, seed=5)[0]
    assert s.kept == len(kept) == 5_500 and s.plan["space"]["spatial_points"] == space.share(
        space.parse_share("0.6"), 5_500)
    assert s.plan["reads"] == 3  # streamed (conftest: nothing held in memory): the result read three times
    assert np.array_equal(_xyz_rows(out), xyz[kept])
    # the ranks are the merge's places: every prefix is the sample of its size
    r = pq.read_table(out).column("r").to_numpy()
    small = oracle.space_sample([rgb], [xyz], space="0.6", count=700, seed=5)[0]
    assert np.array_equal(np.flatnonzero(r < 700), np.searchsorted(kept, small))


def test_a_query_whose_rows_change_between_reads_fails_cleanly(capsys, tmp_path, autzen_parquet):
    out = tmp_path / "out.parquet"
    code, _, err = cli(capsys, "sql", f"SELECT * FROM '{autzen_parquet}' ORDER BY random()", str(out),
                       "--ratio", "0.05", "--space", "0.5")
    assert code == 6 and "other points than pass one" in err and len(err.strip().splitlines()) == 1
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_a_query_whose_points_move_among_equal_colors_fails_cleanly(capsys, tmp_path):
    """Found by a review: the bin-key check of a re-run query passes when rows of equal colors trade places,
    and the spatial share's ids then named other points than its order placed. The coordinates are checked."""
    n = 20_000
    rng = np.random.default_rng(4)
    src = write_parquet(tmp_path / "two_colors.parquet", pa.table(
        {"x": rng.uniform(0, 100, n), "y": rng.uniform(0, 100, n), "z": rng.uniform(0, 5, n),
         "red": np.repeat(np.array([90, 200], np.uint8), n // 2),
         **{c: np.full(n, 120, np.uint8) for c in ("green", "blue")}}))
    query = f"SELECT * FROM '{src}' ORDER BY red, random()"  # the same colors in the same order, every run
    out = tmp_path / "out.parquet"
    code, _, err = cli(capsys, "sql", query, str(out), "--count", "500", "--space", "0.5")
    assert code == 6 and "coordinates came in another order" in err and len(err.strip().splitlines()) == 1
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["two_colors.parquet"]
    code, _, _ = cli(capsys, "sql", query, str(out), "--count", "500", "--space", "0.5", "--materialize", "spool",
                     "--quiet")
    assert code == 0 and pq.read_metadata(out).num_rows == 500


def test_a_querys_share_is_refused_in_one_line_without_coordinates(capsys, tmp_path):
    out = tmp_path / "out.parquet"
    colors = "(i % 256)::UTINYINT AS red, (i // 256 % 256)::UTINYINT AS green, 0::UTINYINT AS blue"
    code, _, err = cli(capsys, "sql", f"SELECT {colors} FROM range(1000) t(i)", str(out), "--ratio", "0.5",
                       "--space", "0.5")
    assert code == 4 and "no coordinates found" in err and len(err.strip().splitlines()) == 1
    code, _, err = cli(capsys, "sql", f"SELECT 'abc' AS x, 0.0 AS y, 0.0 AS z, {colors} FROM range(1000) t(i)",
                       str(out), "--ratio", "0.5", "--space", "0.5")  # found by a hostile test: exit 70 after pass one
    assert code == 4 and "'x' holds string, not numbers" in err and len(err.strip().splitlines()) == 1
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_non_finite_coordinates_are_named(tmp_path, monkeypatch):
    n = 500
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 10, n)
    x[123] = np.nan
    channels = {c: rng.integers(0, 256, n).astype(np.uint8) for c in ("red", "green", "blue")}
    table = pa.table({"x": x, "y": rng.uniform(0, 10, n), "z": rng.uniform(0, 10, n), **channels})
    src = write_parquet(tmp_path / "nan.parquet", table)
    for memory in ("0", "100000"):  # streamed, held
        monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", memory)
        with pytest.raises(CorruptInput, match="non-finite coordinates"):
            sample(str(src), str(tmp_path / "o.parquet"), ratio=0.1, space="0.5")
        assert not (tmp_path / "o.parquet").exists()


# -- eval --space -------------------------------------------------------------------------------------------

def test_eval_adds_a_row_per_share_and_draws_the_trade_off(capsys, tmp_path):
    from prism_stream.evaluate.run import evaluate

    src = str(real_file("laspy__fullwave.laz"))
    ev = evaluate([src], ratios=(0.1,), spaces="0.5,0,0.9", methods=("prism", "random", "voxel"))
    prism_rows = [r for r in ev.rows if r.method.startswith("PRISM")]
    assert [r.params.get("space") for r in prism_rows] == [None, "0.5", "0.9"]  # 0 is PRISM's own row
    xyz, rgb = _cloud(real_file("laspy__fullwave.laz"))
    for r in prism_rows[1:]:
        assert r.count == r.target == 1_075 and r.chamfer is not None
        out = tmp_path / f"s{r.params['space']}.parquet"
        sample(src, str(out), ratio=0.1, space=r.params["space"])
        got = _xyz_rows(out)
        kept = oracle.space_sample([rgb], [xyz], space=r.params["space"], ratio=0.1)[0]
        assert np.array_equal(got, xyz[kept])
    assert ev.settings["spaces"] == ["0.5", "0", "0.9"]
    code, out, err = cli(capsys, "eval", src, "--ratio", "0.1", "--space", "0.5", "--methods", "prism,voxel",
                         "--plots", str(tmp_path / "plots"))
    assert code == 0 and "space=0.5" in out
    assert (tmp_path / "plots" / "space_tradeoff_r0.1.png").stat().st_size > 10_000
    code, _, err = cli(capsys, "eval", src, "--space", "2")
    assert code == 2 and "at most 1" in err


def test_the_winners_are_the_same_whether_the_cells_fit_one_word_or_not(monkeypatch):
    rng = np.random.default_rng(9)
    n = 5_000
    cells = rng.integers(-40, 40, size=(n, 3))
    rarity = rng.integers(1, 5, n).astype(np.uint64)
    prio = rng.permutation(n).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
    ids = np.arange(n, dtype=np.uint64)
    counts = rng.integers(1, 9, n)
    packed = space._winners(cells, rarity, prio, ids, counts)
    monkeypatch.setattr(space, "_packed", lambda c: None)
    apart = space._winners(cells, rarity, prio, ids, counts)
    for a, b in zip(packed, apart):
        assert np.array_equal(a, b)
    assert packed[4].sum() == counts.sum() and len(packed[0]) == len(np.unique(cells, axis=0))


# -- SPEC 7's reference values for SPEC 9 --------------------------------------------------------------------

PINNED_XYZ = np.array([[0, 0, 0], [1, 0, 0], [0.5, 0.5, 0.5], [3, 3, 0], [3.1, 3, 0], [-2, 1, 0.25]], float)
PINNED_RGB = {"red": [200, 200, 10, 10, 10, 200], "green": [10, 10, 10, 200, 200, 10],
              "blue": [10, 10, 200, 10, 10, 10]}


def test_the_pinned_cloud_keeps_the_pinned_points(tmp_path):
    """docs/SPEC.md section 7: six points, seed 0, --space 0.5: the spatial order is 2, 5, 4, 1, 0, 3 (top level
    6: cubes of side 4), and --count 1..6 keep these records."""
    ids = np.arange(6, dtype=np.uint64)
    rarity = np.array([3, 3, 1, 2, 2, 3], np.uint64)  # coarse colors: three reds, one blue, two greens
    assert _engine_order(PINNED_XYZ, rarity, ids, 0, 6, 6).tolist() == [2, 5, 4, 1, 0, 3]
    table = pa.table({"x": PINNED_XYZ[:, 0], "y": PINNED_XYZ[:, 1], "z": PINNED_XYZ[:, 2],
                      **{c: np.array(v, np.uint8) for c, v in PINNED_RGB.items()}})
    src = write_parquet(tmp_path / "six.parquet", table)
    want = {1: [2], 2: [2, 4], 3: [2, 4, 5], 4: [1, 2, 4, 5], 5: [0, 1, 2, 4, 5], 6: [0, 1, 2, 3, 4, 5]}
    for t, kept in want.items():
        out = tmp_path / f"k{t}.parquet"
        sample(str(src), str(out), count=t, space="0.5")
        assert np.array_equal(_xyz_rows(out), PINNED_XYZ[kept]), t
    rgb = tuple(np.array(PINNED_RGB[c]) for c in ("red", "green", "blue"))
    assert [oracle.space_sample([rgb], [PINNED_XYZ], space="0.5", count=t)[0].tolist() for t in want] == \
        list(want.values())


@pytest.mark.parametrize("far", [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, -4.0)])
@pytest.mark.parametrize("step", [2.0 ** -62, 2.0 ** -63])
def test_the_last_level_is_the_specs_whichever_axis_sets_the_top(far, step):
    """The top level depends on which axis holds the largest coordinate (y or z: one or two levels finer than
    x) and on a negative power of two (-2^k lies in cell -1 of side 2^k); the scan's finest level must reach
    SPEC 9's last level, 186 below that top, where points 2^-62 apart still part (found by a hostile test)."""
    xyz = np.zeros((21, 3))
    xyz[0] = far
    xyz[1:, 0] = np.arange(20) * step
    ids = np.arange(21, dtype=np.uint64)
    rarity = np.ones(21, np.uint64)
    for t in (5, 15, 21):
        want = ids[oracle.spatial_order(xyz, rarity, oracle.priority(ids, 0), t, 0)]
        for chunk in (1, 3, 100):
            assert np.array_equal(_engine_order(xyz, rarity, ids, 0, t, chunk), want), (t, chunk)


def test_a_target_near_n_walks_up_without_holding_every_level():
    """T >= N / 2 keeps the scan at its finest level, 186 levels below the top: the order walks up holding a
    few words a cell, and skips the levels where no two cells merge (a hostile test found 2.75 GB and 14 s)."""
    rng = np.random.default_rng(4)
    n = 20_000
    xyz = np.column_stack([rng.uniform(0, 1, n), rng.uniform(0, 1, n), np.zeros(n)])
    ids = np.arange(n, dtype=np.uint64)
    rarity = rng.integers(1, 9, n).astype(np.uint64)
    scan = space.SpatialScan(n)
    prio = priorities_of_np(ids, seed_mix(0))
    scan.add(xyz, rarity, prio, ids)
    assert scan.level <= space.top_level(xyz.min(axis=0), xyz.max(axis=0)) - 180
    got = scan.order(0)
    assert np.array_equal(got, ids[oracle.spatial_order(xyz, rarity, oracle.priority(ids, 0), n, 0)])
    assert len(got) == n


def test_what_the_headers_and_schemas_show_is_refused_before_pass_one(capsys, tmp_path, monkeypatch):
    """Found by a hostile test: a Parquet file without coordinates was refused only after pass one (a
    --per-file run too, where it must stop before the first file is sampled)."""
    from prism_stream.engines import reads

    def no_pass_one(*a, **k):
        raise AssertionError("pass one ran")

    monkeypatch.setattr(reads, "scan", no_pass_one)
    monkeypatch.setattr(reads, "scan_held", no_pass_one)
    rng = np.random.default_rng(2)
    colors = {c: rng.integers(0, 256, 1000).astype(np.uint8) for c in ("red", "green", "blue")}
    bare = write_parquet(tmp_path / "bare.parquet", pa.table({"a": np.zeros(1000), **colors}))
    code, _, err = cli(capsys, str(bare), str(tmp_path / "o.parquet"), "--ratio", "0.5", "--space", "0.5")
    assert code == 4 and "bare.parquet: no coordinates found" in err and "--space need x/y/z" in err
    folder = tmp_path / "tiles"
    folder.mkdir()
    write_parquet(folder / "a_small.parquet", pa.table({"x": np.zeros(1000), "y": np.zeros(1000),
                                                        "z": np.zeros(1000), **colors}))
    write_parquet(folder / "b_bare.parquet", pa.table({"a": np.zeros(1000), **colors}))
    out = tmp_path / "out"
    code, _, err = cli(capsys, str(folder), str(out) + "/", "--ratio", "1", "--space", "0.5", "--per-file")
    assert code == 4 and "b_bare.parquet: no coordinates found" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_eval_refuses_a_share_it_cannot_give(capsys):
    src = str(real_file("laspy__fullwave.laz"))
    for extra in (["--k", "2"], ["--mode", "paper"], ["--methods", "random,voxel"]):
        code, _, err = cli(capsys, "eval", src, "--ratio", "0.1", "--space", "0.5", *extra)
        assert code == 2 and "--space rows" in err and len(err.strip().splitlines()) == 1


def test_a_list_column_of_coordinates_is_taken_by_every_engine(capsys, tmp_path):
    """Found by a hostile test: DuckDB reads a Parquet fixed-size list as a LIST, and sql --space refused the
    `xyz` column the local engine takes. A list of 3 numbers a row is coordinates; another length is refused
    in one line, nothing left."""
    from prism_stream.engines.sql import sample_query

    n = 6_000
    rng = np.random.default_rng(8)
    xyz = rng.uniform(0, 50, (n, 3))
    colors = {c: rng.integers(0, 256, n).astype(np.uint8) for c in ("red", "green", "blue")}
    flat = pa.array(xyz.ravel())
    src = write_parquet(tmp_path / "xyz.parquet", pa.table({"xyz": pa.FixedSizeListArray.from_arrays(flat, 3),
                                                            **colors}))
    local, query = tmp_path / "local.parquet", tmp_path / "query.parquet"
    sample(str(src), str(local), count=600, space="0.5", seed=3)
    sample_query(f"SELECT * FROM '{src}'", str(query), count=600, space="0.5", seed=3)
    kept = oracle.space_sample([tuple(colors.values())], [xyz], space="0.5", count=600, seed=3)[0]
    for out in (local, query):
        got = pq.read_table(out).column("xyz").combine_chunks()
        assert np.array_equal(got.flatten().to_numpy().reshape(-1, 3), xyz[kept])
    short = tmp_path / "short.parquet"
    code, _, err = cli(capsys, "sql", f"SELECT xyz[1:2] AS xyz, red, green, blue FROM '{src}'", str(short),
                       "--count", "600", "--space", "0.5")
    assert code == 4 and "lists that are not 3 numbers" in err and len(err.strip().splitlines()) == 1
    assert not short.exists()


@settings(max_examples=60, deadline=None)
@given(cells=st.lists(st.tuples(*[st.integers(-(1 << 62), (1 << 62) - 1) | st.integers(-3, 3)] * 3),
                      min_size=1, max_size=40))
def test_the_oracles_unique_rows_are_numpys(cells):
    """The oracle's cell grouping (a packed key where the ranges allow, else a sort on the three columns) is
    ``np.unique`` over the rows."""
    cells = np.array(cells, np.int64)
    uniq, inverse = oracle._unique_rows(cells)
    want, want_inverse = np.unique(cells, axis=0, return_inverse=True)
    assert np.array_equal(uniq, want) and np.array_equal(inverse, want_inverse.ravel())


def _bytes_held(a: np.ndarray) -> int:
    """The bytes an array keeps alive: its own, or those of the buffer it is a view of."""
    base = a
    while isinstance(base, np.ndarray) and base.base is not None:
        base = base.base
    return base.nbytes if isinstance(base, np.ndarray) else memoryview(base).nbytes


def test_a_chunks_winners_hold_their_own_bytes_alone():
    """A scan buffers each chunk's winners until a merge: were they views of the chunk's arrays (a point
    each), a scan whose chunks have few cells would hold a block's bytes for each (at 100M points, 300 MiB
    over the spatial read's peak)."""
    from prism_stream.core import space as space_mod

    rng = np.random.default_rng(3)
    n = 1 << 16
    cells = rng.integers(0, 16, (n, 3)).astype(np.int64)
    rarity, prio = rng.integers(0, 5, n).astype(np.uint64), rng.integers(0, 2**63, n).astype(np.uint64)
    out = space_mod._winners(cells, rarity, prio, np.arange(n, dtype=np.uint64), np.ones(n, np.int64))
    assert 1_000 < len(out[0]) < n // 2
    assert [_bytes_held(a) for a in out] == [a.nbytes for a in out]
