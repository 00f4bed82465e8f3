"""The kernel warm-up loads, beside the decoding, the very machine code a run then calls.

A warm-up that loads a kernel for other argument types than the run's (a
writable array where the run passes a read-only memory map, say) costs time
on the second core and saves none on the first: the run then loads its own.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

REAL = Path(__file__).parent / "data" / "real"

SCRIPT = """
import json, sys
from numba.core.registry import CPUDispatcher
from prism_stream.core import jit, warm

def loaded():
    return {n: len(v.signatures) for n, v in vars(jit).items() if isinstance(v, CPUDispatcher)}

warm.warm_up()
warm.wait()
before = loaded()
import prism_stream
prism_stream.sample(sys.argv[1], sys.argv[2], ratio=float(sys.argv[3]))
print(json.dumps({"before": before, "after": loaded()}))
"""


def _loads(src: Path, out: Path, ratio: float) -> dict:
    # the streaming path, which uses the kernels; numba's JIT (this is its warm-up), not the ahead-of-time build
    env = dict(os.environ, PRISM_STREAM_MEMORY_POINTS="0", PRISM_STREAM_AOT="0")
    done = subprocess.run([sys.executable, "-c", SCRIPT, str(src), str(out), str(ratio)], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_the_warm_up_loads_what_the_end_of_a_run_calls(tmp_path):
    for src in (REAL / "pdal__autzen_trim.las", REAL / "laspy__fullwave.laz"):
        got = _loads(src, tmp_path / (src.stem + ".parquet"), 0.01)
        warmed = {n for n, c in got["before"].items() if c}
        assert {"splitmix64_array", "priorities_of", "push_bottom_range", "keep_mask_ids"} <= warmed
        for name in warmed:
            assert got["after"][name] == got["before"][name], (src.name, name, "the run loaded its own version")
        # the run did call the end-of-run kernels (else this test would show nothing)
        assert got["after"]["candidate_scan"] >= 1


BLAS_SCRIPT = """
import json, sys
from prism_stream.core import warm
warm.without_blas()
import prism_stream
prism_stream.sample(sys.argv[1], sys.argv[2], ratio=0.01)
during = "scipy.linalg" in sys.modules
import scipy.linalg  # importable again once the warm-up ended
print(json.dumps({"during": during, "after": scipy.linalg.norm([3.0, 4.0])}))
"""


def test_without_blas_the_run_never_imports_scipy_linalg_and_leaves_it_importable(tmp_path):
    """``prism-stream sample`` skips numba's BLAS search (0.2-0.3 s of scipy.linalg imports): the run's
    kernels still work, and scipy.linalg stays importable after the warm-up."""
    env = dict(os.environ, PRISM_STREAM_MEMORY_POINTS="0")
    src, out = REAL / "pdal__autzen_trim.las", tmp_path / "o.parquet"
    done = subprocess.run([sys.executable, "-c", BLAS_SCRIPT, str(src), str(out)], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got == {"during": False, "after": 5.0}
    import pyarrow.parquet as pq
    assert pq.read_metadata(out).num_rows > 0


def _run_on_a_terminal(args: list, env: dict, until: str | None = None) -> tuple[int, str]:
    """The command line with its stderr on a pseudo-terminal (as a user's shell has it): exit code, stderr.
    ``until``: stop the run (SIGINT) once its stderr shows this text."""
    import pty
    import signal

    master, slave = pty.openpty()
    proc = subprocess.Popen([sys.executable, "-m", "prism_stream_cli.main", *args], env=env, stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=slave)
    os.close(slave)
    seen = b""
    while True:
        try:
            data = os.read(master, 4096)
        except OSError:  # EIO: the child closed its end
            break
        if not data:
            break
        seen += data
        if until is not None and until.encode() in seen.replace(b"\r\n", b"\n") and proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            until = None
    os.close(master)
    return proc.wait(timeout=300), seen.decode(errors="replace")


def test_a_first_compile_is_announced_on_a_terminal_once(tmp_path):
    """With an empty numba cache the first streaming run on a terminal says it compiles; the next one, which
    loads the cache, says nothing."""
    from prism_stream.run.progress import COMPILING

    # numba's JIT with an empty cache (what the announcement is about: a build compiled ahead of time has none)
    env = dict(os.environ, PRISM_STREAM_MEMORY_POINTS="0", NUMBA_CACHE_DIR=str(tmp_path / "cache"),
               PRISM_STREAM_AOT="0")
    args = [str(REAL / "pdal__warsaw_small.las"), str(tmp_path / "o.parquet"), "--ratio", "0.1", "--overwrite"]
    code, first = _run_on_a_terminal(args, env, until=COMPILING.strip())  # stopped there: the compile is long
    assert code == 130 and COMPILING.strip() in first.replace("\r\n", "\n"), first
    # the cache `make test` filled (its warm-up), as a run
    env = dict(os.environ, PRISM_STREAM_MEMORY_POINTS="0", PRISM_STREAM_AOT="0")
    code, second = _run_on_a_terminal(args, env)
    assert code == 0 and "compiling" not in second, second


def test_no_notice_off_a_terminal_or_when_quiet(monkeypatch, capsys):
    """A script's stderr (not a terminal) and --quiet (progress off) get no notice, even with nothing cached."""
    from prism_stream.core import warm
    from prism_stream.run import progress

    monkeypatch.setattr(warm, "cached", lambda: False)
    for tty, enabled in ((False, True), (True, False)):
        monkeypatch.setattr(progress, "_noticed", [False])
        monkeypatch.setattr(progress.sys.stderr, "isatty", lambda: tty, raising=False)
        progress.notice_compiling(enabled)
        assert capsys.readouterr().err == ""
    monkeypatch.setattr(progress, "_noticed", [False])
    monkeypatch.setattr(progress.sys.stderr, "isatty", lambda: True, raising=False)
    progress.notice_compiling(True)  # and the same call on a terminal does say it: the test above can fail
    assert capsys.readouterr().err == progress.COMPILING
