"""``sample --denoise sor:K,STD`` and ``--preset authors`` (SPEC 8): the outliers removed by Open3D's rule,
then PRISM over the cleaned cloud, its records numbered again in input order.

The oracle: ``oracle.open3d_sor_reference`` (Open3D's definition, written from its source) over the whole
cloud's coordinates, then ``oracle.sample`` over the kept points' colors: neither imports the engine. The
second check is by construction: the run equals a run over files that hold only the kept records (written
with laspy), record for record."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import subprocess

import laspy
import numpy as np
import pyarrow.parquet as pq
import pytest

import oracle
from conftest import cli, prism_stream_command, real_file
from prism_stream import sample
from prism_stream.engines import cleaned
from prism_stream.errors import OutputError, UsageError

AUTZEN = "pdal__autzen_trim.las"  # 110,000 points, 8-bit colors in 16-bit fields, 3,627 outliers at sor:100,2


@pytest.fixture(scope="module")
def autzen():
    las = laspy.read(str(real_file(AUTZEN)))
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    rgb = (np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue))
    return las, xyz, rgb, oracle.open3d_sor_reference(xyz, 100, 2.0)


def _rows(path) -> np.ndarray:
    t = pq.read_table(path)
    return np.column_stack([t.column(c).to_numpy() for c in ("x", "y", "z")])


def _expected(xyz, rgb, keep, parts, **options) -> np.ndarray:
    """The oracle's sample of the cleaned cloud split at ``parts`` (record counts of each file), as rows."""
    sources, places = [], []
    at = 0
    for n in parts:
        k = keep[at:at + n]
        sources.append(tuple(c[at:at + n][k] for c in rgb))
        places.append(at + np.flatnonzero(k))
        at += n
    res = oracle.sample(sources, **options)
    return np.concatenate([xyz[p[i]] for p, i in zip(places, res.kept)])


@pytest.mark.parametrize("reads,chunk_size,in_memory", [
    ("auto", 1 << 20, True),     # held in memory
    ("one", 7_000, False),       # one read, a candidate spill
    ("two", 7_000, False),       # two reads, a key cache
    ("one", 1 << 20, False),
])
def test_the_run_is_the_oracle_over_the_cleaned_cloud(autzen, reads, chunk_size, in_memory, monkeypatch, tmp_path):
    las, xyz, rgb, keep = autzen
    if not in_memory:
        monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", "0")
    src = real_file(AUTZEN)
    before = hashlib.sha256(src.read_bytes()).hexdigest()
    out = tmp_path / "out.parquet"
    s = sample(str(src), str(out), ratio=0.05, denoise="sor:100,2.0", reads=reads, chunk_size=chunk_size,
               temp_dir=str(tmp_path))
    want = _expected(xyz, rgb, keep, [len(xyz)], ratio=0.05)
    assert s.points == int(keep.sum()) == 110_000 - 3_627
    assert s.plan["denoise"]["removed"] == 3_627 and s.plan["denoise"]["points_before"] == 110_000
    assert s.kept == len(want) == round(0.05 * s.points)
    assert np.array_equal(_rows(out), want)  # same points, same order
    assert hashlib.sha256(src.read_bytes()).hexdigest() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.parquet"]  # the keep mask and tiles are gone
    meta = json.loads(pq.read_schema(out).metadata[b"prism_stream"])
    assert meta["options"]["denoise"] == "sor:100,2" and meta["denoise"]["removed"] == 3_627


