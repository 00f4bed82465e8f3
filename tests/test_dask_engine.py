"""The Dask engine keeps the local engine's rows, on any number of workers and work units,
through a worker killed mid-pass and on workers much smaller than the input."""

from __future__ import annotations

import functools
import glob
import json
import math
import os
import signal
import subprocess
import sys

import laspy
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import distributed

import prism_stream  # noqa: E402
from prism_stream.engines import dask as dask_engine  # noqa: E402
from prism_stream.engines.dask import driver as dask_driver  # noqa: E402
from prism_stream.errors import CorruptInput, OutputExists, UsageError  # noqa: E402
from prism_stream.run import tempspace  # noqa: E402

from conftest import real_file  # noqa: E402
from fingerprints import base_folder, check, copy_inputs, fingerprint  # noqa: E402

AUTZEN = str(real_file("pdal__autzen_trim.las"))
# a worker process holds ~380 MiB before any data (Python, Dask, numba, pyarrow, the 64 MiB rule table)
# and pauses at 80% of its limit, so 1 GB is the smallest comfortable size at 0 quantization bits
WORKER_MEMORY = "1GB"


def write_tile(path, n, seed, sixteen_bit=False, fmt=3):
    """A generated LAS tile: a few hundred colors plus noise, like a colorized survey."""
    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(point_format=fmt, version="1.2")
    header.scales = [0.01] * 3
    header.offsets = [0, 0, 0]
    with laspy.open(path, mode="w", header=header) as w:
        for a in range(0, n, 2_000_000):
            m = min(2_000_000, n - a)
            pts = laspy.ScaleAwarePointRecord.zeros(m, header=header)
            pts.x = rng.uniform(0, 1000, m)
            pts.y = rng.uniform(0, 1000, m)
            pts.z = rng.uniform(0, 50, m)
            palette = np.random.default_rng(1).integers(20, 236, (300, 3))
            rgb = np.clip(palette[rng.integers(0, 300, m)] + rng.normal(0, 4, (m, 3)), 0, 255).astype(np.uint16)
            if sixteen_bit:
                rgb = rgb * 257
            pts.red, pts.green, pts.blue = rgb.T
            pts.intensity = rng.integers(0, 65535, m)
            w.write_points(pts)


@pytest.fixture(scope="module")
def client():
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                       memory_limit=WORKER_MEMORY, dashboard_address=None)
    with distributed.Client(cluster) as c:
        yield c
    cluster.close()


@pytest.fixture(scope="module")
def tiles(tmp_path_factory):
    """Three LAS tiles (one with 16-bit colors, one 8-bit stored as 16-bit late in the file) and part of autzen."""
    folder = tmp_path_factory.mktemp("tiles")
    write_tile(folder / "a.las", 30_000, 1)
    write_tile(folder / "b.las", 45_000, 2, sixteen_bit=True)
    # c: 8-bit for its first 20,000 points, then one 16-bit value: units of c disagree, the file is 16-bit
    write_tile(folder / "c.las", 25_000, 3)
    with laspy.open(folder / "c.las", mode="r") as r:
        las = r.read()
    las.red[20_000] = 4000
    las.write(folder / "c.las")
    with laspy.open(AUTZEN) as r:  # a real cloud, as its first 25,000 points: the rows, not the size, are checked
        head = r.read_points(25_000)
        with laspy.open(folder / "d.las", mode="w", header=r.header) as w:
            w.write_points(head)
    return folder


@pytest.fixture(scope="module")
def parquet_input(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pq")
    rng = np.random.default_rng(7)
    n = 40_000
    table = pa.table({"x": rng.normal(size=n), "red": rng.integers(0, 40, n).astype(np.uint8) * 6,
                      "green": rng.integers(0, 40, n).astype(np.uint8) * 6,
                      "blue": rng.integers(0, 4, n).astype(np.uint8)})
    pq.write_table(table, folder / "cloud.parquet", row_group_size=3_000)
    return folder / "cloud.parquet"


def local_rows(inputs, out, **options) -> pa.Table:
    prism_stream.sample(inputs, str(out), overwrite=True, **options)
    return pq.read_table(out)


DASK_CASES = {
    "parquet": ("out.parquet", dict(ratio=0.03, seed=5)),
    "laz_tiles_rank": ("tiles/*.laz", dict(count=2_000, rank="prism_rank", quant_bits=2)),
    "parquet_two_reads": ("out/", dict(k=3, reads="two")),
    "plan": (None, dict(ratio=0.01)),
}


@pytest.mark.parametrize("case", sorted(DASK_CASES))
def test_dask_engine_writes_the_recorded_bytes(client, tiles, tmp_path, case):
    """Every part's bytes and the summary's fields, held to what the engine wrote before the engines shared one
    pipeline (tests/fingerprints.py); the units' spill sizes depend on the order units finish in."""
    import warnings

    output, options = DASK_CASES[case]
    base = base_folder(tmp_path)
    inputs = copy_inputs(base, *sorted(tiles.glob("*.las")))
    out = None if output is None else f"{base}/{output}"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        summary = dask_engine.sample(client, inputs, out, unit_size=10_000, **options)
    folder = [] if out is None else [os.path.dirname(out) if "*" in out else out]
    # a unit's spill depends on the prior it started with, which depends on which units finished first
    check(f"dask/{case}", fingerprint(base, folder, summary,
                                      varying={"dask", "spill_points", "spill_bytes", "units_read_again",
                                               "spill_points_written", "spill_compactions"}))


# every rule with units of 10,000 points (several a file: each unit costs a scan of the 2^24-bin table, so
# more of them only slow the test); with one unit a file, two of them
@pytest.mark.parametrize("unit_size,options", [
    (10_000, dict(ratio=0.03, seed=5)), (10_000, dict(count=2_000, quant_bits=2, color_space="chroma")),
    (10_000, dict(ratio=0.2, mode="paper", seed=11)), (10_000, dict(k=3)),
    (10_000, dict(ratio=0.05, quant_bits=5, seed=2)),  # 512 keys: the histogram folds are tables (histogram.fold)
    (1 << 22, dict(ratio=0.03, seed=5)), (1 << 22, dict(k=3))])
def test_same_rows_as_local_engine(client, tiles, tmp_path, unit_size, options):
    import warnings

    inputs = [str(tiles / "*.las")]
    with warnings.catch_warnings(record=True) as local_warned:
        warnings.simplefilter("always")
        expected = local_rows(inputs, tmp_path / "local.parquet", **options)
    with warnings.catch_warnings(record=True) as dask_warned:
        warnings.simplefilter("always")
        summary = dask_engine.sample(client, inputs, str(tmp_path / "out"), unit_size=unit_size, chunk_size=1_500,
                                     **options)
    # d.las (Autzen) has a CRS, the generated tiles none: both engines write none and say so (issue 28, item 7)
    crs = "the inputs do not share one CRS, so none is written"
    assert any(crs in str(w.message) for w in local_warned) and any(crs in str(w.message) for w in dask_warned)
    got = dask_engine.read_dataset(str(tmp_path / "out"))
    assert got.equals(expected)
    assert summary.kept == expected.num_rows
    assert summary.plan["dask"]["units"] >= (4 if unit_size > 1e6 else 13)
    sources = prism_stream.sample(inputs, None, **options).sources
    assert summary.sources == sources
    assert [s["color_depth"] for s in sources] == ["8", "16", "16", "8"]


def test_parquet_row_groups_and_one_worker(tiles, parquet_input, tmp_path):
    """One worker, Parquet input split by row group, a file list: the rows do not move. (A worker of threads:
    the one worker is the point; `--dask local:N`'s processes are the README's example, tests/test_readme.py.)"""
    inputs = [str(parquet_input), str(tiles / "a.las")]
    cols = ["x", "red", "green", "blue"]
    expected = local_rows([str(parquet_input)], tmp_path / "local.parquet", ratio=0.05).select(cols)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) \
            as cluster, distributed.Client(cluster) as one:
        # 3,000-row groups, taken two at a time (the last, 1,000 rows, with its neighbour); local Parquet on
        # Dask reads twice unless told to read once: the same rows either way
        for reads, times in (("auto", 2), ("one", 1)):
            out = tmp_path / f"out-{reads}.parquet"
            summary = dask_engine.sample(one, [str(parquet_input)], str(out), ratio=0.05, unit_size=7_000,
                                         reads=reads)
            assert summary.plan["dask"]["workers"] == 1 and summary.plan["dask"]["units"] == 7
            assert summary.plan["reads"] == times
            assert (summary.plan["why"] == dask_driver.PARQUET_TWICE) == (reads == "auto")
            assert dask_engine.read_dataset(str(out)).select(cols).equals(expected)
        # the hint names what can write these apart: a Dask dataset is one schema, and its tiles take LAS
        # inputs alone (it said FOLDER/*.laz, which then refused these inputs after pass one; a reviewer's find)
        with pytest.raises(prism_stream.PrismError,
                           match=r"columns differ.*or write an output folder in a run without --dask: one output "
                                 r"per input\)$"):
            dask_engine.sample(one, inputs, str(tmp_path / "mixed"), ratio=0.05)
        from prism_stream.formats import parquet as parquet_format

        real = parquet_format.ParquetSource._batches
        parquet_format.ParquetSource._batches = lambda *a, **k: (_ for _ in ()).throw(AssertionError("decoded"))
        try:  # tiles of a Parquet input: refused before a point is decoded
            with pytest.raises(prism_stream.PrismError, match="LAS/LAZ output needs LAS/LAZ inputs"):
                dask_engine.sample(one, [str(parquet_input)], str(tmp_path / "tiles" / "*.laz"), ratio=0.05)
        finally:
            parquet_format.ParquetSource._batches = real
    assert not os.path.exists(tmp_path / "mixed")


