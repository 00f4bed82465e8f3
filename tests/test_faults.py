"""Faults: signals, kills and concurrent writers leave nothing behind and lose nothing (issue 10).

The fault-injection suite sends signals at generated moments of pass one,
the solve (the key cache complete, no output open yet) and pass two (the
output's temporary open): SIGINT for every output writer and for directory
mode (SIGTERM, SIGINT's handler with another exit code, for LAS: LAZ's writer), SIGKILL for Parquet and
directory mode (what a SIGKILL leaves is found by its staging names, the same for every format). No writer
is open before pass two, so the first two phases are signalled for Parquet and directory mode, the other
writers in pass two. After each: no output; no temporary (after a SIGKILL, the
next run removes the ones the killed run left); and a clean rerun is byte for
byte the output of an undisturbed run.

The phase is read from the file system: the key cache growing (pass one),
complete with no output temporary yet (solve and cutoffs), the staging
folder beside the output present (pass two).
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from prism_stream.run import staging

from conftest import prism_stream_command, random_colors, write_las

N = 200_000
SIGNALS = {"SIGINT": (signal.SIGINT, 130), "SIGTERM": (signal.SIGTERM, 143), "SIGKILL": (signal.SIGKILL, None)}
PHASES = ("pass one", "solve", "pass two")
FORMATS = ("parquet", "las", "laz", "ply", "directory")


def one_error_line(err: str, *must: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("prism-stream: error: "), err
    for m in must:
        assert m in lines[0], err
    return lines[0]


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("faults") / "in"
    folder.mkdir()
    write_las(folder / "a.las", random_colors(N, seed=1, palette=3000), point_format=3)
    write_las(folder / "b.las", random_colors(N // 3, seed=2, palette=500, depth=16), point_format=3)
    return folder


def command(inputs: Path, fmt: str, out_dir: Path, temp_dir: Path) -> tuple[list[str], Path]:
    if fmt == "directory":
        target = out_dir / "tiles"
        args = [str(inputs), str(target) + os.sep, "--format", "laz"]
    else:
        target = out_dir / f"sample.{fmt}"
        args = [str(inputs / "a.las"), str(inputs / "b.las"), str(target)]
    return [*prism_stream_command(), *args, "--ratio", "0.2", "--chunk-size", "50000", "--temp-dir", str(temp_dir),
            "--quiet"], target


def output_bytes(target: Path) -> dict:
    """Each output file's content, all but its provenance's command line (which names this run's folders).

    Points, header, metadata and the rest of the provenance must be the same; only the command line's
    length shifts what follows it in the file, so the files are compared by part, not as raw bytes.
    """
    import json

    import laspy
    import pyarrow.parquet as pq

    def provenance(raw) -> dict:
        d = json.loads(raw)
        d.pop("command", None)
        return d

    out = {}
    for p in sorted(target.iterdir()) if target.is_dir() else [target]:
        if p.suffix == ".parquet":
            f = pq.ParquetFile(p)
            meta = dict(f.schema_arrow.metadata)
            meta[b"prism_stream"] = provenance(meta[b"prism_stream"])
            out[p.name] = (f.read().replace_schema_metadata(None).to_pydict(), meta)
        elif p.suffix in (".las", ".laz"):
            las = laspy.read(p)
            vlrs = [provenance(bytes(v.record_data)) if v.user_id == "prism-stream" else (v.user_id, v.record_id)
                    for v in las.header.vlrs]
            h = las.header
            out[p.name] = (las.points.array.tobytes(), list(h.scales), list(h.offsets), h.point_count,
                           list(h.number_of_points_by_return), str(h.parse_crs()), vlrs)
        else:  # PLY: the provenance is in comment lines of the header (one, or more for a long one)
            from prism_stream.formats.ply import _is_provenance, provenance_text

            head, body = p.read_bytes().split(b"end_header\n", 1)
            lines = head.decode("ascii").split("\n")
            comments = [ln[len("comment "):] for ln in lines if ln.startswith("comment ")]
            lines = [ln for ln in lines if not (ln.startswith("comment ") and _is_provenance(ln[len("comment "):]))]
            out[p.name] = (lines, provenance(provenance_text(comments)), body)
    return out


def temporaries(*folders: Path) -> list[str]:
    found = []
    for folder in folders:
        for dirpath, dirnames, names in os.walk(folder):
            found += [os.path.join(dirpath, n) for n in dirnames + names if staging.is_temporary(n)]
    return found


def owned(pid: int) -> str:
    """What the temporaries of process ``pid`` carry in their names."""
    return f"{staging.HOST}-{pid}-"


def cache_bytes(temp_dir: Path, pid: int) -> int:
    total = 0
    for d in temp_dir.glob(staging.WORK_PREFIX + owned(pid) + "*"):
        try:
            total += sum(f.stat().st_size for f in d.iterdir())
        except FileNotFoundError:
            pass
    return total


def phase_of(out_dir: Path, temp_dir: Path, complete: int, pid: int) -> str | None:
    """The phase of run ``pid`` (the temporaries of killed runs may lie beside its own)."""
    if any(owned(pid) in os.path.basename(t) for t in temporaries(out_dir)):
        return "pass two"
    c = cache_bytes(temp_dir, pid)
    if c >= complete:
        return "solve"
    return "pass one" if c > 0 else None


def disturb(cmd, out_dir: Path, temp_dir: Path, sig: int, phase: str, delay: float, complete: int) -> tuple:
    """Run ``cmd``, send ``sig`` ``delay`` seconds into ``phase``: (exit code, stderr, phase when signalled)."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        want = PHASES.index(phase)
        deadline = time.monotonic() + 120
        while proc.poll() is None and time.monotonic() < deadline:
            now = phase_of(out_dir, temp_dir, complete, proc.pid)
            if now is not None and PHASES.index(now) >= want:
                break
            time.sleep(0.0005)
        time.sleep(delay)
        hit = phase_of(out_dir, temp_dir, complete, proc.pid)
        if proc.poll() is None:
            proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return proc.returncode, err, hit


@pytest.fixture(scope="module")
def undisturbed(inputs, tmp_path_factory):
    """A format's output of an undisturbed run (written where the disturbed runs write), made on first use: each
    test worker runs only the formats of the cases it was given."""
    refs = {}

    def reference(fmt: str) -> dict:
        if fmt not in refs:
            base = tmp_path_factory.mktemp(f"ref-{fmt}")
            (base / "out").mkdir()
            (base / "tmp").mkdir()
            cmd, target = command(inputs, fmt, base / "out", base / "tmp")
            done = subprocess.run(cmd, capture_output=True, text=True)
            assert done.returncode == 0, done.stderr
            refs[fmt] = output_bytes(target)
        return refs[fmt]

    return reference


# SIGINT on every writer (each cleans up its own temporary; LAS is LAZ's writer uncompressed, and takes
# SIGTERM, whose handler is SIGINT's with another exit code); SIGKILL, where nothing cleans up and the next
# run removes what the killed one left by its staging names (the same for every format), on a file and on
# directory mode (SIGTERM's exit code at start-up and in a batch: below). No writer is open before pass two:
# pass one and the solve are signalled for a file and for directory mode, the other writers in pass two.
FAULTS = ([(fmt, "SIGINT") for fmt in FORMATS if fmt != "las"]
          + [(fmt, "SIGKILL") for fmt in ("parquet", "directory")] + [("las", "SIGTERM")])
EVERY_PHASE = ("parquet", "directory")


@pytest.mark.parametrize("fmt,signame", FAULTS)
@settings(max_examples=1, deadline=None, suppress_health_check=list(HealthCheck))
@given(delays=st.tuples(*[st.floats(min_value=0.0, max_value=0.12)] * 3))
def test_fault_injection(tmp_path_factory, inputs, undisturbed, fmt, signame, delays):
    phases = PHASES if fmt in EVERY_PHASE else PHASES[-1:]
    delays = delays[-len(phases):]
    base = tmp_path_factory.mktemp("fault")
    out_dir, temp_dir = base / "out", base / "tmp"
    out_dir.mkdir()
    temp_dir.mkdir()
    cmd, target = command(inputs, fmt, out_dir, temp_dir)
    sig, code = SIGNALS[signame]
    complete = 4 * (N + N // 3)
    hits, finished = [], []
    for phase, delay in zip(phases, delays):
        rc, err, hit = disturb(cmd, out_dir, temp_dir, sig, phase, delay, complete)
        hits.append(hit)
        finished.append(rc == 0)
        if rc == 0:  # the run ended before the signal: a complete output, the same as an undisturbed run's
            assert output_bytes(target) == undisturbed(fmt)
            shutil.rmtree(target) if target.is_dir() else target.unlink()
            continue
        if code is None:
            assert rc == -signal.SIGKILL, err
        else:
            assert rc == code, err
            assert "Traceback" not in err
            one_error_line(err, "no output was written")
            assert temporaries(out_dir, temp_dir) == [], "an interrupted run left temporaries"
        assert not target.exists() or (target.is_dir() and not any(
            p for p in target.iterdir() if not staging.is_temporary(p.name))), "an output was published"
    assert hits.count(None) == 0, f"a signal came before pass one: {hits}"
    # a signal in pass one or the solve finds the run still going (pass two is ahead): the case tests a fault
    assert not any(finished[:len(phases) - 1]), f"a run signalled in pass one or the solve had finished: {hits}"
    print(f"{fmt} {signame}: signalled in {hits}")
    done = subprocess.run(cmd, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert temporaries(out_dir, temp_dir) == [], "the clean run did not remove the killed runs' temporaries"
    assert output_bytes(target) == undisturbed(fmt)


# -- signals at start-up and the exit codes -------------------------------------------------------

@settings(max_examples=4, deadline=None, suppress_health_check=list(HealthCheck))
@given(delay=st.floats(min_value=0.0, max_value=0.35), signame=st.sampled_from(["SIGINT", "SIGTERM"]))
def test_a_signal_during_start_up_is_one_line_never_a_traceback(tmp_path_factory, inputs, delay, signame):
    base = tmp_path_factory.mktemp("early")
    sig, code = SIGNALS[signame]
    out = base / "o.parquet"
    proc = subprocess.Popen([*prism_stream_command(), str(inputs / "a.las"), str(out), "--ratio", "0.1",
                             "--temp-dir", str(base), "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    time.sleep(delay)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    if "Traceback" in err:
        # Python's own start-up (site, before the console script's first line) is out of our reach; the
        # traceback must not run through prism-stream's code
        assert not re.search(r'File "[^"]*/(prism_stream|cli)/', err), err
        assert proc.returncode != 0
    elif proc.returncode == -sig:
        # the signal came before the interpreter ran a line of prism-stream: the default action, no output at all
        assert err == ""
    else:
        # what the child inherits from this process decides a signal's fate before its handlers: say it
        assert proc.returncode == code, (err, signal.getsignal(sig), signal.pthread_sigmask(signal.SIG_BLOCK, []))
        one_error_line(err, "no output was written")
    assert not out.exists() and temporaries(base) == []


# A run whose command is wrapped so that, just before it starts, a weakref callback runs with the signal
# arriving inside it: Python cannot raise there ("Exception ignored in ..." and the run would go on); the
# import system's module locks have such callbacks, so a signal during start-up can land in one.
_SIGNAL_IN_A_CALLBACK = """
import os, signal, sys, weakref
import prism_stream_cli.main as main
from prism_stream_cli.app import app

class Thing:
    pass

def callback(_):
    os.kill(os.getpid(), signal.SIG{name})
    for _ in range(100_000):  # the handler runs here, inside the callback
        pass

thing = Thing()
ref = weakref.ref(thing, callback)
invoke = app.invoke

def signalled_invoke(ctx):
    global thing
    thing = None  # the callback runs, and the signal with it
    return invoke(ctx)

app.invoke = signalled_invoke
sys.argv = ["prism-stream", *sys.argv[1:]]
main.run()
"""


def test_a_signal_inside_a_callback_while_an_error_unwinds_is_still_the_interrupt(tmp_path):
    """The callback runs while a missing input's error unwinds: the run ends as interrupted (130), not with
    the error's code, as an interrupt that could be raised would."""
    script = _SIGNAL_IN_A_CALLBACK.replace("{name}", "INT").replace(
        "    thing = None  # the callback runs, and the signal with it\n    return invoke(ctx)",
        "    try:\n        return invoke(ctx)\n    except BaseException:\n        thing = None\n        raise")
    assert "except BaseException" in script
    out = tmp_path / "o.parquet"
    proc = subprocess.run([sys.executable, "-c", script, str(tmp_path / "missing.las"), str(out), "--ratio", "0.1",
                           "--quiet"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 130, proc.stderr
    one_error_line(proc.stderr, "interrupted")
    assert not out.exists()


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_a_signal_inside_a_callback_python_cannot_raise_from_still_interrupts(tmp_path, inputs, signame):
    sig, code = SIGNALS[signame]
    out = tmp_path / "o.parquet"
    proc = subprocess.run([sys.executable, "-c", _SIGNAL_IN_A_CALLBACK.replace("{name}", signame[3:]),
                           str(inputs / "a.las"), str(out), "--ratio", "0.1", "--temp-dir", str(tmp_path), "--quiet"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == code, proc.stderr
    one_error_line(proc.stderr, "no output was written")
    assert not out.exists() and temporaries(tmp_path) == []


def test_sigint_ignored_by_the_parent_stays_ignored(tmp_path, inputs):
    """POSIX's convention, and Python's own: sh starts a script's `cmd &` with SIGINT ignored (so the terminal's
    Ctrl-C spares it), and the run keeps it ignored: SIGINTs all through it change nothing."""
    import pyarrow.parquet as pq

    out = tmp_path / "o.parquet"
    cmd = [*prism_stream_command(), str(inputs / "a.las"), str(out), "--ratio", "0.1", "--temp-dir", str(tmp_path),
           "--quiet"]
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)  # what the child inherits, as from sh's `&`
    try:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    finally:
        signal.signal(signal.SIGINT, before)
    sent = 0
    while proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        sent += 1
        time.sleep(0.05)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0 and err == "", err
    assert sent >= 5  # the run was signalled all through, from its start-up on
    assert pq.read_metadata(out).num_rows == N // 10 and temporaries(tmp_path) == []


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_a_signal_blocked_by_the_parent_still_interrupts(tmp_path, inputs, signame):
    """A signal mask is inherited through exec: started by a parent that blocks SIGINT/SIGTERM (a supervisor
    in a critical section, a thread pool starting up), a run must not hold the signal pending to the end and
    exit 0 as if never interrupted."""
    sig, code = SIGNALS[signame]
    out = tmp_path / "o.parquet"
    proc = subprocess.Popen([*prism_stream_command(), str(inputs / "a.las"), str(out), "--ratio", "0.1",
                             "--temp-dir", str(tmp_path), "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=lambda: signal.pthread_sigmask(signal.SIG_BLOCK, [sig]))
    time.sleep(0.05)  # while the interpreter starts, before the run's handlers: the signal waits, blocked
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err
    one_error_line(err, "no output was written")
    assert not out.exists() and temporaries(tmp_path) == []


def test_stale_temporaries_of_dead_owners_are_removed_and_live_ones_kept(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        names = {
            "dead_file": f".o.parquet.{staging.HOST}-{dead.pid}-0123abcd{staging.SUFFIX}",
            "dead_dir": f".o.parquet.{staging.HOST}-{dead.pid}-89abcdef{staging.SUFFIX}",
            "dead_work": f"{staging.WORK_PREFIX}{staging.HOST}-{dead.pid}-0badcafe",
            "live": f".o.parquet.{staging.HOST}-{live.pid}-0123abcd{staging.SUFFIX}",
            "other_host": f".o.parquet.ffffff-{dead.pid}-0123abcd{staging.SUFFIX}" if staging.HOST != "ffffff"
            else f".o.parquet.000000-{dead.pid}-0123abcd{staging.SUFFIX}",
            "not_ours": f".o.parquet.{dead.pid}.prism-tmp",
            "user_file": "prism-stream-notes.txt",
        }
        for key, name in names.items():
            p = tmp_path / name
            if key in ("dead_dir", "dead_work"):
                p.mkdir()
                (p / "inside").write_text("x")
            else:
                p.write_text("x")
        gone = {os.path.basename(p) for p in staging.sweep(str(tmp_path))}
        assert gone == {names["dead_file"], names["dead_dir"], names["dead_work"]}
        assert sorted(os.listdir(tmp_path)) == sorted(names[k] for k in ("live", "other_host", "not_ours",
                                                                          "user_file"))
    finally:
        live.kill()
        live.wait()


def test_a_temporary_of_an_owner_that_exited_unreaped_is_stale(tmp_path):
    """Found in a fresh clone's suite: a batch killed with its workers left a worker exited but not yet
    reaped (a zombie answers a signal), and the rerun's sweep kept its staged file as a live run's."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    try:
        deadline = time.time() + 30
        while time.time() < deadline:  # exited, and not waited for: a zombie
            with open(f"/proc/{gone.pid}/stat", "rb") as f:
                if f.read().rsplit(b")", 1)[1][1:2] == b"Z":
                    break
            time.sleep(0.01)
        name = f".o.parquet.{staging.HOST}-{gone.pid}-0123abcd{staging.SUFFIX}"
        (tmp_path / name).write_text("x")
        assert [os.path.basename(p) for p in staging.sweep(str(tmp_path))] == [name]
        assert os.listdir(tmp_path) == []
    finally:
        gone.wait()


def test_temporaries_are_registered_before_they_exist(tmp_path, monkeypatch):
    """An interrupt between a temporary's creation and its first use is still cleaned up by discard_all."""
    real_open = os.open

    def interrupted_open(path, *a, **kw):
        fd = real_open(path, *a, **kw)
        os.close(fd)
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "open", interrupted_open)
    with pytest.raises(KeyboardInterrupt):
        staging.new_file(str(tmp_path / "o.parquet"))
    monkeypatch.setattr(os, "open", real_open)
    assert len(os.listdir(tmp_path)) == 1
    staging.discard_all()
    assert os.listdir(tmp_path) == []


# -- concurrent writers ---------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["parquet", "directory"])
def test_two_runs_writing_one_output_exactly_one_wins(tmp_path, inputs, fmt):
    out_dir, temp_dir = tmp_path / "out", tmp_path / "tmp"
    out_dir.mkdir()
    temp_dir.mkdir()
    cmd, target = command(inputs, fmt, out_dir, temp_dir)
    seeds = [cmd + ["--seed", "1"], cmd + ["--seed", "2"]]
    procs = [subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for c in seeds]
    results = [(p.wait(timeout=300), p.communicate()[1]) for p in procs]
    codes = sorted(rc for rc, _ in results)
    assert codes == [0, 7], results
    loser = next(err for rc, err in results if rc == 7)
    # its notes of the output it wrote (said before the publish, which lost the race), then its one error
    one_error_line("\n".join(ln for ln in loser.splitlines() if not ln.startswith("prism-stream: warning: ")),
                   "another run")
    winner = seeds[[rc for rc, _ in results].index(0)]
    # the published output is the winner's, whole
    check_dir = tmp_path / "check"
    check_dir.mkdir()
    ref_cmd, ref_target = command(inputs, fmt, check_dir, temp_dir)
    assert subprocess.run(ref_cmd + winner[-2:], capture_output=True).returncode == 0
    assert output_bytes(target) == output_bytes(ref_target)
    assert temporaries(out_dir, temp_dir) == []


def test_publish_never_replaces_what_appeared_meanwhile(tmp_path):
    """The claim itself: a destination created after the start is never replaced without --overwrite."""
    src = tmp_path / "staged"
    src.write_text("mine")
    dest = tmp_path / "dest"
    dest.write_text("theirs")
    with pytest.raises(FileExistsError):
        staging.publish_new(str(src), str(dest))
    assert dest.read_text() == "theirs" and src.read_text() == "mine"
    os.unlink(dest)
    staging.publish_new(str(src), str(dest))
    assert dest.read_text() == "mine"


# -- batch: a worker dies with its batch ---------------------------------------------------------

def _marked(mark: str) -> list[int]:
    pids = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            with open(f"/proc/{pid}/environ", "rb") as f:
                if f"PRISM_TEST_MARK={mark}".encode() in f.read().split(b"\0"):
                    with open(f"/proc/{pid}/stat") as s:
                        if s.read().split(")")[-1].split()[0] != "Z":
                            pids.append(int(pid))
        except OSError:
            pass
    return pids


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG and /proc are Linux's")
@settings(max_examples=4, deadline=None, suppress_health_check=list(HealthCheck))
@given(delay=st.floats(min_value=0.0, max_value=2.0))
def test_batch_workers_die_with_a_killed_batch_even_during_their_start_up(tmp_path_factory, inputs, delay):
    base = tmp_path_factory.mktemp("batch")
    jobs = base / "jobs.csv"
    jobs.write_text("output,inputs,ratio\n" + "".join(f"{base / f'o{i}.parquet'},{inputs / 'a.las'},0.1\n"
                                                      for i in range(2)))
    mark = uuid.uuid4().hex
    env = {**os.environ, "PRISM_TEST_MARK": mark}
    proc = subprocess.Popen([*prism_stream_command(), "batch", str(jobs), "--jobs", "2", "--log",
                             str(base / "runs.duckdb"), "--quiet"], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    time.sleep(delay)
    proc.kill()
    proc.wait()
    deadline = time.monotonic() + 60
    while _marked(mark) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = _marked(mark)
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    assert left == [], "batch workers outlived their batch"


def test_batch_sigterm_is_143_and_one_line(tmp_path, inputs):
    jobs = tmp_path / "jobs.csv"
    jobs.write_text(f"output,inputs,ratio\n{tmp_path / 'o.parquet'},{inputs / 'a.las'},0.1\n")
    proc = subprocess.Popen([*prism_stream_command(), "batch", str(jobs), "--log", str(tmp_path / "runs.duckdb")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (tmp_path / "runs.duckdb").exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.3)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    one_error_line(err, "terminated")
    assert not (tmp_path / "o.parquet").exists() and temporaries(tmp_path) == []


# -- dask: an interrupt is one line, not the workers' warnings ----------------------------------

@settings(max_examples=1, deadline=None, suppress_health_check=list(HealthCheck))
@given(delay=st.floats(min_value=0.1, max_value=1.0))
def test_dask_interrupted_is_one_line(tmp_path_factory, inputs, delay):
    """The interrupt comes ``delay`` after the run's staging folder appears (the cluster is up and pass one
    starts), in a run of 3M points more: a fixed 3-6 s after the start found the run of the small inputs
    (2.8 s on a quiet machine) already finished now and then."""
    pytest.importorskip("distributed")
    base = tmp_path_factory.mktemp("dask")
    out = base / "out"
    big = base / "big.las"
    write_las(big, random_colors(3_000_000, seed=3, palette=3000), point_format=3)
    # Ctrl-C in a terminal reaches the whole process group: the driver, the nannies and the workers
    proc = subprocess.Popen([*prism_stream_command(), str(big), str(inputs / "b.las"), str(out),
                             "--ratio", "0.2", "--dask", "local:2", "--quiet"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    started = time.monotonic()
    while proc.poll() is None and not list(base.glob(".out.*")) and time.monotonic() - started < 120:
        time.sleep(0.02)
    time.sleep(delay)
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    one_error_line(err, "interrupted")
    assert not out.exists() and temporaries(base) == []