def test_two_files_are_one_cloud_and_the_tiles_do_not_change_it(autzen, monkeypatch, tmp_path):
    """Two LAS files: one removal over both (neighbours across the cut), then one solve; tiles of 20,000
    points (many borders, points redone against every tile) remove the same points."""
    las, xyz, rgb, keep = autzen
    monkeypatch.setattr(cleaned, "TILE_POINTS", 20_000)
    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", "0")
    cut = 61_234
    paths = []
    for i, part in enumerate((slice(0, cut), slice(cut, None))):
        piece = laspy.LasData(las.header)
        piece.points = las.points[part]
        paths.append(str(tmp_path / f"t{i}.las"))
        piece.write(paths[-1])
    out = tmp_path / "out.parquet"
    s = sample(paths, str(out), count=4_000, denoise="sor:100,2.0", seed=7, chunk_size=10_000)
    assert s.plan["denoise"]["tiles"] > 4 and s.plan["denoise"]["redone_points"] > 0
    assert np.array_equal(_rows(out), _expected(xyz, rgb, keep, [cut, len(xyz) - cut], count=4_000, seed=7))
    assert [src["points"] for src in s.sources] == [int(keep[:cut].sum()), int(keep[cut:].sum())]


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_a_las_output_holds_the_records_a_cleaned_file_gives(autzen, suffix, monkeypatch, tmp_path):
    """The records written are the file's own (its point format, scales, every field), exactly those a run
    over a file of the kept records alone writes."""
    las, xyz, rgb, keep = autzen
    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", "0")
    copy = laspy.LasData(las.header)
    copy.points = las.points[keep]
    copy_path = tmp_path / "cleaned.las"
    copy.write(str(copy_path))
    a, b = tmp_path / f"a{suffix}", tmp_path / f"b{suffix}"
    sample(str(real_file(AUTZEN)), str(a), ratio=0.02, denoise="sor:100,2.0", reads="one")
    sample(str(copy_path), str(b), ratio=0.02)
    got, want = laspy.read(str(a)), laspy.read(str(b))
    assert got.header.point_format.id == las.header.point_format.id == want.header.point_format.id
    assert np.array_equal(got.points.array, want.points.array) and len(got.points) == round(0.02 * keep.sum())


def test_rank_over_the_cleaned_cloud_nests(autzen, tmp_path):
    """``rank --denoise``: the points of rank < T are the sample of T of the cleaned cloud."""
    las, xyz, rgb, keep = autzen
    ranked = tmp_path / "r.parquet"
    from prism_stream import rank

    rank(str(real_file(AUTZEN)), str(ranked), ratio=0.1, denoise="sor:100,2.0")
    t = pq.read_table(ranked)
    order = np.argsort(t.column("prism_rank").to_numpy())
    rows = np.column_stack([t.column(c).to_numpy() for c in "xyz"])
    for count in (1, 500, 3_000):
        first = rows[order[:count]]
        want = _expected(xyz, rgb, keep, [len(xyz)], count=count)
        assert sorted(map(tuple, first)) == sorted(map(tuple, want))


def test_the_preset_is_the_authors_pipeline(tmp_path, capsys):
    """``--preset authors``: SOR(100, 2.0), chroma, step 1, k = 1 for what is not given; a ratio given
    replaces its k. The PLY's 510 outliers are those eval's preset removes."""
    src = real_file("odm__option-0000.ply")
    code, out, err = cli(capsys, "sample", src, tmp_path / "a.parquet", "--preset", "authors", "--json")
    assert code == 0, err
    d = json.loads(out)
    assert d["options"] == {**d["options"], "k": 1, "ratio": None, "color_space": "chroma", "quant_step": 1.0,
                            "denoise": "sor:100,2"}
    assert d["plan"]["denoise"]["removed"] == 510 and d["kept"] == d["bins"]  # k = 1: one point a bin
    code, out, err = cli(capsys, "sample", src, tmp_path / "b.parquet", "--preset", "authors", "--ratio", "0.1",
                         "--color-space", "rgb", "--json")
    d = json.loads(out)
    assert code == 0 and d["options"]["k"] is None and d["options"]["ratio"] == 0.1
    assert d["options"]["color_space"] == "rgb" and d["options"]["denoise"] == "sor:100,2"


