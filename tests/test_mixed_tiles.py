"""Tiles whose attributes differ: the one-line error names the columns each file lacks or adds."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

import prism_stream

from conftest import prism_stream_command, random_colors, write_las


@pytest.fixture
def tiles(tmp_path):
    folder = tmp_path / "tiles"
    folder.mkdir()
    n = 500
    write_las(folder / "a.laz", random_colors(n, 1), extra={"height": np.zeros(n, np.float32)})
    write_las(folder / "b.laz", random_colors(n, 2), extra={"confidence": np.ones(n, np.uint8),
                                                            "height": np.zeros(n, np.float64)}, seed=1)
    return folder


def test_parquet_error_names_the_columns(tmp_path, tiles):
    with pytest.raises(prism_stream.PrismError) as info:
        prism_stream.sample(str(tiles / "*.laz"), str(tmp_path / "out.parquet"), ratio=0.1)
    msg = str(info.value)
    assert "b.laz" in msg and "a.laz's" in msg
    assert "extra confidence" in msg and "height (double, not float)" in msg
    assert "\n" not in msg
    assert not (tmp_path / "out.parquet").exists()


def test_cli_one_line(tmp_path, tiles):
    r = subprocess.run([*prism_stream_command(), str(tiles / "*.laz"), str(tmp_path / "out.parquet"),
                        "--ratio", "0.1"], capture_output=True, text=True)
    assert r.returncode != 0
    errors = [line for line in r.stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and "extra confidence" in errors[0], r.stderr
