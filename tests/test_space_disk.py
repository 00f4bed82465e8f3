"""The spatial scan with its points on disk (``engines/spatial_disk.py``): the in-memory scan's order, and the
oracle's, for any cap on the cells held, any file size loaded whole and any fan-out of the routing.

Small caps and files send small clouds down every path a large target takes: the top scan alone (its level
already has T cells), one routing into files loaded whole, and files too large to load, scanned again and
routed again (by cells of a finer level, or of the same level by another hash)."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import oracle
from prism_stream.core import space
from prism_stream.core.kernels import priorities_of_np, seed_mix
from prism_stream.engines.spatial_disk import DiskScan
from prism_stream.run import staging
from test_space import clouds


class _Rarity:
    """Each point's rarity by its bin key (the key here is the point's index)."""

    def __init__(self, rarity):
        self.rarity = rarity

    def of(self, keys):
        return self.rarity[np.asarray(keys, np.int64)]


def _disk_order(folder, xyz, rarity, ids, seed, t, chunk, cap, leaf, fan, sort=None, limit=None):
    scan = DiskScan(t, str(folder), _Rarity(rarity), seed_mix(seed), cap, leaf=leaf, fan=fan)
    if sort is not None:  # the listed births sorted ``sort[0]`` at a time, merged ``sort[1]`` a run at a time
        scan.sort_run, scan.sort_block = sort
    keys = np.arange(len(ids), dtype=np.uint32)
    for a in range(0, len(ids), chunk):
        scan.add(xyz[a:a + chunk], keys[a:a + chunk], ids[a:a + chunk])
    return scan.order(seed, limit), scan


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                   HealthCheck.function_scoped_fixture])
@given(cloud=clouds(), chunk=st.sampled_from([7, 100, 1 << 20]), cap=st.integers(8, 40),
       leaf=st.integers(1, 120), fan=st.integers(2, 5),
       sort=st.tuples(st.integers(1, 30), st.integers(1, 9)) | st.none(), limit=st.integers(0, 50) | st.none())
def test_the_order_on_disk_is_the_oracles(tmp_path, cloud, chunk, cap, leaf, fan, sort, limit):
    xyz, rarity, ids, seed, t = cloud
    folder = tmp_path / f"run{len(os.listdir(tmp_path))}"
    folder.mkdir()
    want = ids[oracle.spatial_order(xyz, rarity, oracle.priority(ids, seed), t, seed)]
    got, _ = _disk_order(folder, xyz, rarity, ids, seed, t, chunk, cap, leaf, fan, sort, limit)
    assert np.array_equal(got, want if limit is None else want[:limit])
    assert os.listdir(folder) == []  # every file it wrote is gone


def _parts_order(folder, cloud, parts, run_tasks, leaf, fan, limit=None):
    """:func:`..spatial_disk.order_in_parts` as a Dask run does it: the points in ``parts`` consecutive parts,
    each scanned (at most ``cap`` cells) with its points in a file of ``folder``/parts, the scans folded, the
    files' work run by ``run_tasks``; the driver's files in ``folder``/driver. Returns the order's ids."""
    from prism_stream.engines import spatial_disk
    from prism_stream.run.staging import ArrayFile

    xyz, rarity, ids, seed, t, cap = cloud
    work, driver = folder / "parts", folder / "driver"
    work.mkdir()
    driver.mkdir()
    keys = np.arange(len(ids), dtype=np.uint32)
    folded, paths = space.SpatialScan(t, cap=cap), []
    for i, at in enumerate(np.array_split(np.arange(len(ids)), parts)):
        paths.append(str(work / f"points-{i:06d}"))
        part = DiskScan.part(t, paths[-1], _Rarity(rarity), seed_mix(seed), cap)
        for a in range(0, len(at), 7):
            part.add(xyz[at[a:a + 7]], keys[at[a:a + 7]], ids[at[a:a + 7]])
        spatial_disk.write_part(part)
        folded.absorb(part.mem.settled())
    disk = DiskScan.of_parts(folded, paths, str(driver), _Rarity(rarity), seed_mix(seed), cap)
    disk.leaf, disk.fan = leaf, fan
    into = ArrayFile(str(driver), "order", np.uint64)
    spatial_disk.order_in_parts(disk, seed, limit, into, run_tasks)
    out = into.read(0, into.size).copy()
    into.discard()
    return out, disk