def test_what_denoise_refuses_before_reading(tmp_path, capsys):
    src = real_file(AUTZEN)
    cases = [
        (["--ratio", "0.1", "--denoise", "sor:200000,2"], "K = 200,000 neighbours is more than the cloud's 110,000"),
        (["--ratio", "0.1", "--denoise", "knn:3"], "--denoise takes sor:K,STD"),
        (["--ratio", "0.1", "--denoise", "sor:10,0"], "needs K >= 1 and STD > 0"),
        (["--ratio", "0.1", "--denoise", "sor:10,2", "--flag", "keep"], "--flag writes every point"),
        (["--ratio", "0.1", "--denoise", "sor:10,2", "--dask", "local:1"], "not available with --dask"),
        (["--ratio", "0.1", "--preset", "mine"], "'mine' is not 'authors'"),
    ]
    for args, said in cases:
        code, out, err = cli(capsys, "sample", src, tmp_path / "o.parquet", *args)
        assert code == 2 and said in err and len(err.strip().splitlines()) == 1, (args, err)
        assert not (tmp_path / "o.parquet").exists()
    code, out, err = cli(capsys, "sql", "--help")
    assert "--denoise" not in out  # a query's result is read once


def test_no_room_for_the_removal_is_said_before_it_writes(monkeypatch, tmp_path):
    monkeypatch.setattr(cleaned, "free_bytes", lambda folder: 1 << 20)
    work = tmp_path / "t"
    work.mkdir()
    with pytest.raises(OutputError, match=r"not enough temporary space: removing outliers from 110,000 points "
                                          r"writes about .* of tiles and distances"):
        sample(str(real_file(AUTZEN)), str(tmp_path / "o.parquet"), ratio=0.1, denoise="sor:100,2",
               temp_dir=str(work))
    assert list(work.iterdir()) == [] and not (tmp_path / "o.parquet").exists()


def test_a_disk_that_fills_during_the_removal_is_said_as_such(monkeypatch, tmp_path):
    from prism_stream.evaluate import tiles

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(tiles, "spill_tiles", full)
    work = tmp_path / "t"
    work.mkdir()
    with pytest.raises(OutputError, match="the temporary disk filled while removing outliers"):
        sample(str(real_file(AUTZEN)), str(tmp_path / "o.parquet"), ratio=0.1, denoise="sor:100,2",
               temp_dir=str(work))
    assert list(work.iterdir()) == [] and not (tmp_path / "o.parquet").exists()


def test_the_cleaned_source_maps_every_range(tmp_path):
    """Any [start, stop) of the cleaned records, in chunks of any size, is the kept records in order."""
    from prism_stream.formats import open_source

    rng = np.random.default_rng(3)
    src = open_source(str(real_file(AUTZEN)), 0)
    try:
        keep = rng.random(src.count) < 0.3
        keep[:70_000] &= rng.random(70_000) < 0.01  # long runs with nothing kept
        c = cleaned.CleanedSource(src, keep)
        assert c.count == int(keep.sum())
        allx = np.concatenate([np.asarray(p.points.x) for p in src.point_chunks(50_000)])[keep]
        for start, stop, size in [(0, None, 999), (5, 6, 1), (100, 2_000, 37), (c.count - 3, None, 1 << 16),
                                  (0, c.count, 70_001), (c.count, None, 10)]:
            parts = list(c.point_chunks(size, start, stop))
            end = c.count if stop is None else stop
            assert [p.start for p in parts] == list(np.cumsum([start] + [len(p) for p in parts])[:-1])
            got = np.concatenate([np.asarray(p.points.x) for p in parts]) if parts else np.zeros(0)
            assert np.array_equal(got, allx[start:end])
            colors = np.concatenate([np.asarray(p.rgb[0]) for p in c.color_chunks(size, start, stop)] or [[]])
            assert len(colors) == end - start
    finally:
        src.close()


def test_with_no_denoise_the_options_say_nothing_of_it():
    from prism_stream.core.quotas import Options

    assert "denoise" not in Options(ratio=0.1).as_dict()
    assert Options(ratio=0.1, denoise="SOR:100,2.0").as_dict()["denoise"] == "sor:100,2"
    with pytest.raises(UsageError):
        Options(ratio=0.1, denoise="sor:0,2")


