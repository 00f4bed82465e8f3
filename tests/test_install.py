"""The wheel installs and runs outside the source tree (what `make dist` builds and the README tells to install).

The wheel is built from a copy of the sources (the checkout is left as it is),
installed with --no-deps into a fresh venv that sees the test venv's packages
only through a path entry (so the editable install of the checkout is not on
the path), then `prism-stream --version`, `python -m prism_stream --version`
and the demo run from it.
"""

from __future__ import annotations

import glob
import os
import shutil
import site
import subprocess
import sys
import venv
from pathlib import Path

import pyarrow.parquet as pq
import pytest

ROOT = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.install


def _run(cmd, cwd="/"):
    """Run outside the checkout (``python -c`` puts the working folder first on the path), no PYTHONPATH."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=300, cwd=cwd, env=env)
    assert r.returncode == 0, f"{cmd}: {r.stdout}\n{r.stderr}"
    return r.stdout


def test_wheel_installs_and_runs_the_demo(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, src / name)
    for folder in ("prism_stream", "cli"):
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__"))
    _run([sys.executable, "-m", "build", "--wheel", "--no-isolation", "--outdir", tmp_path / "dist", src])
    wheels = glob.glob(str(tmp_path / "dist" / "prism_stream-*.whl"))
    assert len(wheels) == 1

    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    py = env_dir / "bin" / "python"
    own = Path(_run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).strip())
    # the dependencies: the test venv's site-packages, appended after the fresh venv's own
    (own / "deps.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    _run([sys.executable, "-m", "pip", "--python", py, "install", "--no-deps", "--quiet", wheels[0]])

    where = _run([py, "-c", "import prism_stream, prism_stream_cli; print(prism_stream.__file__)"]).strip()
    assert where.startswith(str(env_dir)), f"imported {where}, not the installed wheel"
    version = _run([env_dir / "bin" / "prism-stream", "--version"])
    assert "prism-stream" in version and "0." in version
    assert _run([py, "-m", "prism_stream", "--version"]) == version

    out = tmp_path / "autzen_1pct.parquet"
    _run([env_dir / "bin" / "prism-stream", ROOT / "data" / "autzen_trim.laz", out, "--ratio", "0.01", "--quiet"],
         cwd=tmp_path)
    assert pq.read_metadata(out).num_rows == 1100
