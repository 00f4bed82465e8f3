"""The command line: a thin layer whose outputs agree with the library.

`prism-stream IN OUT` is `prism-stream sample IN OUT`; `--plan` writes
nothing; `--json` and `--summary` carry the run's numbers; `--quiet` is
quiet; several inputs and a glob are one cloud with one solve.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
from pathlib import Path

import laspy
import pyarrow.parquet as pq
import pytest

import prism_stream

from conftest import prism_stream_command, real_file, user_env

SUMMARY_FIELDS = ("inputs", "points", "bins", "sources", "rule", "k", "target", "kept", "ratio_achieved", "seed",
                  "seconds", "peak_rss_bytes", "output")


def cli(*args, cwd) -> subprocess.CompletedProcess:
    result = subprocess.run([*prism_stream_command(), *map(str, args)], cwd=cwd, capture_output=True, text=True,
                            timeout=120, env=user_env())
    assert "Traceback" not in result.stderr + result.stdout, result.stderr
    return result


@pytest.fixture(scope="module")
def autzen() -> Path:
    return real_file("pdal__autzen_trim.las")


@pytest.fixture(scope="module")
def autzen_plan(autzen) -> prism_stream.Summary:
    """What the library says about autzen at ratio 0.05 (pass one and the solve)."""
    return prism_stream.plan(str(autzen), ratio=0.05)


def test_default_command_is_sample(tmp_path, autzen):
    short = cli(autzen, tmp_path / "short.parquet", "--ratio", "0.05", "--seed", "3", "--quiet", cwd=tmp_path)
    long = cli("sample", autzen, tmp_path / "long.parquet", "--ratio", "0.05", "--seed", "3", "--quiet",
               cwd=tmp_path)
    assert short.returncode == long.returncode == 0, short.stderr + long.stderr
    a, b = pq.read_table(tmp_path / "short.parquet"), pq.read_table(tmp_path / "long.parquet")
    assert a.num_rows == b.num_rows > 0
    assert a.equals(b)


def test_plan_writes_nothing_and_prints_the_solve(tmp_path, autzen, autzen_plan):
    before = sorted(os.listdir(tmp_path))
    result = cli(autzen, "--plan", "--ratio", "0.05", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert sorted(os.listdir(tmp_path)) == before
    out = result.stdout
    for label, value in (("points N", autzen_plan.points), ("bins B", autzen_plan.bins),
                         ("target T", autzen_plan.target)):
        line = next((ln for ln in out.splitlines() if ln.startswith(label)), None)
        assert line is not None, f"no {label!r} line in:\n{out}"
        assert f"{value:,}" in line, line
    assert "nothing was written" in out
    assert autzen_plan.target == math.floor(0.05 * autzen_plan.points + 0.5)


def test_plan_json_has_no_output(tmp_path, autzen, autzen_plan):
    result = cli(autzen, "--plan", "--ratio", "0.05", "--json", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert data["output"] is None
    assert (data["points"], data["bins"], data["target"], data["kept"]) == (
        autzen_plan.points, autzen_plan.bins, autzen_plan.target, autzen_plan.kept)
    assert os.listdir(tmp_path) == []


def test_json_and_summary_file_carry_the_run(tmp_path, autzen, autzen_plan):
    out = tmp_path / "out.las"
    summary_file = tmp_path / "run.json"
    result = cli(autzen, out, "--ratio", "0.05", "--seed", "9", "--json", "--summary", summary_file, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)  # stdout is the JSON and nothing else
    for name in SUMMARY_FIELDS:
        assert name in data, f"--json lacks {name!r}"
    written = laspy.open(out).header.point_count
    assert data["kept"] == written == autzen_plan.kept
    assert data["points"] == autzen_plan.points and data["bins"] == autzen_plan.bins
    assert data["target"] == autzen_plan.target and data["rule"] == "exact"
    assert data["ratio_achieved"] == pytest.approx(written / data["points"])
    assert data["seed"] == 9
    assert data["inputs"] == [os.path.abspath(autzen)]
    assert data["output"] == os.path.abspath(out)
    assert [s["color_depth"] for s in data["sources"]] == ["8"]  # autzen stores 8-bit values
    assert {"scan", "select", "total"} <= set(data["seconds"])
    assert all(v >= 0 for v in data["seconds"].values())
    assert data["peak_rss_bytes"] > 0

    from_file = json.loads(summary_file.read_text())
    volatile = ("seconds", "peak_rss_bytes")
    assert {k: v for k, v in from_file.items() if k not in volatile} == {
        k: v for k, v in data.items() if k not in volatile}


def test_summary_without_json_still_prints_text(tmp_path, autzen, autzen_plan):
    result = cli(autzen, tmp_path / "o.parquet", "--ratio", "0.05", "--summary", tmp_path / "s.json", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert f"{autzen_plan.kept:,}" in result.stdout
    assert json.loads((tmp_path / "s.json").read_text())["kept"] == autzen_plan.kept


def test_quiet_prints_nothing(tmp_path, autzen):
    result = cli(autzen, tmp_path / "o.parquet", "--ratio", "0.05", "--quiet", cwd=tmp_path)
    assert result.returncode == 0
    assert result.stdout == "" and result.stderr == ""
    assert pq.ParquetFile(tmp_path / "o.parquet").metadata.num_rows > 0


def test_help_and_version(tmp_path):
    top = cli("--help", cwd=tmp_path)
    assert top.returncode == 0 and "sample" in top.stdout
    sub = cli("sample", "--help", cwd=tmp_path)
    assert sub.returncode == 0
    for option in ("--ratio", "--count", "--k", "--seed", "--plan", "--json", "--summary", "--quiet", "--overwrite"):
        assert option in sub.stdout, option
    version = cli("--version", cwd=tmp_path)
    assert version.returncode == 0
    assert version.stdout.strip() == f"prism-stream {prism_stream.__version__}"


def split_las(src: Path, folder: Path, parts: int) -> list[Path]:
    """Cut a cloud into ``parts`` LAS files with the same header, named so that sorted order is cut order."""
    las = laspy.read(src)
    n = len(las.points)
    edges = [n * i // parts for i in range(parts + 1)]
    paths = []
    for i in range(parts):
        piece = laspy.LasData(las.header)
        piece.points = las.points[edges[i]:edges[i + 1]].copy()
        path = folder / f"tile_{i}.las"
        piece.write(path)
        paths.append(path)
    return paths


def test_several_inputs_and_a_glob_are_one_cloud(tmp_path, autzen, autzen_plan):
    tiles = split_las(autzen, tmp_path, 3)
    by_glob = cli(tmp_path / "tile_*.las", tmp_path / "glob.las", "--ratio", "0.05", "--json", cwd=tmp_path)
    listed = cli(*tiles, tmp_path / "listed.las", "--ratio", "0.05", "--json", cwd=tmp_path)
    assert by_glob.returncode == listed.returncode == 0, by_glob.stderr + listed.stderr
    g, s = json.loads(by_glob.stdout), json.loads(listed.stdout)
    assert g["inputs"] == s["inputs"] == [os.path.abspath(p) for p in tiles]  # a glob expands in sorted order
    # one solve over the union: the whole file's N, bins and target, not three separate solves
    assert (g["points"], g["bins"], g["target"], g["kept"]) == (
        autzen_plan.points, autzen_plan.bins, autzen_plan.target, autzen_plan.kept)
    assert [src["points"] for src in g["sources"]] == [laspy.open(t).header.point_count for t in tiles]
    a, b = laspy.read(tmp_path / "glob.las"), laspy.read(tmp_path / "listed.las")
    assert a.points.array.tobytes() == b.points.array.tobytes()
    assert len(a.points) == autzen_plan.kept


@pytest.mark.parametrize("words, cword, want", [
    ("prism-stream ra", 1, {"rank"}),
    ("prism-stream rank --max", 2, {"--max-ratio", "--max-count"}),
    ("prism-stream big.laz --mo", 2, {"--mode"}),  # the sample shorthand completes sample's options
    ("prism-stream sample x.laz --color-space c", 4, {"chroma"}),
])
def test_shell_completion(words, cword, want):
    env = dict(os.environ, COMP_WORDS=words, COMP_CWORD=str(cword), _PRISM_STREAM_COMPLETE="bash_complete")
    run = subprocess.run(prism_stream_command(), env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert {line.split(",", 1)[1] for line in run.stdout.splitlines()} == want
    source = subprocess.run(prism_stream_command(), env=dict(os.environ, _PRISM_STREAM_COMPLETE="bash_source"),
                            capture_output=True, text=True)
    assert "complete -o nosort -F _prism_stream_completion prism-stream" in source.stdout
