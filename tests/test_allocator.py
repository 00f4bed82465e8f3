"""The process settings the command line makes before the libraries that read them load (the time each saves is in
bench/PROFILE.md): no transparent huge pages for Arrow's allocator (mimalloc) at any thread count, checked in a
fresh process by what mimalloc itself prints of its options, and the rule's cases one by one; and no BLAS thread pool
(numpy's OpenBLAS), checked by asking OpenBLAS. A value the user set stays."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from conftest import EDGE

from prism_stream_cli import options

PARQUET = EDGE / "pdal__1.2-with-color.parquet"


def _allow_thp(*args, env=None) -> str:
    """The value mimalloc took for allow_thp in a fresh ``prism-stream`` process (its verbose option list)."""
    run_env = {k: v for k, v in os.environ.items() if k != "MIMALLOC_ALLOW_THP"}
    run_env.update(MIMALLOC_VERBOSE="1", **(env or {}))
    done = subprocess.run([sys.executable, "-m", "prism_stream_cli.main", *map(str, args)],
                          capture_output=True, text=True, timeout=120, env=run_env)
    assert done.returncode == 0, done.stderr
    said = [line for line in done.stderr.splitlines() if "option 'allow_thp'" in line]
    if not said:  # an older pyarrow's mimalloc (2.0) has no such option, a build without mimalloc says nothing
        pytest.skip("this pyarrow's allocator has no allow_thp option")
    return said[0].split(":")[-1].strip()


def test_a_run_loads_arrow_without_huge_pages_at_any_thread_count(tmp_path):
    sample = (PARQUET, tmp_path / "out.parquet", "--ratio", "0.1", "--quiet", "--overwrite")
    assert _allow_thp(*sample, "--threads", "1") == "0"
    assert _allow_thp(*sample, "--threads", "2") == "0"
    assert _allow_thp(*sample) == "0"
    # the probe sees a value the user set
    assert _allow_thp(*sample, "--threads", "2", env={"MIMALLOC_ALLOW_THP": "1"}) == "1"


@pytest.mark.parametrize("command", [
    ("info", PARQUET, "--ratio", "0.1"),  # its pass one over the colors
    ("eval", PARQUET, "--ratio", "0.1", "--quiet"),
    ("rank", PARQUET, "{out}", "--quiet"),
    ("sql", f"SELECT * FROM read_parquet('{PARQUET}')", "{out}", "--ratio", "0.1", "--quiet"),
])
def test_every_command_that_decodes_loads_arrow_after_the_setting(tmp_path, command):
    args = [str(a).replace("{out}", str(tmp_path / "out.parquet")) for a in command]
    assert _allow_thp(*args, "--threads", "2") == "0"


@pytest.mark.parametrize("loaded, preset, want", [
    (False, None, "0"),
    (True, None, None),  # pyarrow loaded already: its allocator has read its options
    (False, "1", "1"),  # the user's value stays
])
def test_small_pages_rule(monkeypatch, loaded, preset, want):
    monkeypatch.delenv("MIMALLOC_ALLOW_THP", raising=False)
    if preset is not None:
        monkeypatch.setenv("MIMALLOC_ALLOW_THP", preset)
    modules = dict(sys.modules)
    if loaded:
        modules.setdefault("pyarrow", sys.modules.get("pyarrow") or object())
    else:
        modules.pop("pyarrow", None)
    monkeypatch.setattr(sys, "modules", modules)
    options.small_pages()
    assert os.environ.get("MIMALLOC_ALLOW_THP") == want


BLAS = """
import ctypes, os, sys
sys.argv = ["prism-stream", *sys.argv[1:]]
from prism_stream_cli.main import run
try:
    run()  # as the console script calls it: the process's own settings
except SystemExit as exc:
    code = exc.code
libs = {line.split()[-1] for line in open("/proc/self/maps") if "openblas" in line and line.split()[-1].endswith(".so")}
counts = []
for path in libs:
    lib = ctypes.CDLL(path)
    for name in ("scipy_openblas_get_num_threads64_", "openblas_get_num_threads64_", "openblas_get_num_threads"):
        if hasattr(lib, name):
            counts.append(getattr(lib, name)())
            break
print(code, counts)
"""


def _blas_threads(tmp_path, env=None):
    run_env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    run_env.update(env or {})
    done = subprocess.run([sys.executable, "-c", BLAS, str(PARQUET), str(tmp_path / "out.parquet"), "--ratio", "0.1",
                           "--quiet", "--overwrite"], capture_output=True, text=True, timeout=120, env=run_env)
    assert done.returncode == 0, done.stderr
    code, counts = done.stdout.strip().splitlines()[-1].split(" ", 1)
    assert code == "0", done.stdout
    if counts == "[]":
        pytest.skip("numpy's BLAS here is not OpenBLAS")
    return counts


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="OpenBLAS starts one thread a core: one here")
def test_a_run_starts_no_blas_thread_pool(tmp_path):
    assert _blas_threads(tmp_path) == "[1]"
    assert _blas_threads(tmp_path, {"OPENBLAS_NUM_THREADS": "2"}) == "[2]"  # the user's value stays


def test_the_default_threads_are_the_cores_this_process_may_use():
    """``taskset -c 0 prism-stream ...`` (or a container's CPU set): one thread by default, not the machine's count
    (a newcomer found two threads there, and huge pages on)."""
    from prism_stream.run.request import Request, cores

    assert cores() == len(os.sched_getaffinity(0))
    assert Request(ratio=0.1).workers == cores() and Request(ratio=0.1, threads=3).workers == 3
    done = subprocess.run(["taskset", "-c", "0", sys.executable, "-c",
                           "from prism_stream.run.request import Request; print(Request(ratio=0.1).workers)"],
                          capture_output=True, text=True, timeout=60)
    if done.returncode != 0 and "taskset" in (done.stderr or ""):
        pytest.skip("no taskset here")
    assert done.stdout.strip() == "1", done.stderr