def test_the_command_line_streams_a_denoised_run(autzen, tmp_path):
    """As a user runs it: its own process, the input streamed (the kernels' warm-up starts beside the removal,
    which needs scipy's KD-tree), a progress-free JSON summary; the rows are the oracle's."""
    las, xyz, rgb, keep = autzen
    out = tmp_path / "out.parquet"
    env = {**os.environ, "PRISM_STREAM_MEMORY_POINTS": "0"}
    run = subprocess.run([*prism_stream_command(), str(real_file(AUTZEN)), str(out), "--ratio", "0.03",
                          "--denoise", "sor:100,2", "--json", "--temp-dir", str(tmp_path)],
                         env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    d = json.loads(run.stdout)
    assert d["plan"]["reads"] == 1 and "spill_points" in d["plan"]  # streamed, not held
    assert np.array_equal(_rows(out), _expected(xyz, rgb, keep, [len(xyz)], ratio=0.03))


def _cloud(path, xyz, seed=0):
    import pyarrow as pa

    rng = np.random.default_rng(seed)
    n = len(xyz)
    cols = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    cols.update({c: rng.integers(0, 256, n).astype(np.uint8) for c in ("red", "green", "blue")})
    pq.write_table(pa.table(cols), path)
    return path


def test_hostile_clouds_are_one_line_and_leave_nothing(tmp_path, capsys):
    rng = np.random.default_rng(1)
    xyz = rng.random((500, 3))
    xyz[7, 2] = np.nan
    nan = _cloud(tmp_path / "nan.parquet", xyz)
    bare = tmp_path / "bare.parquet"
    pq.write_table(pq.read_table(nan).drop(["x", "y", "z"]), bare)
    work = tmp_path / "t"
    work.mkdir()
    for src, code, said in [(nan, 6, "non-finite coordinates; distances (eval, --denoise) need every point"),
                            (bare, 4, "no coordinates found (columns: red, green, blue)")]:
        got, out, err = cli(capsys, "sample", src, tmp_path / "o.parquet", "-r", "0.1", "--denoise", "sor:10,2",
                            "--temp-dir", work)
        assert got == code and said in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "o.parquet").exists() and list(work.iterdir()) == []


def test_a_cloud_of_duplicates_loses_every_point_as_open3d_would(tmp_path):
    """K or more copies of each point: every d_i is 0, so every point goes; then nothing is sampled, said."""
    xyz = np.repeat(np.random.default_rng(2).random((30, 3)), 12, axis=0)
    src = _cloud(tmp_path / "dup.parquet", xyz)
    assert not oracle.open3d_sor_reference(xyz, 10, 2.0).any()
    with pytest.warns(Warning, match="removed every point"):
        s = sample(str(src), str(tmp_path / "o.parquet"), ratio=0.5, denoise="sor:10,2")
    assert s.points == 0 and s.kept == 0 and s.plan["denoise"]["removed"] == 360
    assert pq.read_table(tmp_path / "o.parquet").num_rows == 0


def test_an_empty_file_is_an_empty_cleaned_cloud(tmp_path):
    src = _cloud(tmp_path / "empty.parquet", np.zeros((0, 3)))
    with pytest.warns(Warning, match="no points"):
        s = sample(str(src), str(tmp_path / "o.parquet"), ratio=0.5, denoise="sor:10,2")
    assert s.points == 0 and s.plan["denoise"] == {**s.plan["denoise"], "removed": 0, "points_before": 0}


def test_a_preset_fills_what_is_not_given_however_the_request_is_made():
    from prism_stream.run.request import Request

    r = Request(preset="authors")  # made directly: every field at its default takes the preset's value
    assert (r.denoise, r.color_space, r.quant_step, r.k, r.ratio) == ("sor:100,2.0", "chroma", 1.0, 1, None)
    r = Request(preset="authors", ratio=0.1)  # a target: no k
    assert (r.options.denoise, r.options.color_space, r.k, r.ratio) == ("sor:100,2", "chroma", None, 0.1)
    r = Request.of(preset="authors", color_space="rgb", count=5)  # Request.of knows what was given
    assert (r.color_space, r.quant_step, r.k, r.count) == ("rgb", 1.0, None, 5)
    assert Request.of(r, seed=3).color_space == "rgb"  # a request it made is not filled again
    assert Request(preset="authors", rank="prism_rank").k is None  # ranks take no k
    with pytest.raises(UsageError, match="--preset takes authors"):
        Request(preset="theirs", ratio=0.1)


