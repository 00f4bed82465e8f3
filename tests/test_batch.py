"""`prism-stream batch JOBS`: every job runs, each is logged once, reruns resume.

A failing job is recorded with its error while the others finish, and the
exit code says so; a rerun skips what is done and redoes the rest; a batch
killed midway leaves no partial output, and its rerun leaves one log row per
job and the same outputs as an uninterrupted run.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
import warnings

import duckdb
import numpy as np
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream.sql.batch import read_jobs, run_batch

from conftest import edge_file, random_colors, real_file, user_env, write_parquet

CLI = [sys.executable, "-c", "from prism_stream_cli.main import run; run()"]
# The batch runs in a user's environment: its jobs' small inputs are held in memory, as a user's are (the
# suite's streaming switch would make every job process load the numba kernels, a second each; the outputs
# are the same bytes either way, tests/test_in_memory.py)
ENV = user_env()


def runs(log) -> list[dict]:
    con = duckdb.connect(str(log), read_only=True)
    try:
        rel = con.sql("SELECT * FROM prism_runs ORDER BY job_id")
        return [dict(zip(rel.columns, r)) for r in rel.fetchall()]
    finally:
        con.close()


def batch(*args, cwd):
    return subprocess.run([*CLI, "batch", *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=300,
                          env=ENV)


@pytest.fixture
def clouds(tmp_path):
    """Three generated Parquet clouds and the real Autzen LAS."""
    paths = []
    for i in range(3):
        rgb = random_colors(20000 + 5000 * i, seed=i, palette=500)
        n = len(rgb)
        paths.append(write_parquet(tmp_path / f"g{i}.parquet", {"x": np.arange(n, dtype=np.float64),
                                                                "red": rgb[:, 0], "green": rgb[:, 1],
                                                                "blue": rgb[:, 2]}))
    return paths + [real_file("pdal__autzen_trim.las")]


def test_a_corrupt_input_fails_alone_and_a_rerun_resumes(tmp_path, clouds, monkeypatch):
    bad = tmp_path / "bad.las"
    shutil.copy(edge_file("pdal__garbage_nVariableLength.las"), bad)
    (tmp_path / "jobs.csv").write_text(
        "job_id,inputs,output,ratio,k,seed,mode\n"
        f"a,{clouds[0]},out/a.parquet,0.05,,,\n"
        f"b,{clouds[1]};{clouds[2]},out/b.parquet,,3,7,\n"
        f"bad,{bad},out/bad.parquet,0.1,,,\n"
        f"d,{clouds[3]},out/d.parquet,0.01,,,paper\n")
    (tmp_path / "out").mkdir()
    first = batch("jobs.csv", "--jobs", "2", "--log", "runs.duckdb", cwd=tmp_path)
    assert first.returncode == 1
    assert "bad.las" in first.stderr and "VLR" in first.stderr
    log = {r["job_id"]: r for r in runs(tmp_path / "runs.duckdb")}
    assert {j: r["status"] for j, r in log.items()} == {"a": "done", "b": "done", "bad": "failed", "d": "done"}
    assert "bad.las" in log["bad"]["error"] and not (tmp_path / "out" / "bad.parquet").exists()
    for job, r in log.items():
        assert r["started"] <= r["ended"] and r["seconds"] >= 0 and r["peak_rss_bytes"] > 0, job
    # the log holds what the run did, and each output equals the file command's
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        want = prism_stream.sample([str(clouds[1]), str(clouds[2])], str(tmp_path / "ref.parquet"), k=3, seed=7)
    assert (log["b"]["points"], log["b"]["bins"], log["b"]["kept"], log["b"]["k"], log["b"]["seed"]) == \
        (want.points, want.bins, want.kept, want.k, 7)
    assert pq.read_table(tmp_path / "out" / "b.parquet").equals(pq.read_table(tmp_path / "ref.parquet"))
    assert log["d"]["rule"] == "paper" and log["a"]["target"] == round(0.05 * 20000)

    # fix the bad input; the rerun redoes only that job
    shutil.copy(clouds[3], bad)
    mtimes = {j: os.stat(tmp_path / "out" / f"{j}.parquet").st_mtime_ns for j in "abd"}
    second = batch("jobs.csv", "--jobs", "2", "--log", "runs.duckdb", cwd=tmp_path)
    assert second.returncode == 0, second.stderr
    assert [line.split()[1] for line in second.stdout.splitlines() if line.startswith("skipped")] == ["a:", "b:", "d:"]
    again = {r["job_id"]: r for r in runs(tmp_path / "runs.duckdb")}
    assert len(again) == 4 and all(r["status"] == "done" for r in again.values())
    assert all(again[j]["started"] == log[j]["started"] for j in "abd")
    assert mtimes == {j: os.stat(tmp_path / "out" / f"{j}.parquet").st_mtime_ns for j in "abd"}
    # --force redoes a done job, still one row per job
    monkeypatch.chdir(tmp_path)
    outcomes = run_batch(read_jobs("jobs.csv")[:1], "runs.duckdb", force=True)
    assert [o.status for o in outcomes] == ["done"]
    forced = {r["job_id"]: r for r in runs(tmp_path / "runs.duckdb")}
    assert len(forced) == 4 and forced["a"]["started"] > again["a"]["started"]


def test_jobs_from_parquet_or_a_query(tmp_path, clouds):
    con = duckdb.connect()
    con.execute(f"""COPY (SELECT 'p' || i AS job_id, ['{clouds[0]}'] AS inputs, '{tmp_path}/p' || i || '.parquet'
                          AS output, 0.01 * i AS ratio FROM range(1, 3) t(i)) TO '{tmp_path / "jobs.parquet"}'""")
    con.close()
    jobs = read_jobs(str(tmp_path / "jobs.parquet"))
    assert [(j.job_id, j.inputs, j.options) for j in jobs] == [("p1", [str(clouds[0])], {"ratio": 0.01}),
                                                               ("p2", [str(clouds[0])], {"ratio": 0.02})]
    query = (f"SELECT 'q' AS job_id, 'SELECT * FROM read_parquet(''{clouds[1]}'')' AS query, "
             f"'{tmp_path}/q.parquet' AS output, 4 AS k")
    outcomes = run_batch(jobs + read_jobs(query), str(tmp_path / "runs.duckdb"), workers=2)
    assert sorted(o.status for o in outcomes) == ["done"] * 3
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prism_stream.sample(str(clouds[1]), str(tmp_path / "ref.parquet"), k=4)
    assert pq.read_table(tmp_path / "q.parquet").equals(pq.read_table(tmp_path / "ref.parquet"))


def test_bad_jobs_tables_are_one_line_errors(tmp_path):
    (tmp_path / "jobs.csv").write_text("inputs,output,ratio,colour\na.las,b.parquet,0.1,red\n")
    r = batch("jobs.csv", cwd=tmp_path)
    assert r.returncode == 2 and "colour" in r.stderr and r.stderr.count("\n") == 1
    (tmp_path / "jobs.csv").write_text("inputs,output,ratio\na.las,b.parquet,0.1\nc.las,b.parquet,0.2\n")
    r = batch("jobs.csv", cwd=tmp_path)
    assert r.returncode == 2 and "both write" in r.stderr
    r = batch("missing.csv", cwd=tmp_path)
    assert r.returncode == 3
    assert not (tmp_path / "prism_runs.duckdb").exists()


@pytest.mark.parametrize("field,value,why", [
    ("seed", "-1", "not in 0..2^64-1"), ("seed", "18446744073709551616", "not in 0..2^64-1"),
    ("count", "100.7", "not a whole number"), ("k", "2.5", "not a whole number"),
    ("quant_bits", "1.9", "not a whole number"), ("seed", "1.5", "not a whole number"),
    ("count", "abc", "not a whole number")])
def test_a_job_field_the_command_line_would_refuse_is_refused_not_cut(tmp_path, field, value, why):
    """A seed past uint64 was an internal error that stopped the batch (the log's column holds uint64), and a
    count of 100.7 ran as 100: both are refused from the table, before any job, naming the job and field."""
    (tmp_path / "jobs.csv").write_text(f"job_id,inputs,output,ratio,{field}\nj7,a.las,b.parquet,0.1,{value}\n")
    r = batch("jobs.csv", cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "job j7" in r.stderr and field in r.stderr and why in r.stderr, r.stderr
    assert read_jobs_ok(tmp_path, "seed", "18446744073709551615") == 18446744073709551615
    assert read_jobs_ok(tmp_path, "count", "100.0") == 100 and read_jobs_ok(tmp_path, "count", " 7 ") == 7
    assert read_jobs_ok(tmp_path, "seed", "9007199254740993.0") == 9007199254740993  # not through a float


def test_the_run_log_is_no_jobs_table_output_or_input(tmp_path, clouds):
    """--log naming a job's output (the job replaced the log, then the log's next write failed: an internal
    error), the jobs table or an input is refused before any job runs, and nothing is touched."""
    (tmp_path / "jobs.csv").write_text(f"job_id,inputs,output,ratio\na,{clouds[0]},a.parquet,0.1\n")
    before = clouds[0].read_bytes()
    (tmp_path / "dir.csv").write_text(f"job_id,inputs,output,ratio\nd,{clouds[0]},outdir/,0.1\n")
    r = batch("dir.csv", "--log", f"outdir/{clouds[0].stem}.parquet", cwd=tmp_path)  # the file the job writes
    assert r.returncode == 2 and "in its output folder" in r.stderr, r.stderr
    for log, why in (("a.parquet", "job a's output"), ("jobs.csv", "jobs table"), (str(clouds[0]), "job a's input")):
        r = batch("jobs.csv", "--log", log, cwd=tmp_path)
        assert r.returncode == 2 and why in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert not (tmp_path / "a.parquet").exists() and clouds[0].read_bytes() == before


def read_jobs_ok(tmp_path, field, value):
    (tmp_path / "ok.csv").write_text(f"inputs,output,{field}\na.las,b.parquet,{value}\n")
    return read_jobs(str(tmp_path / "ok.csv"))[0].options[field]


def test_a_killed_batch_reruns_to_the_same_outputs(tmp_path, clouds):
    """SIGKILL midway: no partial output appears; the rerun leaves one row per job and the same files."""
    rows = ["job_id,inputs,output,ratio,seed"]
    for i in range(6):
        rows.append(f"j{i},{clouds[i % 4]},out/j{i}.parquet,0.05,{i}")
    (tmp_path / "jobs.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "out").mkdir()
    proc = subprocess.Popen([*CLI, "batch", "jobs.csv", "--jobs", "2", "--log", "runs.duckdb"], cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True, env=ENV)
    deadline = time.time() + 120
    while time.time() < deadline and len(list((tmp_path / "out").glob("j*.parquet"))) < 3:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    finished = sorted((tmp_path / "out").glob("j*.parquet"))
    assert 3 <= len(finished) < 6, "the batch was not killed midway"
    for f in finished:  # whatever is there under its final name is complete
        assert pq.read_metadata(f).num_rows > 0
    time.sleep(0.5)  # the workers die with the batch (PR_SET_PDEATHSIG): nothing appears afterwards
    assert sorted((tmp_path / "out").glob("j*.parquet")) == finished

    rerun = batch("jobs.csv", "--jobs", "2", "--log", "runs.duckdb", cwd=tmp_path)
    assert rerun.returncode == 0, rerun.stderr
    log = runs(tmp_path / "runs.duckdb")
    assert sorted(r["job_id"] for r in log) == [f"j{i}" for i in range(6)]
    assert all(r["status"] == "done" for r in log)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [f"j{i}.parquet" for i in range(6)]

    # the same outputs as an uninterrupted run
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i in range(6):
            prism_stream.sample(str(clouds[i % 4]), str(tmp_path / "ref.parquet"), ratio=0.05, seed=i, overwrite=True)
            assert pq.read_table(tmp_path / "out" / f"j{i}.parquet").equals(pq.read_table(tmp_path / "ref.parquet"))