def test_las_tiles_of_different_dimensions_are_pointed_to_tiles(client, tmp_path):
    """LAS inputs whose extra dimensions differ, into one Dask dataset: the refusal (before pass one) points to
    FOLDER/*.laz, which writes them apart, and that run works."""
    from conftest import random_colors, write_las

    folder = tmp_path / "in"
    folder.mkdir()
    write_las(folder / "a.laz", random_colors(400, 1), extra={"height": np.zeros(400, np.float32)})
    write_las(folder / "b.laz", random_colors(400, 2), extra={"confidence": np.ones(400, np.uint8)}, seed=1)
    with pytest.raises(prism_stream.PrismError, match=r"columns differ.*or write FOLDER/\*\.laz: one tile per "
                                                      r"input\)$"):
        dask_engine.sample(client, [str(folder / "*.laz")], str(tmp_path / "one"), ratio=0.2)
    assert not (tmp_path / "one").exists()
    dask_engine.sample(client, [str(folder / "*.laz")], str(tmp_path / "apart" / "*.laz"), ratio=0.2)
    assert sorted(os.listdir(tmp_path / "apart")) == ["a.laz", "b.laz"]


def test_cutoff_bounds_and_partitions_do_not_change_rows(client, tiles, tmp_path):
    """A bound too low for most bins (redone without one) and many reduce partitions: same rows."""
    inputs = [str(tiles / "*.las")]
    expected = local_rows(inputs, tmp_path / "local.parquet", ratio=0.1)
    summary = dask_engine.sample(client, inputs, str(tmp_path / "out"), ratio=0.1, unit_size=8_000,
                                 bound_sigmas=0.0, bottoms_per_reducer=200)
    stats = summary.plan["dask"]
    assert stats["bins_redone"] > 0 and stats["cutoff_partitions"] > 5
    assert dask_engine.read_dataset(str(tmp_path / "out")).equals(expected)
    fine = dask_engine.sample(client, inputs, str(tmp_path / "out2"), ratio=0.1, unit_size=8_000)
    assert fine.plan["dask"]["bins_redone"] == 0
    # the bound keeps the reduce near the sample's size, not the input's
    assert fine.plan["dask"]["bottoms_pairs"][0] < 3 * fine.kept


@pytest.mark.parametrize("reads", ["auto", "two"])
def test_one_unit_and_many_cutoff_partitions(client, tiles, tmp_path, reads):
    """A lone unit's bottom set spans every slot: each partition still cuts it to its own range."""
    inputs = [str(tiles / "a.las")]
    expected = local_rows(inputs, tmp_path / "local.parquet", ratio=0.3)
    summary = dask_engine.sample(client, inputs, str(tmp_path / "out"), ratio=0.3, unit_size=10**9,
                                 bottoms_per_reducer=5, reads=reads)
    assert summary.plan["dask"]["units"] == 1 and summary.plan["dask"]["cutoff_partitions"] > 1
    assert dask_engine.read_dataset(str(tmp_path / "out")).equals(expected)


@pytest.mark.parametrize("options,group", [(dict(ratio=0.05, space="0.5"), 8),
                                           (dict(count=3_000, space="0.8", seed=4, rank="r", quant_bits=2), 0)])
def test_a_spatial_share_keeps_the_local_engines_rows(client, tiles, tmp_path, options, group, monkeypatch):
    """--space (SPEC 9): groups of units scan their points, the scans are folded on the cluster; 8- and 16-bit
    tiles, units of a few chunks, a group a unit (SPACE_GROUP 0: folds of folds), the ranks the merge's places."""
    import warnings

    monkeypatch.setattr(dask_driver, "SPACE_GROUP", group)

    inputs = [str(tiles / "*.las")]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the tiles share no CRS: said by both engines (test above)
        local = prism_stream.sample(inputs, str(tmp_path / "local.parquet"), **options)
        summary = dask_engine.sample(client, inputs, str(tmp_path / "out"), unit_size=7_000, chunk_size=1_500,
                                     **options)
    assert dask_engine.read_dataset(str(tmp_path / "out")).equals(pq.read_table(tmp_path / "local.parquet"))
    assert summary.plan["space"] == local.plan["space"] and summary.plan["reads"] == 3

    def said(path):  # the provenance: its options and ranks as the local run's (a review found "rank" differed)
        meta = json.loads(pq.read_schema(path).metadata[b"prism_stream"])
        return meta["options"], meta.get("rank")

    assert said(sorted(glob.glob(str(tmp_path / "out" / "*.parquet")))[0]) == said(tmp_path / "local.parquet")
    assert summary.plan["dask"]["units"] >= 10


def test_a_spatial_share_is_the_oracles_and_writes_tiles(client, tmp_path):
    import oracle

    las = laspy.read(AUTZEN)
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    rgb = tuple(np.asarray(las.points[c]) for c in ("red", "green", "blue"))
    kept = oracle.space_sample([rgb], [xyz], space="0.7", count=2_500, seed=9)[0]
    dask_engine.sample(client, AUTZEN, str(tmp_path / "out" / "*.laz"), count=2_500, space="0.7", seed=9,
                       unit_size=20_000)
    got = laspy.read(tmp_path / "out" / "pdal__autzen_trim.laz")
    assert got.points.array.tobytes() == las.points.array[kept].tobytes()


