"""Under CI a skipped test fails the run, by name (the hooks in conftest.py).

`make test` installs every optional dependency and the test data is in the
repository, so under CI a skip can only mean a test that stopped running.
Each case runs pytest in a child process on a small suite beside a copy of
this folder's conftest.py.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

CONFTEST = Path(__file__).with_name("conftest.py")

SUITE = {
    "test_runs.py": "def test_runs():\n    assert True\n",
    "test_skips.py": "import pytest\n\n\ndef test_skips():\n    pytest.skip('no data')\n\n\n"
                     "@pytest.mark.xfail(reason='known', strict=True)\ndef test_xfails():\n    assert False\n",
    "test_skips_at_import.py": "import pytest\n\npytest.skip('no module', allow_module_level=True)\n",
}


def run_suite(folder: Path, files: list[str], ci: str | None, *args: str) -> subprocess.CompletedProcess:
    shutil.copyfile(CONFTEST, folder / "conftest.py")
    for name in files:
        (folder / name).write_text(SUITE[name])
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_", "CI"))}
    if ci is not None:
        env["CI"] = ci
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", *args, *files],
                          cwd=folder, env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("workers", [[], ["-n", "2"]], ids=["serial", "xdist"])
def test_a_skip_fails_the_run_under_ci_and_is_named(tmp_path, workers):
    done = run_suite(tmp_path, ["test_runs.py", "test_skips.py", "test_skips_at_import.py"], "true", *workers)
    assert done.returncode == pytest.ExitCode.TESTS_FAILED, done.stdout + done.stderr
    assert "2 skipped under CI: the run fails" in done.stdout, done.stdout
    assert "SKIPPED test_skips.py::test_skips - Skipped: no data" in done.stdout, done.stdout
    assert "SKIPPED test_skips_at_import.py - Skipped: no module" in done.stdout, done.stdout
    assert "test_xfails" not in done.stdout.split("skipped under CI")[1]  # an xfail is not a skip


def test_without_skips_ci_passes(tmp_path):
    done = run_suite(tmp_path, ["test_runs.py"], "true")
    assert done.returncode == pytest.ExitCode.OK, done.stdout + done.stderr
    assert "skipped under CI" not in done.stdout


def test_outside_ci_a_skip_is_reported_not_fatal(tmp_path):
    done = run_suite(tmp_path, ["test_runs.py", "test_skips.py"], None)
    assert done.returncode == pytest.ExitCode.OK, done.stdout + done.stderr
    assert "1 skipped" in done.stdout and "skipped under CI" not in done.stdout


@pytest.mark.parametrize("ci,fails", [(None, False), ("", False), ("false", False), ("0", False), ("no", False),
                                      ("true", True), ("1", True), ("yes", True)])
def test_what_counts_as_ci(monkeypatch, ci, fails):
    """The value of CI that makes a skip fail the run (one child run above shows the hook acting on it)."""
    from conftest import skips_fail_the_run

    if ci is None:
        monkeypatch.delenv("CI", raising=False)
    else:
        monkeypatch.setenv("CI", ci)
    assert skips_fail_the_run() is fails
