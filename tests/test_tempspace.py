"""Temporary disk predicted before it is used (issue 26): the forecast's numbers, the decisions a run takes
on them before pass one, the spill's budget during pass one, and what --plan reports."""

from __future__ import annotations

import json
import math
import os

import laspy
import numpy as np
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings, strategies as st

from conftest import real_file
from prism_stream import sample
from prism_stream.core.quotas import Options
from prism_stream.errors import OutputError
from prism_stream.engines import reads
from prism_stream.formats.las import LasSource
from prism_stream.run import tempspace

AUTZEN = real_file("pdal__autzen_trim.las")
PLY = real_file("odm__option-0000.ply")


def test_exact_heap_spill_is_the_sum_it_stands_for():
    """sum_{i <= n} min(1, t / i) against t (1 + ln(n / t)): the harmonic sum is within t / (2 t) + 1 of it."""
    for n, t in [(10, 1), (1000, 10), (10**5, 300), (50, 50), (7, 100)]:
        exact = sum(min(1.0, t / i) for i in range(1, n + 1))
        got = tempspace.exact_heap_spill(n, t)
        assert abs(got - exact) <= 1.0, (n, t, got, exact)
    counts = np.array([10, 1000, 5, 0])
    quotas = np.array([1, 10, 5, 0])
    per_bin = tempspace.exact_heap_spill(counts, quotas)
    assert per_bin.shape == (4,) and per_bin[2] == 5 and per_bin[3] == 0


def test_exact_heaps_in_random_order_keep_what_the_formula_says():
    """A simulation of exact heaps (a point is a candidate when it is among the t smallest so far)."""
    rng = np.random.default_rng(1)
    n, t, runs = 4000, 40, 30
    seen = []
    for _ in range(runs):
        p = rng.random(n)
        kept, cand = [], 0
        for x in p:
            if len(kept) < t or x < kept[-1]:
                cand += 1
                kept.append(x)
                kept.sort()
                del kept[t:]
        seen.append(cand)
    expect = sum(min(1.0, t / i) for i in range(1, n + 1))
    assert abs(np.mean(seen) - expect) < 4 * np.std(seen) / math.sqrt(runs) + 1, (np.mean(seen), expect)
    assert abs(tempspace.exact_heap_spill(n, t) - expect) <= 1


@given(n=st.integers(0, 10**10), r=st.floats(1e-4, 0.5))
def test_the_bound_is_twice_the_expectation_and_never_more_than_n(n, r):
    t = int(math.floor(r * n + 0.5))
    b = tempspace.spill_bound(n, t)
    assert 0 <= b <= n
    if t > 0:
        assert b == min(n, math.ceil(2 * t * (1 + math.log(n / t))))
    else:
        assert b == 0


def test_target_bound_of_a_fixed_k_is_k_for_every_bin_there_can_be():
    assert tempspace.target_bound(Options(ratio=0.01), 12345) == 123
    assert tempspace.target_bound(Options(k=3, quant_bits=6), 10**6) == 3 * 64  # 4 levels a channel: 64 bins
    assert tempspace.target_bound(Options(k=3), 100) == 100  # no more than N


def test_record_bytes_by_format(tmp_path):
    las = LasSource(str(AUTZEN), 0)
    try:
        assert tempspace.record_bytes(las) == laspy.open(str(AUTZEN)).header.point_format.size
    finally:
        las.close()
    from prism_stream.run.inputs import open_sources

    s = sample(str(AUTZEN), str(tmp_path / "a.parquet"), ratio=0.5)
    (src,) = open_sources([str(tmp_path / "a.parquet")])
    try:
        schema = pq.read_schema(str(tmp_path / "a.parquet"))
        fixed = sum(f.type.bit_width // 8 for f in schema if hasattr(f.type, "bit_width") and
                    _fixed(f.type))
        variable = sum(1 for f in schema if not _fixed(f.type))
        assert tempspace.record_bytes(src) == fixed + tempspace.VARIABLE_BYTES * variable
        assert s.kept > 0
    finally:
        src.close()


