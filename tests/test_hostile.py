"""Hostile options: every failure is the README's exit code and one line naming the path (issue 10).

- usage errors (exit 2) are one line, never click's four-line block or an OverflowError;
- ``--summary`` never replaces an input, the output or a file the run did not create;
- no option value reaches DuckDB as SQL text (quotes, semicolons, comments), and the
  ``prism_sample`` macros cannot be steered by a user column named like their own;
- OS errors (unwritable output or temporary folder, unreadable input, a full temporary
  folder, a missing summary folder) are exit 8 or 6, never 70;
- ``python -m prism_stream`` is the command line.
"""

from __future__ import annotations

import ctypes
import json
import os
import resource
import subprocess
import sys
from pathlib import Path

import duckdb
import numpy as np
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from prism_stream.engines.sql import connect, sample_query
from prism_stream.errors import PrismError
from prism_stream.sql import identifier, register
from prism_stream.sql.batch import read_jobs

from conftest import cli, prism_stream_command, random_colors, write_las, write_parquet

ROOT = os.geteuid() == 0


def one_error_line(err: str, *must: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, f"expected one line on stderr, got {err!r}"
    assert lines[0].startswith("prism-stream: error: "), err
    for m in must:
        assert m in lines[0], f"{m!r} not in {lines[0]!r}"
    assert "Traceback" not in err and "internal error" not in err
    return lines[0]


@pytest.fixture(scope="module")
def cloud(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("hostile")
    return write_las(folder / "in.las", random_colors(20_000, seed=3, palette=400))


@pytest.fixture(scope="module")
def cloud_parquet(tmp_path_factory) -> Path:
    rgb = random_colors(20_000, seed=5, palette=400)
    folder = tmp_path_factory.mktemp("hostile")
    return write_parquet(folder / "in.parquet", {"x": np.arange(len(rgb), dtype=np.float64),
                                                 "red": rgb[:, 0].astype(np.uint16),
                                                 "green": rgb[:, 1].astype(np.uint16),
                                                 "blue": rgb[:, 2].astype(np.uint16)})


# -- category 6: usage errors are one line, exit 2 ------------------------------------------------

USAGE = [
    (["--ratio", "abc"], "--ratio"),
    (["--ratio", "0.1", "--seed", "-1"], "--seed"),
    (["--ratio", "0.1", "--seed", str(1 << 64)], "--seed"),
    (["--ratio", "0.1", "--chunk-size", "0"], "--chunk-size"),
    (["--ratio", "0.1", "--quant-bits", "8"], "--quant-bits"),
    (["--ratio", "0.1", "--threads", "0"], "--threads"),
    (["--ratio", "0.1", "--rgb-columns", "a,b"], "--rgb-columns"),
    (["--k", "9223372036854775808"], "--k"),
    (["--count", "99999999999999999999999"], "--count"),
    (["--k", "0"], "--k"),
    (["--ratio", "nan"], "--ratio"),
    (["--ratio", "0.1", "--mode", "nope"], "--mode"),
    (["--ratio", "0.1", "--k", "3"], "one of"),
]


@pytest.mark.parametrize("args,flag", USAGE, ids=[" ".join(a) for a, _ in USAGE])
def test_bad_option_values_are_one_line_exit_2(capsys, tmp_path, cloud, args, flag):
    code, out, err = cli(capsys, cloud, tmp_path / "out.parquet", *args)
    assert code == 2, err
    one_error_line(err, flag)
    assert not (tmp_path / "out.parquet").exists()


def test_an_output_named_like_an_option_is_one_line_with_the_way_out(capsys, tmp_path, cloud, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = cli(capsys, cloud, "-out.parquet", "--ratio", "0.1")
    assert code == 2
    one_error_line(err, "'--'", "./NAME")
    code, _, err = cli(capsys, "--ratio", "0.1", "--quiet", cloud, "--", "-out.parquet")
    assert code == 0, err
    assert (tmp_path / "-out.parquet").is_file()


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flag=st.sampled_from(["--ratio", "--count", "--k", "--seed", "--quant-bits", "--chunk-size", "--threads"]),
       value=st.one_of(st.integers(min_value=-(1 << 70), max_value=1 << 70).map(str),
                       st.text(alphabet="0123456789.-e+xnaif", min_size=1, max_size=12)))
def test_generated_option_values_never_end_in_an_internal_error(capsys, tmp_path, cloud, flag, value):
    target = [] if flag in ("--ratio", "--count", "--k") else ["--ratio", "0.1"]
    out = tmp_path / "gen.parquet"
    code, _, err = cli(capsys, cloud, out, *target, flag, value, "--quiet", "--overwrite")
    assert code in (0, 2), err
    if code:
        one_error_line(err)
    assert "internal error" not in err


# -- category 2: the summary file never replaces what the run did not create ------------------------

def _input_bytes(path: Path) -> bytes:
    return Path(path).read_bytes()


@pytest.mark.parametrize("overwrite", [False, True])
def test_summary_is_never_an_input(capsys, tmp_path, cloud, overwrite):
    before = _input_bytes(cloud)
    extra = ["--overwrite"] if overwrite else []
    link = tmp_path / "link.las"
    link.symlink_to(cloud)
    hard = tmp_path / "hard.las"
    os.link(cloud, hard)
    for summary in (cloud, link, hard):
        code, _, err = cli(capsys, cloud, tmp_path / "o.parquet", "--ratio", "0.1", "--summary", summary, *extra)
        assert code == 2, err
        one_error_line(err, str(summary), "input")
    # an input given as a folder: its files are inputs too
    code, _, err = cli(capsys, cloud.parent, tmp_path / "o.parquet", "--ratio", "0.1", "--summary", cloud, *extra)
    assert code == 2, err
    one_error_line(err, "input")
    assert _input_bytes(cloud) == before
    assert not (tmp_path / "o.parquet").exists()


def test_summary_is_never_the_output(capsys, tmp_path, cloud):
    out = tmp_path / "o.parquet"
    code, _, err = cli(capsys, cloud, out, "--ratio", "0.1", "--summary", out)
    assert code == 2
    one_error_line(err, "output")
    # directory mode: one of the outputs
    code, _, err = cli(capsys, cloud, f"{tmp_path / 'd'}/", "--ratio", "0.1", "--summary", tmp_path / "d" / "in.las")
    assert code == 2, err
    one_error_line(err, "output")
    assert not out.exists() and not (tmp_path / "d").exists()


def test_summary_never_replaces_a_file_without_overwrite(capsys, tmp_path, cloud):
    other = tmp_path / "notes.txt"
    other.write_text("keep me")
    dangling = tmp_path / "dangling.json"
    dangling.symlink_to(tmp_path / "nowhere")
    for summary in (other, dangling):
        code, _, err = cli(capsys, cloud, tmp_path / "o.parquet", "--ratio", "0.1", "--summary", summary)
        assert code == 7, err
        one_error_line(err, str(summary))
    assert other.read_text() == "keep me"
    assert not (tmp_path / "nowhere").exists()
    assert not (tmp_path / "o.parquet").exists()


def test_summary_through_a_symlink_replaces_the_link_not_its_target(capsys, tmp_path, cloud):
    target = tmp_path / "target.json"
    target.write_text("{}")
    link = tmp_path / "link.json"
    link.symlink_to(target)
    code, _, err = cli(capsys, cloud, tmp_path / "o.parquet", "--ratio", "0.1", "--summary", link, "--overwrite",
                       "--quiet")
    assert code == 0, err
    assert target.read_text() == "{}"
    assert not link.is_symlink() and json.loads(link.read_text())["kept"] == 2000


def test_summary_in_a_missing_folder_fails_before_the_output_is_written(capsys, tmp_path, cloud):
    out = tmp_path / "o.parquet"
    code, _, err = cli(capsys, cloud, out, "--ratio", "0.1", "--summary", tmp_path / "no" / "s.json")
    assert code == 8
    one_error_line(err, "s.json", "folder")
    assert not out.exists()
    code, _, err = cli(capsys, "sql", "SELECT 1 AS red, 2 AS green, 3 AS blue", out, "--ratio", "1",
                       "--summary", tmp_path / "no" / "s.json")
    assert code == 8
    one_error_line(err, "s.json")
    assert not out.exists()


def test_summary_into_a_device_or_a_pipe_writes_into_it(capsys, tmp_path, cloud):
    """A device or a FIFO (or a link to one) is written into, never replaced by a file: ``--summary /dev/stderr``
    works, and ``--summary /dev/full --overwrite`` cannot turn a device into a file."""
    import stat
    import threading

    fifo = tmp_path / "summary.fifo"
    os.mkfifo(fifo)
    link = tmp_path / "to_fifo.json"
    link.symlink_to(fifo)
    for summary, extra in ((fifo, []), (link, ["--overwrite"])):
        got = []
        reader = threading.Thread(target=lambda: got.append(fifo.read_text()))
        reader.start()
        code, _, err = cli(capsys, cloud, tmp_path / "o.parquet", "--ratio", "0.1", "--summary", summary, "--quiet",
                           "--overwrite", *extra)
        reader.join(timeout=30)
        assert code == 0, err
        assert json.loads(got[0])["kept"] == 2000
        assert stat.S_ISFIFO(os.stat(fifo).st_mode) and link.is_symlink()
    device = tmp_path / "null"  # a device of the test's own (never a system one: a regression would replace it)
    try:
        os.mknod(device, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    except OSError:
        return  # not root: the FIFO above is the case
    code, _, err = cli(capsys, cloud, tmp_path / "o.parquet", "--ratio", "0.1", "--summary", device, "--overwrite",
                       "--quiet")
    assert code == 0, err
    assert stat.S_ISCHR(os.stat(device).st_mode)


def test_summary_through_a_link_to_a_descriptor_writes_into_what_it_is_open_on(tmp_path, cloud):
    """``--summary /dev/stdout`` with stdout redirected to a file (the link resolves to that file): the summary
    is written into the stream, never a file renamed over the link (a reviewer replaced a link so)."""
    import subprocess
    import sys

    link = tmp_path / "mystdout"
    link.symlink_to("/proc/self/fd/1")
    with open(tmp_path / "redirected.txt", "w") as out:
        done = subprocess.run([sys.executable, "-c", "from prism_stream_cli.main import run; run()", str(cloud),
                               str(tmp_path / "o.parquet"), "--ratio", "0.1", "--quiet", "--overwrite",
                               "--summary", str(link)], stdout=out, stderr=subprocess.PIPE, text=True)
    assert done.returncode == 0, done.stderr
    assert link.is_symlink() and os.readlink(link) == "/proc/self/fd/1"
    assert json.loads((tmp_path / "redirected.txt").read_text())["kept"] == 2000


def test_summary_in_a_folder_no_file_can_be_made_in_fails_before_the_run(capsys, tmp_path, cloud):
    """/proc lets root pass ``access()`` but takes no new file: refused before pass one, no output written."""
    out = tmp_path / "o.parquet"
    code, _, err = cli(capsys, cloud, out, "--ratio", "0.1", "--summary", "/proc/prism-summary.json")
    assert code == 8, err
    one_error_line(err, "prism-summary.json", "not writable")
    assert not out.exists()


# -- category 3: nothing reaches DuckDB as SQL text ------------------------------------------------

HOSTILE = ["x'; COPY (SELECT 42) TO 'PWNED.csv'; SELECT '", "a\"b", "--", "/* x */", "x'--", "';", "\\'", "$$x$$"]
hostile_text = st.one_of(st.sampled_from(HOSTILE),
                         st.text(alphabet="ab'\";-/*\\ $\nCOPYTO()", min_size=1, max_size=30))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(value=hostile_text)
def test_connection_settings_are_values_not_sql(tmp_path, monkeypatch, value):
    monkeypatch.chdir(tmp_path)
    try:
        con = connect(memory_limit=None, temp_directory=os.path.join(str(tmp_path), value))
    except PrismError:
        con = None
    if con is not None:
        assert con.execute("SELECT current_setting('temp_directory')").fetchone()[0].endswith(value)
        con.close()
    try:
        con = connect(memory_limit=value)
    except PrismError as exc:  # a value DuckDB does not take is a usage error, one line
        assert exc.exit_code == 2 and "\n" not in str(exc)
    else:
        con.close()
    assert not list(tmp_path.glob("PWNED*"))


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(value=hostile_text)
def test_sql_command_options_cannot_inject(capsys, tmp_path, monkeypatch, cloud_parquet, value):
    monkeypatch.chdir(tmp_path)
    query = f"SELECT * FROM read_parquet({identifier(str(cloud_parquet)).replace(chr(34), chr(39))})"
    for opts in (["--temp-dir", value], ["--memory-limit", value], ["--database", value]):
        code, _, err = cli(capsys, "sql", query, tmp_path / "o.parquet", "--ratio", "0.5", *opts, "--overwrite",
                           "--quiet", "--materialize", "spool")
        assert code in (0, 2, 3, 8), err
        if code:
            one_error_line(err)
    assert not list(tmp_path.glob("PWNED*"))


def test_spool_and_temp_folder_with_quotes_in_their_path(tmp_path, cloud_parquet):
    weird = tmp_path / "it's -- a /* dir */; x"
    weird.mkdir(parents=True)
    query = f"SELECT * FROM read_parquet('{cloud_parquet}')"
    for how in ("spool", "rerun"):
        out = tmp_path / f"{how}.parquet"
        s = sample_query(query, str(out), ratio=0.25, temp_dir=str(weird), materialize=how, memory_limit="1GB")
        assert s.kept == 5000 and out.is_file()
    assert os.listdir(weird) == []


def test_jobs_file_path_is_a_parameter(tmp_path, cloud):
    jobs = tmp_path / "j'); COPY (SELECT 1) TO 'PWNED.csv'; --.csv"
    jobs.write_text(f"output,inputs,ratio\n{tmp_path / 'o.parquet'},{cloud},0.1\n")
    [job] = read_jobs(str(jobs))
    assert job.inputs == [str(cloud)] and job.options == {"ratio": 0.1}
    assert not list(tmp_path.glob("PWNED*")) and not list(Path.cwd().glob("PWNED*"))


def test_identifier_quotes_every_name():
    con = duckdb.connect()
    for name in ['red', 'a"b', "x'; DROP TABLE t; --", "__prism_r", ""]:
        if not name:
            continue
        got = con.execute(f"SELECT 1 AS {identifier(name)}").description[0][0]
        assert got == name


@pytest.mark.parametrize("column", ["__prism_r", "__prism_g", "__prism_b", "__prism_src", "__prism_row",
                                    "__prism_id", "__prism_bin", "__prism_rec", "__prism_priority",
                                    "__prism_quota", "__prism_shift", "__prism_ordinal", "__prism_file"])
def test_a_user_column_named_like_the_macros_own_changes_nothing(tmp_path, column):
    rng = np.random.default_rng(1)
    n = 6000
    rgb = random_colors(n, seed=2, palette=300)
    base = {"x": np.arange(n, dtype=np.int64), "red": rgb[:, 0].astype(np.uint16),
            "green": rgb[:, 1].astype(np.uint16), "blue": rgb[:, 2].astype(np.uint16)}
    plain = write_parquet(tmp_path / "plain.parquet", base)
    evil = write_parquet(tmp_path / "evil.parquet", {**base, column: rng.integers(0, 1 << 20, n)})
    con = register(duckdb.connect())
    want = con.execute("SELECT x FROM prism_sample_parquet(?, ratio := 0.1)", [str(plain)]).fetchall()
    got = con.execute(f"SELECT x, {identifier(column)} FROM prism_sample_parquet(?, ratio := 0.1)",
                      [str(evil)]).fetchall()
    assert [r[0] for r in got] == [r[0] for r in want] and len(want) == 600
    con.execute("CREATE TABLE t AS SELECT * FROM read_parquet(?)", [str(evil)])
    con.execute("CREATE TABLE p AS SELECT * FROM read_parquet(?)", [str(plain)])
    a = con.execute("SELECT x FROM prism_sample(p, ratio := 0.1, id := 'x')").fetchall()
    b = con.execute(f"SELECT x, {identifier(column)} FROM prism_sample(t, ratio := 0.1, id := 'x')").fetchall()
    assert [r[0] for r in b] == [r[0] for r in a]
    # the user's column comes back unchanged
    values = dict(zip(base["x"].tolist(), pq.read_table(evil).column(column).to_pylist()))
    assert all(values[x] == v for x, v in b)


# -- category 5: OS errors are documented codes ---------------------------------------------------

def _obey_permissions():
    """In the child, before exec: as root, drop the capabilities that ignore file permissions."""
    if ROOT:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        for cap in (1, 2):  # CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH, from the bounding set (gone after exec)
            if libc.prctl(24, cap, 0, 0, 0) != 0:  # PR_CAPBSET_DROP
                raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


@pytest.fixture
def open_tmp(tmp_path):
    return tmp_path


def run_cli(*args, cwd=None, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([*prism_stream_command(), *map(str, args)], capture_output=True, text=True, cwd=cwd,
                          timeout=300, **kw)


def test_permission_errors_are_documented_codes(open_tmp):
    src = write_las(open_tmp / "in.las", random_colors(5000, seed=1))
    os.chmod(src, 0o644)
    ro = open_tmp / "ro"
    ro.mkdir(mode=0o555)
    os.chmod(ro, 0o555)
    secret = write_las(open_tmp / "secret.las", random_colors(100, seed=1))
    os.chmod(secret, 0o000)
    cases = [
        ((src, ro / "o.parquet", "--ratio", "0.1"), 8, "ro"),
        ((src, f"{ro / 'd'}/", "--ratio", "0.1"), 8, "ro"),
        ((secret, open_tmp / "o.parquet", "--ratio", "0.1"), 3, "secret.las"),
        ((src, open_tmp / "o.parquet", "--ratio", "0.1", "--temp-dir", ro), 8, "ro"),
        ((src, open_tmp / "o.parquet", "--ratio", "0.1", "--temp-dir", open_tmp / "missing"), 8, "missing"),
        ((src, open_tmp / "o.parquet", "--ratio", "0.1", "--summary", ro / "s.json"), 8, "s.json"),
    ]
    for args, code, name in cases:
        done = run_cli(*args, "--quiet", preexec_fn=_obey_permissions)
        assert done.returncode == code, (args, done.stderr)
        one_error_line(done.stderr, name)
        assert not (open_tmp / "o.parquet").exists()
    assert os.listdir(ro) == []


def _full_disk():
    resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))


def test_a_full_temp_folder_is_exit_8_and_leaves_nothing(tmp_path):
    src = write_las(tmp_path / "in.las", random_colors(100_000, seed=1))
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    out = tmp_path / "out" / "o.parquet"
    out.parent.mkdir()
    done = run_cli(src, out, "--ratio", "0.1", "--temp-dir", tmp, "--quiet", "--chunk-size", "10000",
                   preexec_fn=_full_disk)
    assert done.returncode == 8, done.stderr
    one_error_line(done.stderr, str(tmp))
    assert os.listdir(tmp) == [] and os.listdir(out.parent) == []


@pytest.mark.parametrize("command,out_name", [("sample", "o.laz"), ("sample", "o.las"), ("sample", "o.copc.laz"),
                                              ("rank", "o.laz"), ("sample", "tiles/*.laz")])
def test_a_full_disk_under_a_las_output_is_exit_8_and_leaves_nothing(tmp_path, command, out_name):
    """A write the disk refuses (here: the file size limit) while LAZ is compressed: lazrs reports only that
    'Failed to call write' (internal error 70); the writer's file remembers the OSError behind it."""
    from conftest import user_env

    src = write_las(tmp_path / "in.las", random_colors(100_000, seed=1))
    folder = tmp_path / "out"
    folder.mkdir()
    out = folder / out_name
    args = [command, src, out] + (["--ratio", "0.9"] if command == "sample" else []) + ["--quiet"]
    done = run_cli(*args, preexec_fn=_full_disk, env=user_env())  # held in memory: no temporary files
    assert done.returncode == 8, done.stderr
    one_error_line(done.stderr, f"{folder}{os.sep}", "cannot write")
    assert os.listdir(folder) == []


def test_a_full_disk_under_a_dask_output_names_the_part_in_the_output(tmp_path):
    """A part a worker could not write is named in the output folder, where it would have been published
    (its sink named it beside the folder: a file that never exists); exit 8, nothing left."""
    pytest.importorskip("distributed")
    src = write_las(tmp_path / "in.las", random_colors(100_000, seed=1))
    folder = tmp_path / "out"
    folder.mkdir()
    done = run_cli(src, folder / "dk", "--ratio", "0.9", "--dask", "local:1", "--reads", "one", "--quiet",
                   preexec_fn=_full_disk)
    assert done.returncode == 8, done.stderr
    one_error_line(done.stderr, f"{folder / 'dk'}{os.sep}part-", "cannot write the output")
    assert os.listdir(folder) == []


def test_bad_dask_address_is_one_line(tmp_path, cloud):
    pytest.importorskip("distributed")
    done = run_cli(cloud, tmp_path / "o", "--ratio", "0.1", "--dask", "foo bar", "--quiet")
    assert done.returncode in (2, 9), done.stderr
    one_error_line(done.stderr, "foo bar")
    assert not (tmp_path / "o").exists()


# -- python -m prism_stream -------------------------------------------------------------------

def test_python_m_prism_stream_is_the_command_line(tmp_path, cloud):
    done = subprocess.run([sys.executable, "-m", "prism_stream", "--version"], capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.startswith("prism-stream "), done.stderr
    out = tmp_path / "o.parquet"
    done = subprocess.run([sys.executable, "-m", "prism_stream", str(cloud), str(out), "--ratio", "0.1", "--json"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["kept"] == pq.read_metadata(out).num_rows == 2000
    done = subprocess.run([sys.executable, "-m", "prism_stream", str(cloud), str(out), "--ratio", "0.1"],
                          capture_output=True, text=True)
    assert done.returncode == 7
    one_error_line(done.stderr, str(out))


def test_a_file_whose_name_holds_glob_characters_is_that_file(capsys, tmp_path, cloud):
    """`w[1].las` exists: it is the input, not a pattern that matches no file (a pattern is one only when no such
    file is there); `info` and `check` read it too."""
    named = tmp_path / "w[1] *?.las"
    named.write_bytes(Path(cloud).read_bytes())
    code, _, err = cli(capsys, named, tmp_path / "o.parquet", "--ratio", "0.1")
    assert code == 0, err
    assert pq.read_metadata(tmp_path / "o.parquet").num_rows > 0
    for command in ("info", "check"):
        code, out, err = cli(capsys, command, named)
        assert code in (0, 1) and "matches no file" not in err, (command, err)
    code, _, err = cli(capsys, tmp_path / "w[2].las", tmp_path / "o2.parquet", "--ratio", "0.1")
    assert code == 3 and "matches no file" in err
