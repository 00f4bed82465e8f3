"""A ``.copc.laz`` output is refused (exit 4, one line) rather than written as a plain LAZ under a COPC name."""

from __future__ import annotations

import subprocess

import pytest

import prism_stream
from prism_stream.errors import UnsupportedFormat

from conftest import prism_stream_command, real_file


def test_copc_output_is_refused(tmp_path):
    out = tmp_path / "out.copc.laz"
    with pytest.raises(UnsupportedFormat, match=r"COPC output is not written.*name the output \.laz"):
        prism_stream.sample(str(real_file("pdal__autzen_trim.las")), str(out), ratio=0.1)
    assert not list(tmp_path.iterdir())


def test_copc_output_cli_exit_4(tmp_path):
    out = tmp_path / "Out.COPC.LAZ"
    r = subprocess.run([*prism_stream_command(), str(real_file("potree__lion_takanawa.copc.laz")), str(out),
                        "--ratio", "0.1"], capture_output=True, text=True)
    assert r.returncode == 4, r.stderr
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "name the output .laz" in lines[0], r.stderr
    assert not list(tmp_path.iterdir())


def test_copc_input_to_laz_still_works(tmp_path):
    out = tmp_path / "lion.laz"
    prism_stream.sample(str(real_file("potree__lion_takanawa.copc.laz")), str(out), ratio=0.1)
    assert out.exists()