def _fixed(t) -> bool:
    try:
        t.bit_width
        return True
    except ValueError:
        return False


@settings(max_examples=6, deadline=None)
@given(chunk=st.sampled_from([1_000, 7_777, 65_536]), ratio=st.sampled_from([0.003, 0.05, 0.3]),
       cloud=st.sampled_from([AUTZEN, PLY]))
def test_the_plan_reports_the_spill_the_run_makes(chunk, ratio, cloud, tmp_path_factory):
    """--plan runs the run's candidate filter over the colors alone: its spill is the run's, point for point."""
    out = tmp_path_factory.mktemp("plan") / "o.parquet"
    plan = sample(str(cloud), None, ratio=ratio, chunk_size=chunk)
    run = sample(str(cloud), str(out), ratio=ratio, chunk_size=chunk)
    assert run.plan["reads"] == 1
    assert plan.plan["temp"]["spill_points_run"] == run.plan["spill_points"]
    assert plan.kept == run.kept and plan.k == run.k
    # the bytes: the index exactly, a LAS record exactly, other formats' columns within a tenth (a PLY
    # chunk pickles 30 bytes a point for the 27 of its columns), each frame's own bytes within FRAME_BYTES
    frames = -(-run.points // chunk)
    slack = (0 if cloud == AUTZEN else 0.12) * run.plan["spill_bytes"] + tempspace.FRAME_BYTES * frames
    assert abs(plan.plan["temp"]["spill_bytes_run"] - run.plan["spill_bytes"]) <= slack


def _free(monkeypatch, free: int):
    monkeypatch.setattr(tempspace, "free_bytes", lambda folder: free)


def _run_and_two_reads(tmp_path):
    """The output of --reads two, which every path must equal."""
    base = sample(str(AUTZEN), str(tmp_path / "base.parquet"), ratio=0.01, reads="two")
    return base, pq.read_table(tmp_path / "base.parquet")


def test_a_spill_bound_too_big_for_the_disk_reads_twice_from_the_start(tmp_path, monkeypatch):
    _, want = _run_and_two_reads(tmp_path)
    free = _room_for_the_key_cache_alone(tmp_path)
    _free(monkeypatch, free)
    s = sample(str(AUTZEN), str(tmp_path / "o.parquet"), ratio=0.01)
    assert s.plan["reads"] == 2 and "may reach" in s.plan["why"], s.plan["why"]
    assert s.plan["temp"]["free_bytes"] == free
    assert pq.read_table(tmp_path / "o.parquet").equals(want)


def _room_for_the_key_cache_alone(tmp_path) -> int:
    """Free space that holds the key cache (4 bytes a point), the output and the reserve, not the spill's bound."""
    src = LasSource(str(AUTZEN), 0)
    try:
        f = tempspace.forecast([src], Options(ratio=0.01), str(tmp_path), str(tmp_path / "o.parquet"))
    finally:
        src.close()
    assert f.output_bytes > 0 and f.spill_bytes_bound > f.key_cache_bytes + 1000
    return tempspace.RESERVE + f.output_bytes + f.key_cache_bytes + 1000


def test_no_room_for_either_path_is_refused_before_pass_one(tmp_path, monkeypatch):
    _free(monkeypatch, tempspace.RESERVE + 1000)
    import prism_stream.engines.reads as reads

    def no_pass_one(*a, **k):
        raise AssertionError("pass one started")

    monkeypatch.setattr(reads, "scan", no_pass_one)
    monkeypatch.setattr(reads, "scan_candidates", no_pass_one)
    out = tmp_path / "o.parquet"
    with pytest.raises(OutputError) as e:
        sample(str(AUTZEN), str(out), ratio=0.01)
    assert "not enough temporary space" in str(e.value) and "--temp-dir" in str(e.value)
    assert not out.exists() and os.listdir(tmp_path) == []


def _cli(capsys, *args) -> tuple[int, str, str]:
    from prism_stream_cli.main import run

    with pytest.raises(SystemExit) as e:
        run(list(args))
    out, err = capsys.readouterr()
    return e.value.code, out, err


def test_the_command_refuses_in_one_line(tmp_path, monkeypatch, capsys):
    _free(monkeypatch, tempspace.RESERVE + 1000)
    tmp = tmp_path / "t"
    tmp.mkdir()
    code, out, err = _cli(capsys, str(AUTZEN), str(tmp_path / "o.parquet"), "--ratio", "0.01", "--temp-dir",
                          str(tmp))
    assert code == 8  # OutputError: a temporary could not be written (README exit codes)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and str(tmp) in lines[0] and "not enough temporary space" in lines[0], err
    assert not (tmp_path / "o.parquet").exists() and os.listdir(tmp) == []


def test_a_spill_past_its_budget_stops_and_the_run_reads_twice(tmp_path, monkeypatch):
    """Input in scan order can spill past the random-order bound: the spill stops at the free space it was
    given (here a bound that says 0 and room for the key cache alone) and the run reads twice, same output."""
    _, want = _run_and_two_reads(tmp_path)
    n = laspy.open(str(AUTZEN)).header.point_count
    with monkeypatch.context() as m:
        m.setattr(reads, "compact_mark", lambda bound: None)
        spilled = sample(str(AUTZEN), str(tmp_path / "one.parquet"), ratio=0.01).plan["spill_bytes"]
    monkeypatch.setattr(tempspace, "spill_bound", lambda n, t: 0)
    free = tempspace.RESERVE + int(0.0101 * n) * 200 + 4 * n + 1000
    assert free - tempspace.RESERVE < spilled  # the budget is less than what the spill needs
    _free(monkeypatch, free)
    with monkeypatch.context() as m:
        m.setattr(reads, "compact_mark", lambda bound: None)  # no compaction: the spill passes its budget
        s = sample(str(AUTZEN), str(tmp_path / "o.parquet"), ratio=0.01)
    assert s.plan["reads"] == 2 and "passed" in s.plan["why"], s.plan["why"]
    assert pq.read_table(tmp_path / "o.parquet").equals(want)
    left = [p for p in os.listdir(tmp_path) if p not in ("base.parquet", "one.parquet", "o.parquet")]
    assert left == []
    # compacted at its mark (here every chunk: a bound of 0), the same spill stays within the same budget; a
    # file read as 8-bit from the start (an auto file of 8-bit values may prove 16-bit until its end, and
    # its spill is compacted only once no counted point can still change bins)
    s = sample(str(AUTZEN), str(tmp_path / "c.parquet"), ratio=0.01, chunk_size=10_000, color_depth="8")
    assert s.plan["reads"] == 1 and s.plan["spill_compactions"] > 1, s.plan
    assert s.plan["spill_points_written"] > s.plan["spill_points_peak"] >= s.plan["spill_points"]
    assert pq.read_table(tmp_path / "c.parquet").equals(want)


def test_plan_text_and_json_carry_the_forecast(capsys):
    code, out, err = _cli(capsys, "--plan", str(AUTZEN), "--ratio", "0.01")
    assert code == 0, err
    assert "when run, the run's filter" in out and "random order: about" in out
    assert "free in" in out and "a run reads the input once" in out
    code, out, err = _cli(capsys, "--plan", str(AUTZEN), "--ratio", "0.01", "--json")
    t = json.loads(out)["plan"]["temp"]
    assert t["spill_points_run"] > 0 and t["free_bytes"] > 0 and t["start"]["spill_points_bound"] > 0
    code, out, err = _cli(capsys, "--plan", str(AUTZEN), "--ratio", "0.01", "--reads", "two")
    assert "reads the input twice (--reads two)" in out, out


def test_plan_says_a_run_would_read_twice_or_be_refused(tmp_path, monkeypatch, capsys):
    _free(monkeypatch, _room_for_the_key_cache_alone(tmp_path))
    code, out, err = _cli(capsys, "--plan", str(AUTZEN), "--ratio", "0.01")
    assert "a run reads the input twice: the spill may take up to" in out, out
    _free(monkeypatch, tempspace.RESERVE + 1000)
    code, out, err = _cli(capsys, "--plan", str(AUTZEN), "--ratio", "0.01")
    assert "a run would be refused" in out, out


def test_dask_reads_twice_when_the_spill_bound_does_not_fit_beside_the_output(tmp_path, monkeypatch):
    """The Dask units spill into the staging folder beside the output: its disk is the one forecast."""
    import distributed

    from prism_stream.engines import dask as dask_engine

    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as c:
        one = dask_engine.sample(c, [str(AUTZEN)], str(tmp_path / "one"), ratio=0.01, unit_size=40_000)
        assert one.plan["reads"] == 1 and one.plan["dask"]["temp"]["spill_points_bound"] > 0
        want = dask_engine.read_dataset(str(tmp_path / "one"))
        _free(monkeypatch, tempspace.RESERVE + 1000)
        two = dask_engine.sample(c, [str(AUTZEN)], str(tmp_path / "two"), ratio=0.01, unit_size=40_000)
        assert two.plan["reads"] == 2 and "may reach" in two.plan["why"], two.plan["why"]
        assert dask_engine.read_dataset(str(tmp_path / "two")).equals(want)
        # a bound that fits, and a disk that cannot hold the units' spills: each unit stops at its share of
        # the free space and is read again, and the disk is never filled
        monkeypatch.setattr(tempspace, "spill_bound", lambda n, t: 0)
        f = one.plan["dask"]["temp"]
        _free(monkeypatch, tempspace.RESERVE + f["output_bytes"] + one.plan["spill_bytes"] // 4)
        shared = dask_engine.sample(c, [str(AUTZEN)], str(tmp_path / "shared"), ratio=0.01, unit_size=40_000)
        assert shared.plan["reads"] == 2 and "ran out of temporary space" in shared.plan["why"], shared.plan
        assert shared.plan["units_read_again"] >= 1
        assert dask_engine.read_dataset(str(tmp_path / "shared")).equals(want)


def test_a_ranking_run_counts_its_ranks_temporaries(tmp_path, monkeypatch):
    from prism_stream import rank

    n = laspy.open(str(AUTZEN)).header.point_count
    s = rank(str(AUTZEN), str(tmp_path / "r.parquet"), ratio=0.5)
    t = s.plan["temp"]
    assert t["rank_bytes"] == tempspace.RANK_BYTES * s.kept and s.kept == round(0.5 * n)
    # room for the key cache and the output, not for the ranks' temporaries as well
    _free(monkeypatch, tempspace.RESERVE + t["output_bytes"] + t["key_cache_bytes"] + 1000)
    with pytest.raises(OutputError) as e:
        rank(str(AUTZEN), str(tmp_path / "r2.parquet"), ratio=0.5)
    assert "ranks" in str(e.value) and not (tmp_path / "r2.parquet").exists()


def test_a_file_given_as_the_temporary_folder_is_said_to_be_one(capsys, tmp_path):
    """Found by a hostile test: ``--temp-dir`` naming a file was told "does not exist"."""
    from conftest import cli, real_file

    afile = tmp_path / "afile"
    afile.write_text("")
    out = tmp_path / "out.parquet"
    code, _, err = cli(capsys, str(real_file("pdal__autzen_trim.las")), str(out), "--ratio", "0.05",
                       "--temp-dir", str(afile))
    assert code == 8 and f"{afile}: the temporary folder is a file, not a folder" in err and not out.exists()