def _in_order(fn, jobs):
    return [fn(*args) for args in jobs]


def _backwards_twice(fn, jobs):
    """Every task run twice, the last first (a worker lost after a task: it runs again; any order)."""
    for args in reversed(jobs):
        fn(*args)
    return [fn(*args) for args in jobs]


@settings(max_examples=35, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(cloud=clouds(), cap=st.integers(8, 40), leaf=st.integers(1, 120), fan=st.integers(2, 5),
       parts=st.integers(1, 4), sort=st.integers(1, 30), again=st.booleans(), limit=st.integers(0, 50) | st.none())
def test_the_order_in_parts_is_the_oracles(tmp_path, monkeypatch, cloud, cap, leaf, fan, parts, sort, again, limit):
    """The order of a Dask run's scan on disk (the parts' files routed, visited and listed by tasks, merged on
    the driver) is the oracle's, for any number of parts, any order of the tasks and a task run twice; once
    done, neither the parts' files nor the driver's are left (only a twice-run task's first outputs, which
    the run removes with the staging folder)."""
    from prism_stream.engines import spatial_disk

    monkeypatch.setattr(spatial_disk, "SORT_RUN", sort)  # the tasks' listed births in runs of ``sort``
    xyz, rarity, ids, seed, t = cloud
    folder = tmp_path / f"run{len(os.listdir(tmp_path))}"
    folder.mkdir()
    want = ids[oracle.spatial_order(xyz, rarity, oracle.priority(ids, seed), t, seed)]
    got, _ = _parts_order(folder, (xyz, rarity, ids, seed, t, cap), parts, _backwards_twice if again else _in_order,
                          leaf, fan, limit)
    assert np.array_equal(got, want if limit is None else want[:limit])
    assert os.listdir(folder / "driver") == []
    if not again:
        assert [p for p in (folder / "parts").rglob("*") if p.is_file()] == []
    # no file is still watched as this process's (a task's files go to the driver; found by the suite: a later
    # run in the same process took a removed run file for its own temporary data changed)
    assert not [p for p in staging._MARKS if p.startswith(str(folder))]


@pytest.mark.parametrize("t", [3_000, 20_000])
def test_a_large_cloud_in_parts_is_the_in_memory_order(tmp_path, monkeypatch, t):
    """Routed twice, rescanned and counted again (as the whole-file test below), in 5 parts."""
    from prism_stream.engines import spatial_disk

    monkeypatch.setattr(spatial_disk, "SORT_RUN", 1_000)
    peak = [0]

    class Measured(spatial_disk.ArrayFile):  # every file's bytes (the parts', the tasks', the driver's)
        def _written(self):
            super()._written()
            peak[0] = max(peak[0], sum(f.stat().st_size for f in tmp_path.rglob("*") if f.is_file()))

    monkeypatch.setattr(spatial_disk, "ArrayFile", Measured)
    xyz, rarity, ids = _city(60_000)
    mem = space.SpatialScan(t)
    mem.add(xyz, rarity, priorities_of_np(ids, seed_mix(11)), ids)
    got, disk = _parts_order(tmp_path, (xyz, rarity, ids, 11, t, 256), 5, _in_order, 2_000, 4)
    assert np.array_equal(got, mem.order(11))
    assert disk.routed > len(ids) and disk.written == len(ids)
    # the parts' files and their routed pieces at once, within what the forecast counts (the order's ids: 8 a point)
    assert 2 * 36 * len(ids) <= peak[0] <= space.disk_bytes(len(ids), t) + 8 * t


def _city(n, seed=3):
    """Streets of points 1 cm apart, a few dense blobs and far outliers: many levels between the cells a
    small cap tracks and the first level with T cells."""
    rng = np.random.default_rng(seed)
    parts = [np.round(rng.uniform(0, 200, (n // 2, 3)) * [1, 1, 0.05], 2),
             rng.normal(50, 0.01, (n // 4, 3)), rng.normal(-3000, 1e-4, (n // 8, 3)),
             rng.uniform(-1e6, 1e6, (n - n // 2 - n // 4 - n // 8, 3))]
    xyz = np.concatenate(parts)[rng.permutation(n)] + [500_000.0, 4_000_000.0, 0.0]
    return xyz, rng.integers(1, 50, n).astype(np.uint64), np.arange(n, dtype=np.uint64)


@pytest.mark.parametrize("t", [5, 3_000, 20_000])
def test_a_large_cloud_routed_twice_is_the_in_memory_order(tmp_path, t):
    xyz, rarity, ids = _city(60_000)
    prio = priorities_of_np(ids, seed_mix(11))
    mem = space.SpatialScan(t)
    mem.add(xyz, rarity, prio, ids)
    want = mem.order(11)
    got, scan = _disk_order(tmp_path, xyz, rarity, ids, 11, t, 10_000, cap=256, leaf=2_000, fan=4,
                            sort=(1_000, 100))
    assert np.array_equal(got, want)
    if t > 256:  # the listed births (at least T) were sorted in runs of 1,000 on disk and merged
        assert scan.sorted >= t and scan.sort_runs == -(-scan.sorted // 1_000) >= 3  # the last one part-full
    if t > 256:  # the top scan stopped coarser than the last level: the points were routed, some again, and
        assert scan.routed > len(ids) and scan.rescanned > 0  # the blobs' files scanned on their own
    else:  # the top scan's level has T cells: its order is the whole order
        assert scan.routed == 0
    if t == 20_000:  # the last level below some files' first count: those counted again
        assert scan.recounted > 0
    assert os.listdir(tmp_path) == []


def test_points_apart_only_far_below_the_extent_are_counted_again_exactly(tmp_path):
    """A file is first counted from the finest level its codes fit one word at: about 2^-21 of its extent a
    axis. Points a millionth apart beside points a million apart merge there; with T near N the last level
    is below it, and those files are counted again from the last possible level."""
    rng = np.random.default_rng(5)
    far = rng.uniform(-1e6, 1e6, (300, 3))
    near = 1e-6 * rng.integers(0, 1000, (3_000, 3))
    xyz = np.concatenate([far, near])[rng.permutation(3_300)]
    rarity = rng.integers(1, 9, 3_300).astype(np.uint64)
    ids = np.arange(3_300, dtype=np.uint64)
    t = 3_000
    want = ids[oracle.spatial_order(xyz, rarity, oracle.priority(ids, 2), t, 2)]
    got, scan = _disk_order(tmp_path, xyz, rarity, ids, 2, t, 1_000, cap=64, leaf=500, fan=3)
    assert scan.recounted > 0
    assert np.array_equal(got, want)


@pytest.mark.parametrize("reads,held", [("auto", False), ("two", False), ("auto", True)])
def test_a_run_whose_cells_do_not_fit_is_the_oracles_sample(reads, held, monkeypatch, tmp_path):
    """The whole run, its scan sent to disk by a budget of nothing (and a few cells, small files): the
    oracle's sample, the points said in the summary, and nothing left in the temporary folder."""
    from conftest import real_file
    from prism_stream import sample
    from prism_stream.engines import spatial, spatial_disk
    from test_space import AUTZEN, _cloud, _xyz_rows

    xyz, rgb = _cloud(real_file(AUTZEN))
    # held: the input in memory (its ids kept by a mask: found by a review, the ids in a file kept none)
    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", str(1 << 20) if held else "0")
    monkeypatch.setattr(space, "MEMORY_BUDGET", 0)
    monkeypatch.setattr(spatial, "CAP", 300)
    monkeypatch.setattr(spatial_disk, "LEAF", 4_000)
    monkeypatch.setattr(spatial_disk, "FAN", 5)
    temp = tmp_path / "temp"
    temp.mkdir()
    peak = [0]

    class Measured(spatial_disk.ArrayFile):  # the scan's files' bytes on disk, after each write
        def _written(self):
            super()._written()
            used = sum(f.stat().st_size for f in temp.rglob("space.*"))
            peak[0] = max(peak[0], used)

    monkeypatch.setattr(spatial_disk, "ArrayFile", Measured)
    monkeypatch.setattr(spatial_disk, "SORT_RUN", 500)  # the order's births sorted in runs on disk, merged
    out = tmp_path / "out.parquet"
    s = sample(str(real_file(AUTZEN)), str(out), ratio=0.05, space="0.5", reads=reads, chunk_size=7_000,
               temp_dir=str(temp))
    kept = oracle.space_sample([rgb], [xyz], space="0.5", ratio=0.05)[0]
    assert s.kept == len(kept) == 5_500
    assert np.array_equal(_xyz_rows(out), xyz[kept])
    assert s.plan["space"]["points_on_disk"] == len(xyz) and s.plan["space"]["points_routed"] >= len(xyz)
    if not held:  # (a held input forecasts no temporary files: its scan's room is checked before the read)
        assert s.plan["temp"]["space_bytes"] == space.disk_bytes(len(xyz))  # forecast before pass one
    assert 2 * 36 * len(xyz) <= peak[0] <= space.disk_bytes(len(xyz))  # the points and their routed copy
    assert list(temp.iterdir()) == []


def test_a_share_whose_points_would_not_fit_the_temporary_folder_is_refused_before_pass_one(capsys, monkeypatch,
                                                                                           tmp_path):
    from conftest import cli, real_file
    from prism_stream.engines import reads
    from prism_stream.run import tempspace
    from test_space import AUTZEN

    def no_pass_one(*a, **k):
        raise AssertionError("pass one ran")

    n = 110_000
    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", "0")
    monkeypatch.setattr(reads, "scan", no_pass_one)
    monkeypatch.setattr(space, "MEMORY_BUDGET", 0)
    # room for the key cache and the output, and half the spatial share's points
    monkeypatch.setattr(tempspace, "free_bytes",
                        lambda folder: tempspace.RESERVE + 4 * n + 10**6 + space.disk_bytes(n) // 2)
    out = tmp_path / "out.parquet"
    code, _, err = cli(capsys, str(real_file(AUTZEN)), str(out), "--ratio", "0.05", "--space", "0.5")
    from prism_stream.run.staging import gib

    assert code == 8 and "not enough temporary space" in err
    assert f"the spatial share's points {gib(space.disk_bytes(n))}" in err
    assert len(err.strip().splitlines()) == 1 and not out.exists()
    monkeypatch.setattr(space, "MEMORY_BUDGET", 300 << 20)  # the cells in memory: the same room is enough
    with pytest.raises(AssertionError, match="pass one ran"):
        from prism_stream import sample
        sample(str(real_file(AUTZEN)), str(out), ratio=0.05, space="0.5")


def _merge_reference(spatial, prism, a, t):
    """SPEC 9's merge as its text says it, place by place over sets."""
    taken, out, i_s, i_p, filled = set(), [], 0, 0, 0
    for place in range(t):
        if space.share(a, place + 1) > space.share(a, place):
            while i_s < len(spatial) and spatial[i_s] in taken:
                i_s += 1
            if i_s < len(spatial):
                taken.add(spatial[i_s])
                out.append(spatial[i_s])
                filled += 1
                continue
        while prism[i_p] in taken:
            i_p += 1
        taken.add(prism[i_p])
        out.append(prism[i_p])
    return out, filled


@settings(max_examples=200, deadline=None)
@given(data=st.data(), t=st.integers(0, 60), a=st.sampled_from([0, 1, 250_000, 500_000, 999_999, 1_000_000]))
def test_the_merge_is_the_specs_place_by_place(data, t, a):
    universe = data.draw(st.integers(max(t, 1), 3 * t + 2))  # ids both orders share, some only one has
    prism = data.draw(st.permutations(range(universe)))[:t]
    spatial = data.draw(st.lists(st.integers(0, universe - 1), unique=True, max_size=t + 5))
    got, filled = space.merge(np.array(spatial, np.uint64), np.array(prism, np.uint64), a, t)
    want, want_filled = _merge_reference(spatial, prism, a, t)
    assert got.tolist() == want and filled == want_filled


@pytest.mark.parametrize("fail_at, among", [(1, "space."), (40, "space."), (3, "space.sorted."), (1, "space.order"),
                                             (2, "space.prism."), (4, "space.merge.")])
def test_a_disk_that_fills_during_the_scan_is_said_and_leaves_nothing(monkeypatch, tmp_path, fail_at, among):
    """The points' file in the spatial read, a routed file later, the third run of the order's sort, the
    order's ids, PRISM's order's sorts and the merge's."""
    import errno

    from conftest import real_file
    from prism_stream import sample
    from prism_stream.engines import spatial, spatial_disk
    from prism_stream.errors import OutputError
    from test_space import AUTZEN

    writes = []

    class Filling(spatial_disk.ArrayFile):
        def append(self, values):
            if among not in os.path.basename(self.path):
                return super().append(values)
            writes.append(1)
            if len(writes) >= fail_at:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            super().append(values)

    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", "0")
    monkeypatch.setattr(space, "MEMORY_BUDGET", 0)
    monkeypatch.setattr(spatial, "CAP", 300)
    monkeypatch.setattr(spatial_disk, "LEAF", 4_000)
    monkeypatch.setattr(spatial_disk, "ArrayFile", Filling)
    monkeypatch.setattr(spatial_disk, "SORT_RUN", 500)
    respace, left = spatial.respace, []

    def watched(plan, run, *args):  # the scan's and the merge's files still there as the error leaves them
        try:
            return respace(plan, run, *args)
        except BaseException:
            left.append(sorted(f for f in os.listdir(run.tmp) if f.startswith("space.")))
            raise

    monkeypatch.setattr(spatial, "respace", watched)
    temp = tmp_path / "temp"
    temp.mkdir()
    out = tmp_path / "out.parquet"
    with pytest.raises(OutputError, match="cannot write the temporary files: No space left on device"):
        sample(str(real_file(AUTZEN)), str(out), ratio=0.05, space="0.5", chunk_size=7_000, temp_dir=str(temp))
    assert len(writes) == fail_at  # it failed where it was made to, and went no further
    if among != "space.":  # past the spatial read, each step removes its own files on an error (the run's
        assert left == [[]]  # folder goes too, which would hide it)
    assert list(temp.iterdir()) == [] and not out.exists()


def test_a_querys_scan_on_disk_is_refused_when_the_folder_has_no_room(capsys, monkeypatch, tmp_path):
    """A query's size is known after pass one only: its scan's room is checked before the spatial read."""
    from conftest import cli
    from prism_stream.run import staging

    monkeypatch.setattr(space, "MEMORY_BUDGET", 0)
    monkeypatch.setattr(staging, "free_bytes", lambda folder: staging.RESERVE + space.disk_bytes(5_000) - 1)
    out = tmp_path / "out.parquet"
    temp = tmp_path / "temp"
    temp.mkdir()
    colors = "(i % 256)::UTINYINT AS red, (i // 256 % 256)::UTINYINT AS green, 0::UTINYINT AS blue"
    code, _, err = cli(capsys, "sql", f"SELECT i::DOUBLE AS x, 0.0 AS y, 0.0 AS z, {colors} FROM range(5000) t(i)",
                       str(out), "--ratio", "0.5", "--space", "0.5", "--temp-dir", str(temp))
    assert code == 8 and "the spatial share's scan of 5,000 points writes up to" in err
    assert f"{temp}: not enough temporary space" in err  # the folder the user gave (found by a hostile test)
    assert len(err.strip().splitlines()) == 1 and not out.exists() and list(temp.iterdir()) == []
    monkeypatch.setattr(staging, "free_bytes", lambda folder: staging.RESERVE + space.disk_bytes(5_000))
    code, _, err = cli(capsys, "sql", f"SELECT i::DOUBLE AS x, 0.0 AS y, 0.0 AS z, {colors} FROM range(5000) t(i)",
                       str(out), "--ratio", "0.5", "--space", "0.5")
    assert code == 0 and out.exists()



@settings(max_examples=100, deadline=None)
@given(data=st.data(), block=st.integers(1, 9))
def test_the_id_selector_reads_a_file_of_ids_as_it_reads_the_array(tmp_path_factory, data, block):
    """A large target's kept ids stay in a file that pass two reads a block at a time: each chunk's mask is
    the array's, in the order pass two asks (and out of it)."""
    from prism_stream.core.kernels import ID_SHIFT
    from prism_stream.engines.spatial import IdSelector
    from prism_stream.run.staging import ArrayFile

    sizes = data.draw(st.lists(st.integers(0, 40), min_size=1, max_size=3))  # points of each file
    every = [(o << ID_SHIFT) | s for o, n in enumerate(sizes) for s in range(n)]
    kept = sorted(data.draw(st.sets(st.sampled_from(every), max_size=len(every))) if every else [])
    ids = np.array(kept, np.uint64)
    f = ArrayFile(str(tmp_path_factory.mktemp("ids")), "space.chosen", np.uint64)
    f.append(ids)
    on_disk = IdSelector(f)
    on_disk.BLOCK = block
    on_disk.__init__(f)  # the blocks' first ids, at this block size
    held = IdSelector(ids)
    asks = [(o, s, n) for o, size in enumerate(sizes) for s in range(0, max(size, 1), 7) for n in (7,)]
    asks += data.draw(st.lists(st.tuples(st.integers(0, len(sizes)), st.integers(0, 45), st.integers(0, 12)),
                               max_size=6))
    for o, s, n in asks:
        keys = np.zeros(n, np.uint32)
        assert np.array_equal(on_disk.mask(keys, o, s), held.mask(keys, o, s))
    f.discard()


@pytest.mark.parametrize("order", ["input", "rank"])
def test_a_ranked_run_past_the_budget_has_the_in_memory_runs_ranks(monkeypatch, tmp_path, order):
    """The places of the merge on disk (a file pass two reads beside the ids) are the in-memory merge's, in
    input order and in rank order."""
    import pyarrow.parquet as pq

    from conftest import real_file
    from prism_stream import rank
    from prism_stream.engines import spatial, spatial_disk
    from test_space import AUTZEN

    held = tmp_path / "held.parquet"
    rank(str(real_file(AUTZEN)), str(held), ratio=0.05, space="0.5", chunk_size=7_000, order=order)
    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", "0")
    monkeypatch.setattr(space, "MEMORY_BUDGET", 0)
    monkeypatch.setattr(spatial, "CAP", 300)
    monkeypatch.setattr(spatial_disk, "LEAF", 4_000)
    monkeypatch.setattr(spatial_disk, "SORT_RUN", 500)
    monkeypatch.setattr(spatial.IdSelector, "BLOCK", 999)
    temp = tmp_path / "temp"
    temp.mkdir()
    on_disk = tmp_path / "disk.parquet"
    s = rank(str(real_file(AUTZEN)), str(on_disk), ratio=0.05, space="0.5", chunk_size=7_000, temp_dir=str(temp),
             order=order)
    assert s.plan["space"]["points_on_disk"] > 0
    a, b = pq.read_table(held), pq.read_table(on_disk)
    assert a.num_rows == b.num_rows == 5_500 and a.column_names == b.column_names
    for name in a.column_names:
        assert a.column(name).equals(b.column(name)), name
    assert list(temp.iterdir()) == []


def test_the_forecast_counts_the_steps_after_the_scan():
    """The scan's 105 bytes a point bound a target up to N and a sort merged in one pass; past
    MERGED_AT_ONCE records, a pass writes a sort's records again, and a target near N costs more."""
    n = 10**9
    assert space.disk_bytes(n) == space.disk_bytes(n, n // 100) == 105 * n
    m = 10**8
    assert space.disk_bytes(m, m) == 105 * m  # the merge 96 bytes a place, the births 69 + 32 a point
    assert space.disk_bytes(n, n) == (36 + 32 + 1 + 64) * n  # 10^9 births: past one pass, written twice
    big = 1 << 30
    assert space.disk_bytes(big, big) == (36 + 32 + 1 + 64) * big  # 2 T births past one pass: written twice
    assert space.disk_bytes(big, big // 4) == 105 * big


def test_parts_read_as_one_file_one_open_at_a_time(tmp_path):
    """A Dask run's groups' files (or a routed file's pieces, one a group) are read as one file, however many
    there are: one of them open at a time (a cluster of many threads makes thousands, past the usual 1,024
    open files), empty ones included, and removed together unless they are a task's inputs."""
    from prism_stream.engines.spatial_disk import RECORD, Parts

    rng = np.random.default_rng(1)
    sizes = rng.integers(0, 40, 300)
    paths, whole = [], np.zeros(int(sizes.sum()), RECORD)
    whole["id"] = np.arange(len(whole))
    for i, (a, n) in enumerate(zip(np.cumsum(sizes) - sizes, sizes)):
        paths.append(str(tmp_path / f"p{i}"))
        whole[a:a + n].tofile(paths[-1])
    before = len(os.listdir("/proc/self/fd"))
    parts = Parts(paths, keep=True)
    assert parts.size == len(whole)
    for block in (1, 7, 1_000, len(whole)):
        got = np.concatenate([parts.read(a, min(block, len(whole) - a)) for a in range(0, len(whole), block)])
        assert np.array_equal(got, whole)
        assert len(os.listdir("/proc/self/fd")) <= before + 1
    parts.discard()
    assert len(os.listdir(tmp_path)) == 300  # a task's inputs stay
    Parts(paths).discard()
    assert os.listdir(tmp_path) == []


def test_a_routing_task_holds_few_files_open(tmp_path):
    """A routing task on a worker writes up to FAN files, and a worker runs one a thread: found by a review,
    8 threads at a fan-out of 256 passed the usual 1,024 open files. Its outputs are not held open: it routes
    to 200 files with 30 file descriptors to spare, and the files hold the part's points, cell by cell."""
    import resource

    from prism_stream.engines import spatial_disk

    rng = np.random.default_rng(4)
    rec = np.zeros(20_000, spatial_disk.RECORD)
    for axis in "xyz":
        rec[axis] = rng.uniform(0, 1_000, len(rec))
    rec["id"] = np.arange(len(rec))
    path = str(tmp_path / "points-000000")
    rec.tofile(path)
    frame = spatial_disk.Frame(100, 0, 64, 1_000, 256, -100, 20, 0)
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (len(os.listdir("/proc/self/fd")) + 30, hard))
    try:
        files, n = spatial_disk.route_part(path, frame, 200)
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    assert n == len(rec) and sum(f is not None for f in files) > 150
    got = np.concatenate([np.fromfile(f, spatial_disk.RECORD) for f in files if f is not None])
    assert np.array_equal(np.sort(got["id"]), rec["id"])
    cells = [{tuple(c) for c in space.cells_at(spatial_disk._xyz(np.fromfile(f, spatial_disk.RECORD)), 0)}
             for f in files if f is not None]
    assert sum(len(c) for c in cells) == len(set().union(*cells))  # every cell in one file