def test_a_file_size_limit_met_while_writing_tiles_is_exit_8(tmp_path):
    """A real short write (a file-size limit: numpy's tofile said it without an errno, internal error 70):
    exit 8 in one line, nothing left in the temporary folder, no output."""
    import resource

    work = tmp_path / "t"
    work.mkdir()

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (1_000_000, 1_000_000))  # tiles of autzen: 3.6 MB

    run = subprocess.run([*prism_stream_command(), str(real_file(AUTZEN)), str(tmp_path / "o.parquet"), "--ratio",
                          "0.1", "--denoise", "sor:100,2", "--temp-dir", str(work), "-q"], preexec_fn=limit,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 8, run.stderr
    assert "the temporary disk filled while removing outliers (File too large)" in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1 and list(work.iterdir()) == []
    assert not (tmp_path / "o.parquet").exists()


def test_per_file_refuses_every_file_before_the_first_is_sampled(tmp_path, capsys, monkeypatch):
    from prism_stream.evaluate import denoise

    folder = tmp_path / "in"
    folder.mkdir()
    _cloud(folder / "a.parquet", np.random.default_rng(4).random((3_000, 3)))
    _cloud(folder / "b.parquet", np.random.default_rng(5).random((100, 3)))
    called = []
    monkeypatch.setattr(denoise, "sor_keep_streamed", lambda *a, **k: called.append(1))
    code, out, err = cli(capsys, "sample", folder, f"{tmp_path / 'out'}/", "--ratio", "0.1", "--per-file",
                         "--denoise", "sor:101,2")
    assert code == 2 and "b.parquet: --denoise sor:101,2: K = 101 neighbours is more than the cloud's 100" in err
    assert called == [] and not (tmp_path / "out").exists()
    code, out, err = cli(capsys, "sample", folder, tmp_path / "o.parquet", "--ratio", "0.1", "--preset", "authors",
                         "--flag", "keep")
    assert code == 2 and "--preset authors (its --denoise sor:100,2) removes points and --flag" in err


def test_a_target_given_later_replaces_the_k_a_preset_filled(tmp_path):
    from prism_stream import rank
    from prism_stream.run.request import Request

    request = Request(preset="authors")  # k = 1 filled: no target given
    s = sample(str(real_file("odm__option-0000.ply")), str(tmp_path / "a.parquet"), request, ratio=0.05)
    assert s.options["k"] is None and s.options["ratio"] == 0.05 and s.options["denoise"] == "sor:100,2"
    r = rank(str(real_file("odm__option-0000.ply")), str(tmp_path / "r.parquet"), request)
    assert r.options["k"] is None and r.options["color_space"] == "chroma"
    assert Request.of(preset="authors", quant_bits=1, ratio=0.1).quant_step is None  # bits given: no step
    assert Request(preset="authors", k=3).k == 3  # a k given is the user's


def test_a_removal_of_every_point_says_so(capsys, tmp_path):
    """sor:1 removes every point (each point's one neighbour is itself: every mean distance is 0, as Open3D
    computes it): the warning said 'the input has no points', of an input of 3,000 points. It now names the
    removal."""
    src = real_file("pdal__warsaw_small.las")
    code, _, err = cli(capsys, src, tmp_path / "o.parquet", "--ratio", "0.5", "--denoise", "sor:1,2", "--quiet")
    assert code == 0 and "--denoise sor:1,2 removed every point of the input; the output is empty" in err, err
    assert "the input has no points" not in err
    assert pq.read_metadata(tmp_path / "o.parquet").num_rows == 0