def test_points_at_the_origin_before_the_rest_leave_the_level_open(client, tmp_path):
    """Found by a review: a unit (or a first chunk) of records all at (0, 0, 0) fixed the scan at level 0,
    coarser than the cloud needs, and its fold kept it there: 1,055 points placed spatially of 3,000."""
    import oracle

    rng = np.random.default_rng(0)
    xyz = np.zeros((100_000, 3))
    xyz[60_000:] = np.round(rng.uniform(0.5, 10, (40_000, 3)), 2)
    header = laspy.LasHeader(point_format=2, version="1.2")
    header.scales, header.offsets = [0.01] * 3, [0, 0, 0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    rgb = [rng.integers(0, 256, 100_000).astype(np.uint16) for _ in range(3)]
    las.red, las.green, las.blue = rgb
    las.write(tmp_path / "in.las")
    kept = oracle.space_sample([tuple(rgb)], [xyz], space="1", count=3_000, seed=1)[0]
    local = prism_stream.sample(str(tmp_path / "in.las"), str(tmp_path / "local.las"), count=3_000, space="1",
                                seed=1, chunk_size=10_000)
    assert laspy.read(tmp_path / "local.las").points.array.tobytes() == las.points.array[kept].tobytes()
    dask_engine.sample(client, str(tmp_path / "in.las"), str(tmp_path / "out" / "*.las"), count=3_000, space="1",
                       seed=1, unit_size=10_000)
    got = laspy.read(tmp_path / "out" / "in.las")
    assert got.points.array.tobytes() == las.points.array[kept].tobytes()
    assert local.plan["space"]["spatial_points"] == 3_000


def _space_on_disk(monkeypatch, temp=None):
    """A spatial share's scan sent to disk on the driver, whatever its target (a budget of nothing, a few cells
    tracked, small files routed a few ways, the order's births sorted in runs): decided on the driver, and
    handed to the workers' tasks. Returns the largest bytes the scan's files of ``temp`` held at once."""
    from prism_stream.core import space
    from prism_stream.engines import spatial, spatial_disk

    monkeypatch.setattr(space, "MEMORY_BUDGET", 0)
    monkeypatch.setattr(spatial, "CAP", 300)
    monkeypatch.setattr(spatial_disk, "LEAF", 4_000)
    monkeypatch.setattr(spatial_disk, "FAN", 5)
    monkeypatch.setattr(spatial_disk, "SORT_RUN", 500)
    peak = [0]
    if temp is not None:
        class Measured(spatial_disk.ArrayFile):  # the scan's files' bytes on disk, after each write
            def _written(self):
                super()._written()
                peak[0] = max(peak[0], sum(f.stat().st_size for f in temp.rglob("space.*")))

        monkeypatch.setattr(spatial_disk, "ArrayFile", Measured)
    return peak


@pytest.mark.parametrize("options,unit,tiled", [(dict(ratio=0.05, space="0.5"), 20_000, False),
                                                (dict(count=3_000, space="0.8", seed=4, rank="r"), 7_000, False),
                                                (dict(count=2_500, space="0.7", seed=9, rank="r"), 60_000, True)])
def test_a_spatial_share_past_the_memory_budget_is_scanned_on_disk(client, tmp_path, monkeypatch, options, unit,
                                                                   tiled):
    """A target whose cells do not fit in memory (no refusal since stop 60): the groups' scans track a few
    cells and write their points beside the output, the driver sorts them out by cell in its temporary
    folder and merges there. The oracle's sample (in-memory Parquet, ranks, LAZ tiles), the local run's
    summary, and nothing left in the staging or temporary folders."""
    import oracle
    from prism_stream.core import space

    las = laspy.read(AUTZEN)
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    rgb = tuple(np.asarray(las.points[c]) for c in ("red", "green", "blue"))
    where = {k: v for k, v in options.items() if k in ("ratio", "count", "seed")}
    kept = oracle.space_sample([rgb], [xyz], space=options["space"], **where)[0]
    held = prism_stream.sample(AUTZEN, str(tmp_path / ("held.laz" if tiled else "held.parquet")), chunk_size=7_000,
                               **options)
    temp = tmp_path / "temp"
    temp.mkdir()
    peak = _space_on_disk(monkeypatch, temp)
    out = tmp_path / "out" / "*.laz" if tiled else tmp_path / "out"
    summary = dask_engine.sample(client, AUTZEN, str(out), unit_size=unit, chunk_size=7_000, temp_dir=str(temp),
                                 **options)
    assert summary.kept == len(kept) and summary.plan["reads"] == 3
    facts = summary.plan["space"]
    assert facts["points_on_disk"] == len(xyz) and facts["points_routed"] >= len(xyz)
    assert {k: v for k, v in facts.items() if not k.startswith("points_")} == \
        {k: v for k, v in held.plan["space"].items() if not k.startswith("points_")}
    if tiled:  # the tile's ids and ranks sent as files beside the output, read a block at a time
        got = laspy.read(tmp_path / "out" / "pdal__autzen_trim.laz")
        want = laspy.read(tmp_path / "held.laz")
        assert got.points.array.tobytes() == want.points.array.tobytes()
        assert np.array_equal(np.column_stack([got.x, got.y, got.z]), xyz[kept])
    else:
        table = dask_engine.read_dataset(str(out))
        assert table.equals(pq.read_table(tmp_path / "held.parquet"))
        assert np.array_equal(np.column_stack([table[c].to_numpy() for c in "xyz"]), xyz[kept])
    # the driver's temporary folder holds the order's merge and the merge with PRISM's order (the points' files
    # are in the staging folder: tests/test_space_disk.py measures those)
    assert 0 < peak[0] <= space.disk_bytes(len(xyz), summary.kept)
    assert list(temp.iterdir()) == []
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no staging folder left


@pytest.mark.parametrize("where", ["worker", "driver"])
def test_a_spatial_share_on_disk_that_fails_leaves_nothing(client, tmp_path, monkeypatch, where):
    """A group's points that cannot be placed (a non-finite coordinate, found on a worker while its points go
    to the staging folder) or a full temporary disk under the driver's sort: one line, and neither the
    output, its staging folder (the groups' files) nor the driver's temporary files are left."""
    from prism_stream.engines import spatial_disk

    temp = tmp_path / "temp"
    temp.mkdir()
    _space_on_disk(monkeypatch)
    n = 30_000
    rng = np.random.default_rng(3)
    xyz = rng.uniform(0, 100, (n, 3))
    if where == "worker":
        xyz[n - 5, 1] = np.nan
    else:  # the driver's merge of the sorted runs the workers wrote
        def full(self, *a, **k):
            raise OSError(28, "No space left on device", os.path.join(self.folder, "space.sorted.1"))

        monkeypatch.setattr(spatial_disk.DiskScan, "taken", full)
    table = pa.table({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                      **{c: rng.integers(0, 256, n).astype(np.uint8) for c in ("red", "green", "blue")}})
    pq.write_table(table, tmp_path / "in.parquet", row_group_size=5_000)
    error = CorruptInput if where == "worker" else prism_stream.errors.OutputError
    with pytest.raises(error) as caught:
        dask_engine.sample(client, str(tmp_path / "in.parquet"), str(tmp_path / "out"), ratio=0.1, space="0.5",
                           temp_dir=str(temp))
    said = str(caught.value)
    assert "\n" not in said and (said.endswith("non-finite coordinates; --space needs every point placed")
                                  if where == "worker" else said.startswith(f"{temp}: cannot write"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.parquet", "temp"]
    assert list(temp.iterdir()) == []


def test_a_full_staging_disk_under_the_spatial_tasks_is_one_line(tmp_path, monkeypatch):
    """A routing task on a worker that runs out of room beside the output: one line naming that folder (not
    a traceback from the worker), and nothing left."""
    from prism_stream.engines import spatial_disk

    _space_on_disk(monkeypatch)
    route = spatial_disk.route_part

    @functools.wraps(route)
    def full(path, *args):
        route(path, *args)
        raise OSError(28, "No space left on device", path + ".000")

    monkeypatch.setattr(spatial_disk, "route_part", full)  # (the task calls it through the module)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) \
            as cluster, distributed.Client(cluster) as one:
        with pytest.raises(prism_stream.errors.OutputError) as caught:
            dask_engine.sample(one, AUTZEN, str(tmp_path / "out"), ratio=0.05, space="0.5", unit_size=20_000,
                               temp_dir=str(tmp_path))
    said = str(caught.value)  # the folder beside the output, not the staging folder (gone with the run)
    assert said == f"{tmp_path}: cannot write the spatial share's files beside the output: No space left on device"
    assert os.listdir(tmp_path) == []


def test_a_full_disk_under_the_drivers_copy_of_a_tiles_sample_is_one_line(client, tmp_path, monkeypatch):
    """The driver copies a tile's ids beside the output past the budget: a full disk there is one line naming
    the output's folder (not an internal error), and nothing is left."""
    _space_on_disk(monkeypatch)

    def full(self, stage, *a):
        raise OSError(28, "No space left on device", os.path.join(stage, ".keep", "tile-000000.ids"))

    monkeypatch.setattr(dask_driver.OnCluster, "_tile_files", full)
    with pytest.raises(prism_stream.errors.OutputError) as caught:
        dask_engine.sample(client, AUTZEN, str(tmp_path / "out" / "*.laz"), ratio=0.05, space="0.5",
                           unit_size=20_000, temp_dir=str(tmp_path))
    assert str(caught.value) == f"{tmp_path}: cannot write a tile's sample beside the output: No space left on device"
    assert os.listdir(tmp_path) == []


def _slow_write(i: int, folder: str) -> int:
    import time

    if i == 0:
        raise ValueError("the first task fails")
    time.sleep(0.4)
    with open(os.path.join(folder, f"{i:03d}"), "w"):
        pass
    return i


@pytest.mark.parametrize("how", ["windowed", "all at once"])
def test_a_failed_step_leaves_no_task_writing(tmp_path, how):
    """One task of a step fails (run a window at a time, or submitted all at once as the spatial share's steps
    are): its error reaches the driver only once the step's other tasks are cancelled and the running ones
    have ended, so nothing is written after it (a straggler's file would land after the driver removed the
    staging folder)."""
    import time

    from prism_stream.engines.dask.cluster import gather, gather_settled, windowed

    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) \
            as cluster, distributed.Client(cluster) as c:
        with pytest.raises(ValueError, match="the first task fails"):
            if how == "windowed":
                windowed(c, 40, lambda i: c.submit(_slow_write, i, str(tmp_path), key=f"slow-{i}"),
                         lambda i, f: gather(c, f))
            else:
                gather_settled(c, [c.submit(_slow_write, i, str(tmp_path), key=f"slow-{i}") for i in range(8)])
        seen = sorted(os.listdir(tmp_path))
        time.sleep(1.2)  # three task lengths: a task still running would have written by now
        assert sorted(os.listdir(tmp_path)) == seen
    if how == "windowed":
        assert 1 <= len(seen) < 39  # the one running beside the failure finished; the queued ones never ran
    else:
        assert len(seen) == 7  # gather waits for every task of the step before it says the first error


def test_settle_waits_for_a_task_that_reaches_its_worker_after_the_first_look(monkeypatch):
    """A task the scheduler sent before the cancel can reach its worker after settle's first look and start
    there (the scheduler's messages and client.run travel apart): settle returns only after two looks 0.1 s
    apart find nothing that may run, so one that appears in between is waited for."""
    from prism_stream.engines.dask import cluster

    looks = iter([set(), {"k"}, set(), {"k"}, {"k"}, set(), set(), set()])
    seen = []

    def executing(client, keys):
        seen.append(keys)
        return next(looks)

    class Future:
        key = "k"

    class Client:
        def cancel(self, futures):
            pass

    monkeypatch.setattr(cluster, "_executing", executing)
    cluster.settle(Client(), [Future()])
    assert len(seen) == 7  # empty, running, empty, running, running, empty, empty: done


def test_a_full_disk_under_the_tiles_samples_folder_is_one_line(client, tmp_path, monkeypatch):
    """The folder of the tiles' samples (``.keep``, past the budget) on a full disk: one line naming the output's
    folder, nothing left."""
    _space_on_disk(monkeypatch)
    real = os.mkdir

    def full(path, *args, **kwargs):
        if os.path.basename(os.fspath(path)) == ".keep":
            raise OSError(28, "No space left on device", os.fspath(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(os, "mkdir", full)
    with pytest.raises(prism_stream.errors.OutputError) as caught:
        dask_engine.sample(client, AUTZEN, str(tmp_path / "out" / "*.laz"), ratio=0.05, space="0.5",
                           unit_size=20_000, temp_dir=str(tmp_path))
    assert str(caught.value) == f"{tmp_path}: cannot write a tile's sample beside the output: No space left on device"
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("what", ["here", "the units' spills beside the output"])
def test_a_full_disk_under_the_drivers_first_writes_is_one_line(client, tmp_path, monkeypatch, what):
    """The driver's first writes beside the output (the staging folder, the spills' folder in it) on a full
    disk: one line naming the output's folder (it was "internal error: OSError"), and nothing left."""
    real = os.mkdir

    def full(path, *args, **kwargs):
        p = os.fspath(path)
        hit = os.path.basename(p) == ".spill" if "spills" in what else os.path.dirname(p) == str(tmp_path)
        if hit:
            raise OSError(28, "No space left on device", p)
        return real(path, *args, **kwargs)

    monkeypatch.setattr(os, "mkdir", full)  # the driver's process only: the workers are processes of their own
    with pytest.raises(prism_stream.errors.OutputError) as caught:
        dask_engine.sample(client, AUTZEN, str(tmp_path / "out"), ratio=0.05, unit_size=20_000)
    assert str(caught.value) == f"{tmp_path}: cannot write {what}: No space left on device"
    assert os.listdir(tmp_path) == []


def test_a_spatial_share_on_disk_is_refused_before_pass_one_without_room(client, tmp_path, monkeypatch):
    """The groups' points go beside the output and the rest to the driver's temporary folder: where either
    has no room (as the forecast counts it), one line naming that folder, before pass one, nothing written."""
    from prism_stream.core import space
    from prism_stream.engines import spatial
    from prism_stream.run import staging

    _space_on_disk(monkeypatch)
    monkeypatch.setattr(dask_driver.OnCluster, "scan", lambda *a: (_ for _ in ()).throw(AssertionError("pass one")))
    n = laspy.open(AUTZEN).header.point_count
    temp, beside = tmp_path / "temp", tmp_path / "outputs"
    temp.mkdir()
    beside.mkdir()
    need = space.disk_bytes(n, n // 20)
    staged, merged = space.cluster_disk_bytes(n, n // 20)
    assert max(staged, merged) == need < staged + merged  # one disk: the most of both at once

    real = staging.free_bytes

    def free(folder):
        return {str(temp): room["temp"], str(beside): room["beside"]}.get(str(folder)) or real(folder)

    monkeypatch.setattr(staging, "free_bytes", free)
    r = staging.RESERVE
    for room, devices, named in (({"temp": need, "beside": 10**12}, 1, temp),  # the reserve kept free
                                 ({"temp": 10**12, "beside": staged + r - 1}, 2, beside),
                                 ({"temp": merged + r - 1, "beside": 10**12}, 2, temp),
                                 ({"temp": need + r, "beside": 0}, 1, None),  # one disk: the temporary folder's
                                 ({"temp": merged + r, "beside": staged + r}, 2, None)):
        # one disk for both (the temporary folder's check counts the points' files too), or two
        monkeypatch.setattr(spatial, "same_disk", lambda a, b, devices=devices: devices == 1)
        if named is None:
            spatial.check_cluster_room(prism_stream.run.request.Request.of(ratio=0.05, space="0.5").options, n,
                                       str(temp), str(beside / "out"))
            continue
        with pytest.raises(prism_stream.errors.OutputError, match="the spatial share's scan of") as caught:
            dask_engine.sample(client, AUTZEN, str(beside / "out"), ratio=0.05, space="0.5", temp_dir=str(temp))
        assert str(caught.value).startswith(f"{named}: not enough ")
        assert list(beside.iterdir()) == [] and list(temp.iterdir()) == []
    # a temporary folder that does not exist: the usual one line (found by a review: the room check's stat)
    monkeypatch.setattr(staging, "free_bytes", real)
    with pytest.raises(prism_stream.errors.PrismError) as caught:
        dask_engine.sample(client, AUTZEN, str(beside / "out"), ratio=0.05, space="0.5",
                           temp_dir=str(tmp_path / "missing"))
    assert str(caught.value).startswith(f"{tmp_path / 'missing'}") and list(beside.iterdir()) == []
    bare = tmp_path / "bare.parquet"
    pq.write_table(pa.table({"a": np.zeros(10), **{c: np.zeros(10, np.uint8) for c in ("red", "green", "blue")}}),
                   bare)
    with pytest.raises(prism_stream.errors.UnsupportedFormat, match="no coordinates found"):
        dask_engine.sample(client, str(bare), str(tmp_path / "out"), ratio=0.5, space="0.5")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("reads,space", [("one", None), ("two", "0.5")])
def test_a_step_of_many_units_keeps_a_window_of_tasks(client, tiles, tmp_path, monkeypatch, reads, space):
    """A task a unit (the scans, the spatial share's scans, the selection's parts) is submitted only while fewer
    than a window of that step's tasks are unfinished: a run of 20,000 units does not hand the scheduler 20,000
    tasks at once."""
    from prism_stream.engines.dask import cluster

    monkeypatch.setattr(cluster, "IN_FLIGHT", 1)  # 2 worker threads: a window of 2
    submitted: dict = {}
    most: dict = {}
    submit = client.submit

    def counted(*args, key=None, **kw):
        f = submit(*args, key=key, **kw)
        step = key.rsplit("-", 1)[0] if key else "?"
        open_ = [g for g in submitted.get(step, []) if not g.done()] + [f]
        submitted[step] = open_
        most[step] = max(most.get(step, 0), len(open_))
        return f

    monkeypatch.setattr(client, "submit", counted)
    inputs = [str(tiles / "*.las")]
    extra = {} if space is None else {"space": space}
    summary = dask_engine.sample(client, inputs, str(tmp_path / "out"), ratio=0.03, unit_size=15_000, reads=reads,
                                 **extra)
    parts = sorted(str(tmp_path / "out" / n) for n in os.listdir(tmp_path / "out"))
    assert summary.outputs == parts and all(p.endswith(".parquet") for p in parts)  # every part written
    units = {s: len(v) for s, v in submitted.items()}
    per_unit = [s for s in most if s.startswith(("prism-select-", "prism-scan", "prism-space-"))]
    assert any(s.startswith("prism-select-") for s in per_unit), most
    for step in per_unit:
        assert most[step] <= 2, (step, most[step], units)


def test_one_las_per_tile(client, tiles, tmp_path):
    inputs = [str(tiles / "*.las")]
    prism_stream.sample(inputs, str(tmp_path / "local.las"), ratio=0.04)
    local = laspy.read(tmp_path / "local.las").points.array
    summary = dask_engine.sample(client, inputs, str(tmp_path / "out" / "*.laz"), ratio=0.04, unit_size=6_000)
    names = sorted(os.listdir(tmp_path / "out"))
    assert names == ["a.laz", "b.laz", "c.laz", "d.laz"]
    assert summary.outputs == [str(tmp_path / "out" / n) for n in names]  # every file written, as a local run's
    parts = [laspy.read(tmp_path / "out" / n) for n in names]
    assert np.concatenate([p.points.array for p in parts]).tobytes() == local.tobytes()
    assert sum(len(p.points) for p in parts) == summary.kept
    crs_vlrs = [(v.user_id, v.record_id) for v in laspy.read(AUTZEN).header.vlrs]
    assert [(v.user_id, v.record_id) for v in parts[3].header.vlrs][:len(crs_vlrs)] == crs_vlrs


def test_one_copc_per_tile(client, tiles, tmp_path):
    inputs = [str(tiles / "*.las")]
    prism_stream.sample(inputs, str(tmp_path / "local.las"), ratio=0.04)
    local = laspy.read(tmp_path / "local.las")
    dask_engine.sample(client, inputs, str(tmp_path / "out" / "*.copc.laz"), ratio=0.04, unit_size=6_000)
    names = sorted(os.listdir(tmp_path / "out"))
    assert names == ["a.copc.laz", "b.copc.laz", "c.copc.laz", "d.copc.laz"]
    got = []
    for n in names:
        with laspy.CopcReader.open(str(tmp_path / "out" / n)) as r:
            got.append(r.query())
    rows = np.concatenate([np.stack([p.X, p.Y, p.Z, p.red, p.green, p.blue], axis=1) for p in got])
    want = np.stack([local.X, local.Y, local.Z, local.red, local.green, local.blue], axis=1)
    assert np.array_equal(rows[np.lexsort(rows.T[::-1])], want[np.lexsort(want.T[::-1])])


def test_a_tiles_notes_are_in_the_summary_as_the_local_runs_are(client, tmp_path):
    """What a tile's writer changed or left out (here: a WKT CRS record pyproj cannot read) is warned once the
    tile is published and listed in the summary's warnings, as the local run lists its outputs' notes."""
    warsaw = real_file("pdal__warsaw_small.las")
    (tmp_path / "local").mkdir()
    with pytest.warns(prism_stream.PrismWarning) as local_warned:
        local = prism_stream.sample([str(warsaw)], str(tmp_path / "local" / "*.las"), count=100)
    with pytest.warns(prism_stream.PrismWarning) as dask_warned:
        summary = dask_engine.sample(client, [str(warsaw)], str(tmp_path / "out" / "*.las"), count=100)
    note = [w for w in summary.warnings if "WKT record is not a CRS" in w]
    assert len(note) == 1 and note[0].startswith(str(tmp_path / "out" / warsaw.name) + ": ")
    # the same words after the same tile's name
    assert [w for w in local.warnings if "WKT record" in w] == [note[0].replace(str(tmp_path / "out"),
                                                                               str(tmp_path / "local"))]
    assert note[0] in [str(w.message) for w in dask_warned] and local_warned


def _logged_reads(monkeypatch, log):
    """Log every chunk iterator a unit opens: (file, first record, what it decodes)."""
    from prism_stream.formats.base import Unit

    for name in ("point_chunks", "color_chunks"):
        real = getattr(Unit, name)

        def logged(self, chunk_size, real=real, name=name):
            with open(log, "a") as f:  # a file: a task may run a serialized copy of this function
                f.write(f"{os.path.basename(self.source.path)} {self.start} {name}\n")
            return real(self, chunk_size)

        monkeypatch.setattr(Unit, name, logged)


def test_each_unit_is_read_once(tiles, tmp_path, monkeypatch):
    """Pass one spills each unit's candidates; the cutoffs and pass two read the spills. Every unit is
    decoded once, except c.las's (8-bit for 20,000 points, then a 16-bit value): its units that saw no
    value above 255, and the one that saw it after its first points, spilled nothing for the 16-bit
    outcome, so they are read again, and the summary says so. The staging folder holds no spill after."""
    log = tmp_path / "reads.txt"
    _logged_reads(monkeypatch, log)
    inputs = [str(tiles / "*.las")]
    expected = local_rows(inputs, tmp_path / "local.parquet", ratio=0.01)
    log.unlink()
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as c:
        summary = dask_engine.sample(c, inputs, str(tmp_path / "out"), ratio=0.01, unit_size=6_000)
        reads = sorted(tuple(line.split()) for line in log.read_text().splitlines())
        assert dask_engine.read_dataset(str(tmp_path / "out")).equals(expected)
        # c.las: 25,000 points in units of 6,000, a 16-bit value at 20,000: the unit holding it sees it in its
        # first chunk (a whole unit here), the 4 others see none
        c_units = 4
        assert summary.plan["reads"] == 2 and summary.plan["units_read_again"] == c_units
        assert summary.plan["why"] == (f"{c_units} of {summary.plan['dask']['units']} units saw no color value "
                                       "above 255 (or saw one only after their first points) in a file proved "
                                       "16-bit: those points move to bin 0, and the units are read again")
        # units of 6,000 points and T = 2,100: the bound is weak, but some points are ruled out
        assert 0 < summary.plan["spill_points"] < summary.points
        units = summary.plan["dask"]["units"]
        per_unit: dict = {}
        for name, start, kind in reads:
            per_unit.setdefault((name, int(start)), []).append(kind)
        assert len(per_unit) == units
        again = {u: k for u, k in per_unit.items() if len(k) > 1}
        assert sorted(again) == [("c.las", s) for s in (0, 6_000, 12_000, 24_000)]
        for kinds in again.values():  # pass one; the cutoffs (colors) and pass two, from the file
            assert sorted(kinds) == ["color_chunks", "point_chunks", "point_chunks"]
        assert all(k == ["point_chunks"] for u, k in per_unit.items() if u not in again)
        assert sorted(os.listdir(tmp_path)) == sorted(["local.parquet", "out", "reads.txt"])
        assert all(n.startswith("part-") for n in os.listdir(tmp_path / "out"))  # no spill left in the output

        log.unlink()
        again = dask_engine.sample(c, inputs, str(tmp_path / "two"), ratio=0.01, unit_size=6_000, reads="two")
        assert again.plan["reads"] == 2 and again.plan["why"] == "--reads two"
        assert dask_engine.read_dataset(str(tmp_path / "two")).equals(expected)
        reads = [tuple(line.split()) for line in log.read_text().splitlines()]
        assert len(reads) == 3 * units  # pass one, the cutoffs, pass two


def test_units_start_with_the_counts_of_the_units_done(parquet_input, tiles, tmp_path):
    """One thread: each unit starts after the one before it is done. A uint8 Parquet file's units are final
    at once, so every unit but the first starts with a prior; a LAS file whose 16-bit fields hold 8-bit
    values (a.las) may yet prove 16-bit, so its units wait for the whole file and get none."""
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as c:
        for path, expect_prior in ((parquet_input, True), (tiles / "a.las", False)):
            out = tmp_path / f"out-{path.stem}"
            expected = local_rows(str(path), tmp_path / f"{path.stem}.parquet", ratio=0.05)
            summary = dask_engine.sample(c, str(path), str(out), ratio=0.05, unit_size=6_000, reads="one")
            stats = summary.plan["dask"]
            assert stats["units"] > 3
            assert stats["units_with_prior"] == (stats["units"] - 1 if expect_prior else 0)
            if expect_prior:  # a merge only once the units done since the last add a share of the prior's points
                growth = 1 + dask_driver.PRIOR_GROWTH
                assert 1 <= stats["prior_merges"] <= 2 + math.log(stats["units"]) / math.log(growth)
                assert stats["prior_merges"] < stats["units"] - 1
            assert dask_engine.read_dataset(str(out)).equals(expected)


def test_the_units_share_the_spill_budget_by_need_not_by_points(client, tmp_path, monkeypatch):
    """The staging disk leaves four times the forecast's bound for the spill, more than the units spill
    together, but the first wave (no prior) spills most of its points. Each unit starts with an equal part
    of the budget not yet spoken for, so none runs out and the input is read once; a part by points (the
    budget x the unit's points / N, before) was smaller than every unit's spill here, and all 20 were read
    again. The units never take more than the budget together."""
    import dataclasses

    folder = tmp_path / "in"
    folder.mkdir()
    for i in range(2):
        write_tile(folder / f"t{i}.las", 40_000, 20 + i)
    inputs = [str(folder / "*.las")]
    expected = local_rows(inputs, tmp_path / "local.parquet", ratio=0.01)
    room = 4  # the units' spills add up to 3-4 times the bound here: 80,000 points, 4,000 a first-wave unit
    real = dask_driver.forecast
    budgets = []

    def just_the_bound(*args, **kwargs):
        temp = real(*args, **kwargs)
        temp = dataclasses.replace(temp, free=room * temp.spill_bytes_bound + temp.output_bytes + temp.rank_bytes
                                   + tempspace.RESERVE)
        budgets.append(temp.budget)
        return temp

    monkeypatch.setattr(dask_driver, "forecast", just_the_bound)
    summary = dask_engine.sample(client, inputs, str(tmp_path / "out"), ratio=0.01, unit_size=4_000)
    assert dask_engine.read_dataset(str(tmp_path / "out")).equals(expected)
    stats = summary.plan["dask"]
    assert summary.plan["reads"] == 1, summary.plan.get("why")
    assert stats["units"] == 20 and 0 < summary.plan["spill_bytes"] <= budgets[0]


def test_a_unit_out_of_spill_space_is_read_again(tiles, tmp_path, monkeypatch):
    """A unit whose spill meets a full disk (ENOSPC) drops it and is read again: same rows, reported."""
    import errno

    from prism_stream.run.spill import Spill

    real = Spill.add
    calls = []

    def full(self, chunk, keys, mask, first_id, candidates=None):
        calls.append(1)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, chunk, keys, mask, first_id, candidates)

    inputs = [str(tiles / "*.las")]
    expected = local_rows(inputs, tmp_path / "local.parquet", ratio=0.05)
    monkeypatch.setattr(Spill, "add", full)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as c:
        summary = dask_engine.sample(c, inputs, str(tmp_path / "out"), ratio=0.05, unit_size=6_000)
    assert dask_engine.read_dataset(str(tmp_path / "out")).equals(expected)
    # a.las's third unit met the full disk; c.las's 4 units that saw no 16-bit value are read again too
    assert summary.plan["reads"] == 2 and summary.plan["units_read_again"] == 5
    n = summary.plan["dask"]["units"]
    assert summary.plan["why"].startswith(f"1 of {n} units ran out of temporary space for their spill; 4 of {n} "
                                          "units saw no color value above 255")
    assert sorted(os.listdir(tmp_path)) == ["local.parquet", "out"]  # the dropped spill went with the stage


def test_a_cloud_of_many_colors_reads_its_later_units_twice(tiles, tmp_path, monkeypatch):
    """Once a finished unit shows more colors than the priors fit (estimated_bins > PRIOR_BINS), no prior is
    made and the units not started read twice: same rows as the local engine, said in the summary."""
    inputs = [str(tiles / "*.las")]
    expected = local_rows(inputs, tmp_path / "local.parquet", ratio=0.05, seed=3)
    monkeypatch.setattr(dask_driver, "PRIOR_BINS", 100)
    monkeypatch.setattr(dask_driver, "PRIOR_EVIDENCE", 50)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as c:
        summary = dask_engine.sample(c, inputs, str(tmp_path / "out"), ratio=0.05, seed=3, unit_size=6_000,
                                     reads="one")
    assert dask_engine.read_dataset(str(tmp_path / "out")).equals(expected)
    n = summary.plan["dask"]["units"]
    assert summary.plan["units_read_again"] == n - 1  # the first unit alone spilled; then one at a time, rereads
    assert f"{n - 1} of {n} units were read twice: the cloud has more colors" in summary.plan["why"]
    assert summary.plan["dask"]["prior_merges"] == 0 and summary.plan["dask"]["bins_estimated"] > 100


def test_the_bins_estimate():
    est = dask_driver.estimated_bins
    assert est(3_850_000, 19_492) == pytest.approx(19_492, rel=1e-6)  # few colors: what a unit shows
    assert est(3_850_000, 3_400_000) == pytest.approx(15.16e6, rel=0.01)  # 2^24 keys: about 15.9M bins
    b, p = 50_000, 80_000  # B equal bins show B (1 - exp(-p / B)) in p draws: the estimate inverts it
    assert est(p, round(b * -np.expm1(-p / b))) == pytest.approx(b, rel=1e-4)
    assert est(100, 100) == float("inf") and est(0, 0) == 0


class KillFirstSelect(distributed.WorkerPlugin):
    """Kills the worker process the first time any worker starts a pass-two task."""

    def __init__(self, marker):
        self.marker = marker

    def transition(self, key, start, finish, **kw):
        if finish == "executing" and "prism-select" in str(key):
            try:
                fd = os.open(self.marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                return
            os.close(fd)
            os.kill(os.getpid(), signal.SIGKILL)


def test_worker_killed_in_pass_two(client, tiles, tmp_path):
    import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    inputs = [str(tiles / "*.las")]
    expected = local_rows(inputs, tmp_path / "local.parquet", ratio=0.05)
    marker = tmp_path / "killed"
    client.register_plugin(KillFirstSelect(str(marker)), name="kill-first-select")
    try:
        dask_engine.sample(client, inputs, str(tmp_path / "out"), ratio=0.05, unit_size=5_000)
    finally:
        client.unregister_worker_plugin("kill-first-select")
    assert marker.exists()
    assert dask_engine.read_dataset(str(tmp_path / "out")).equals(expected)
    assert not [n for n in os.listdir(tmp_path / "out") if not n.startswith("part-")]
    assert not glob.glob(str(tmp_path / ".out.*"))
    client.wait_for_workers(2, timeout=60)


def test_workers_far_smaller_than_input(tmp_path, monkeypatch):
    """A 10M-point tile (260 MB of records, ~530 MB as Arrow) on 700 MB workers, which pause at
    560 MB and hold ~380 MB before any data: only a streaming engine fits. No restart; what dask spills
    is at most the unit histograms, never the tile. At 1 quantization bit, as docs/CLUSTER.md advises for
    workers under 1 GB: a pass-one task's candidate filter holds a table over the key space, 128 MiB at 0
    bits (16 MiB at 1), which with the 380 MB baseline passes dask's 70% spill mark on a 700 MB worker."""
    path = tmp_path / "big.las"
    write_tile(path, 10_000_000, 9, fmt=2)
    monkeypatch.setattr(dask_engine.cluster, "STALL_SECONDS", 30.0)  # a paused cluster fails fast instead of hanging
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, memory_limit="700MB",
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as small:
        small.wait_for_workers(2, timeout=60)
        before = set(small.scheduler_info()["workers"])
        summary = dask_engine.sample(small, str(path), str(tmp_path / "out"), ratio=0.01, unit_size=1 << 20,
                                     chunk_size=1 << 18, quant_bits=1)
        assert set(small.scheduler_info()["workers"]) == before  # no worker died and came back
        # every byte dask wrote to disk during the run (its cumulative spill metric). Its spill starts when a
        # worker process passes 70% (490 MB), which a worker at ~380 MB idle reaches when the driver is slow
        # to merge (another test process loading the machine): then it spills unit histograms, at most
        # ~12 MB each for these 1M-point units (99 MB seen in CI). An engine holding the tile would spill
        # it (260 MB of records, 530 MB as Arrow) or be killed at 95%
        spilled = small.run(lambda dask_worker: dask_worker.data.cumulative_metrics[("disk-write", "bytes")])
        assert sum(spilled.values()) < 200 << 20, spilled
    assert summary.plan["reads"] == 1  # the units' spills are on disk, in the staging folder
    assert pq.ParquetDataset(str(tmp_path / "out")).read().num_rows == summary.kept == 100_000


def test_a_cluster_paused_at_its_memory_limit_fails_instead_of_hanging(tmp_path, monkeypatch):
    import dask

    monkeypatch.setattr(dask_engine.cluster, "STALL_SECONDS", 2.0)
    # pause at 20% of 1 GB: below what a worker holds before any data, so it is paused from the start (a worker
    # in this process, whose memory the monitor reads: the pause is the point, not a process's start-up)
    with dask.config.set({"distributed.worker.memory.pause": 0.2, "distributed.worker.memory.terminate": False}), \
            distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, memory_limit="1GB",
                                     dashboard_address=None) as cluster, distributed.Client(cluster) as tiny:
        with pytest.raises(dask_engine.ClusterError, match="paused"):
            dask_engine.sample(tiny, AUTZEN, str(tmp_path / "out"), ratio=0.01)
    assert not (tmp_path / "out").exists()


def test_errors_name_the_file_and_leave_nothing(client, tiles, tmp_path):
    bad = tmp_path / "nulls.parquet"
    pq.write_table(pa.table({"red": pa.array([1, None, 3], pa.uint8()), "green": pa.array([1, 2, 3], pa.uint8()),
                             "blue": pa.array([1, 2, 3], pa.uint8())}), bad)
    with pytest.raises(CorruptInput, match=f"{bad}: column 'red' has 1 points with no color"):
        dask_engine.sample(client, str(bad), str(tmp_path / "out"), ratio=0.5)
    assert os.listdir(tmp_path) == ["nulls.parquet"]
    (tmp_path / "taken").mkdir()
    with pytest.raises(OutputExists):
        dask_engine.sample(client, str(tiles / "a.las"), str(tmp_path / "taken"), ratio=0.5)


def test_keep_and_drop_choose_the_parts_columns_as_the_local_run_does(client, tiles, tmp_path):
    """--drop on the cluster: the dataset's parts lack the column, every other one as the local run writes it."""
    inputs = [str(tiles / "a.las")]
    expected = local_rows(inputs, tmp_path / "local.parquet", ratio=0.1, drop=("intensity", "gps_time"))
    assert "intensity" not in expected.column_names and "red" in expected.column_names
    dask_engine.sample(client, inputs, str(tmp_path / "out"), ratio=0.1, drop=("intensity", "gps_time"))
    assert dask_engine.read_dataset(str(tmp_path / "out")).equals(expected)
    with pytest.raises(UsageError, match="--keep 'nope': the inputs have no such column"):
        dask_engine.sample(client, inputs, str(tmp_path / "out2"), ratio=0.1, keep=("nope",))
    with pytest.raises(UsageError, match="--drop 'nope': the inputs have no such column"):
        dask_engine.sample(client, inputs, str(tmp_path / "bad") + "/*.laz", ratio=0.1, drop=("nope",))
    assert sorted(os.listdir(tmp_path)) == ["local.parquet", "out"]


def test_keep_and_drop_in_tiles_as_the_local_output_folder(client, tiles, tmp_path, monkeypatch):
    """LAS tiles on the cluster: the same records as the local run's output folder (gps_time written as 0, said
    for each tile after the commit, as the local run says it)."""
    import warnings

    inputs = [str(tiles / "a.las"), str(tiles / "d.las")]
    with warnings.catch_warnings(record=True) as local_warned:
        warnings.simplefilter("always")
        prism_stream.sample(inputs, str(tmp_path / "local") + "/", ratio=0.1, drop=("gps_time",), output_format="laz")
    with warnings.catch_warnings(record=True) as dask_warned:
        warnings.simplefilter("always")
        dask_engine.sample(client, inputs, str(tmp_path / "out") + "/*.laz", ratio=0.1, drop=("gps_time",))
    for name in ("a.laz", "d.laz"):
        got, want = laspy.read(tmp_path / "out" / name), laspy.read(tmp_path / "local" / name)
        assert got.points.array.tobytes() == want.points.array.tobytes() and not np.any(got.gps_time)
    said = "--drop: gps_time written as 0 in every record"
    assert sum(said in str(w.message) for w in local_warned) == sum(said in str(w.message) for w in dask_warned) == 2
    # what a tile's writer refuses is refused before pass one, as the local run refuses it
    monkeypatch.setattr(dask_engine.driver, "unit_refs", lambda *a, **k: pytest.fail("pass one started"))
    with pytest.raises(UsageError, match="--drop 'return_number': a LAS output keeps it"):
        dask_engine.sample(client, inputs, str(tmp_path / "bad") + "/*.laz", ratio=0.1, drop=("return_number",))


def test_cli_dask_option(client, tiles, tmp_path):
    address = client.scheduler.address
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "prism_stream_cli.main", str(tiles / "a.las"), str(out), "--ratio", "0.1",
           "--dask", address, "--quiet"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    expected = local_rows([str(tiles / "a.las")], tmp_path / "local.parquet", ratio=0.1)
    assert dask_engine.read_dataset(str(out)).equals(expected)
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert again.returncode == 7 and again.stderr.count("\n") == 1 and "already exists" in again.stderr


def test_values_held_on_purpose_in_the_graph_raise_no_advice(client):
    """:func:`cluster.held` (and the plan's rules' parts) put a value in the task graph so that the scheduler can
    rebuild it; past 10 MB Dask advises scattering it instead, which the command line printed as a warning the user can
    do nothing about (over 2^24 bins: twice). The value still comes back whole."""
    import warnings

    from prism_stream.engines.dask import cluster

    value = np.arange(3 << 20, dtype=np.int64)  # 24 MiB
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        future = cluster.held(client, value, "prism-test-held-large")
    assert not [w for w in seen if "large graph" in str(w.message)]
    assert np.array_equal(future.result(), value)
    with warnings.catch_warnings(record=True) as seen:  # the advice itself is Dask's, not silenced for others
        warnings.simplefilter("always")
        client.submit(len, value, key="prism-test-not-held", pure=False).result()
    assert [w for w in seen if "large graph" in str(w.message)]


# -- ranks -------------------------------------------------------------------------------------

@pytest.mark.parametrize("options", [dict(seed=4), dict(count=3_000, seed=9, quant_bits=1)])
def test_ranks_are_the_local_engines(client, tiles, tmp_path, options):
    """Units rank nothing themselves: their kept points are ranked on the driver, the same ranks as locally."""
    inputs = [str(tiles / "*.las")]
    expected = local_rows(inputs, tmp_path / "local.parquet", rank="prism_rank", **options)
    summary = dask_engine.sample(client, inputs, str(tmp_path / "out"), unit_size=15_000, chunk_size=2_000,
                                 rank="prism_rank", **options)
    got = dask_engine.read_dataset(str(tmp_path / "out"))
    assert got.equals(expected)
    assert summary.plan["rank"]["column"] == "prism_rank"
    tiles_out = tmp_path / "tiles"
    dask_engine.sample(client, inputs, str(tiles_out / "*.laz"), unit_size=15_000, rank="prism_rank", **options)
    ranks = np.concatenate([np.asarray(laspy.read(tiles_out / f"{t}.laz")["prism_rank"]) for t in "abcd"])
    assert np.array_equal(ranks, expected.column("prism_rank").to_numpy())


def test_rank_order_is_refused_on_the_cluster(client, tiles, tmp_path):
    with pytest.raises(prism_stream.PrismError, match="--order rank is not available with --dask"):
        dask_engine.sample(client, [str(tiles / "a.las")], str(tmp_path / "out"), rank="prism_rank", order="rank")
    assert not os.path.exists(tmp_path / "out")


def test_the_commit_drops_what_killed_tasks_left(tmp_path):
    """A task killed mid-write leaves its hidden temporary file in the staging folder: never published."""
    from prism_stream.engines.dask import driver
    from prism_stream.run import staging

    stage = tmp_path / "stage"
    stage.mkdir()
    pq.write_table(pa.table({"x": [1.0]}), stage / "part-000000-0000000000000.parquet")
    (stage / f".part-000000-0000000005000.parquet.1234{staging.SUFFIX}").write_bytes(b"half a part")
    (stage / "notes.txt").write_text("not a leftover: kept")
    driver._commit(str(stage), str(tmp_path / "out"), None, None)
    assert sorted(os.listdir(tmp_path / "out")) == ["notes.txt", "part-000000-0000000000000.parquet"]
    assert not stage.exists()


def test_the_commit_of_nothing_is_one_empty_part_with_the_schema(tmp_path):
    from prism_stream.engines.dask import driver

    stage = tmp_path / "stage"
    stage.mkdir()
    schema = pa.schema([("x", pa.float64()), ("red", pa.uint8())])
    driver._commit(str(stage), str(tmp_path / "out"), None, schema)
    assert os.listdir(tmp_path / "out") == ["part-000000-0000000000000.parquet"]
    empty = pq.read_table(tmp_path / "out" / "part-000000-0000000000000.parquet")
    assert empty.num_rows == 0 and empty.schema.equals(schema)


def test_a_commit_that_cannot_rename_puts_the_old_output_back(tmp_path, monkeypatch):
    from prism_stream.engines.dask import driver
    from prism_stream.errors import OutputError

    stage, out = tmp_path / "stage", tmp_path / "out"
    stage.mkdir()
    out.mkdir()
    (out / "old.txt").write_text("the previous run's output")
    pq.write_table(pa.table({"x": [1.0]}), stage / "part-000000-0000000000000.parquet")
    rename = os.rename

    def refuse_the_stage(src, dst):
        if os.fspath(src) == str(stage):
            raise PermissionError(13, "Permission denied")
        return rename(src, dst)

    monkeypatch.setattr(driver.os, "rename", refuse_the_stage)
    with pytest.raises(OutputError, match="cannot commit the output"):
        driver._commit(str(stage), str(out), None, None, overwrite=True)
    assert os.listdir(out) == ["old.txt"]
    assert not [p for p in os.listdir(tmp_path) if p not in ("stage", "out")], os.listdir(tmp_path)


def test_a_failed_input_beside_the_output_keeps_its_own_name(tmp_path):
    """A pass-two task that cannot read an input lying beside the output (the staging folder's folder) was
    reported as OUTPUT/input.parquet, a path that does not exist; a part it failed to write still is named in
    the output folder."""
    from prism_stream.errors import CorruptInput

    folder = str(tmp_path / "out.parquet")
    stage = str(tmp_path / ".out.parquet.host-1-abcd.prism-tmp")
    src = str(tmp_path / "garbled.parquet")
    read = CorruptInput("cannot read the file", src)
    dask_driver._named_in_output(read, stage, folder, [src])
    assert read.path == src
    part = CorruptInput("disk full", os.path.join(stage, "part-000001.parquet"))
    dask_driver._named_in_output(part, stage, folder, [src])
    assert part.path == os.path.join(folder, "part-000001.parquet")
