"""The run summary, as text and as JSON, for every mode (issue 10, category 7).

Each mode runs twice: with ``--json`` (the summary as data) and without
(the text); the text must carry the JSON's numbers, and the summary file
(``--summary``) must be the JSON printed. A crash in the summary printer
after the outputs were published (``--per-file`` once did that) fails here.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest


from conftest import cli, random_colors, write_las, write_parquet


@pytest.fixture(scope="module")
def tiles(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("tiles")
    write_las(folder / "a.las", random_colors(30_000, seed=1, palette=500))
    write_las(folder / "b.las", random_colors(20_000, seed=2, palette=300, depth=16))
    write_las(folder / "c.las", random_colors(10, seed=3, palette=1))  # one color: a warning
    return folder


def n(v) -> str:
    return f"{v:,}"


def both(capsys, tmp_path, *args, out_name):
    """(json summary, text) of the same run, written twice (the second with --overwrite)."""
    summary = tmp_path / "s.json"
    out = [str(tmp_path / out_name) + ("/" if out_name.endswith("/") else "")] if out_name else []
    code, stdout, err = cli(capsys, *args, *out, "--json", "--summary", summary)
    assert code == 0, err
    data = json.loads(stdout)
    assert json.loads(summary.read_text()) == data
    code, text, err = cli(capsys, *args, *out, "--overwrite")
    assert code == 0, err
    assert "Traceback" not in err and "internal error" not in err
    return data, text


def check_common(data, text, plan=False):
    assert f"points N    {n(data['points'])}" in text
    assert f"{'would keep  ' if plan else 'kept        '}{n(data['kept'])}" in text  # a plan keeps nothing
    if data["target"] is not None:
        assert f"target T    {n(data['target'])}" in text
    assert f"{100 * data['ratio_achieved']:.3f}% of N" in text


MODES = {
    "exact": (["--ratio", "0.1"], "exact: K = "),
    "paper": (["--ratio", "0.1", "--mode", "paper"], "paper (integer k* closest to T): k* = "),
    "k": (["--k", "5"], "fixed k = 5"),
    "count": (["--count", "999", "--quant-bits", "2", "--color-space", "chroma"], "exact: K = "),
}


@pytest.mark.parametrize("mode", MODES)
def test_one_output(capsys, tmp_path, tiles, mode):
    args, rule = MODES[mode]
    data, text = both(capsys, tmp_path, tiles / "a.las", tiles / "b.las", *args, out_name="o.parquet")
    check_common(data, text)
    assert rule in text
    if mode == "k":
        assert "target T    - (K fixed)" in text and data["target"] is None
    assert f"bins B      {n(data['bins'])} ({data['options']['color_space']}, " \
           f"{data['options']['quant_bits']} quant bits)" in text
    p = data["plan"]
    assert f"{n(p['bins_capped'])} capped, {n(p['bins_kept_whole'])} kept whole, {n(p['bins_dropped'])} dropped" in text
    assert "bin sizes   min" in text
    assert "color depth 16, 8" in text or "color depth 8, 16" in text
    assert text.rstrip().endswith(f"output      {data['output']}")
    assert data["outputs"] == [data["output"]]


@pytest.mark.parametrize("reads", ["auto", "two"])
def test_the_summary_says_how_the_input_was_read(capsys, tmp_path, tiles, reads):
    data, text = both(capsys, tmp_path, tiles / "a.las", "--ratio", "0.1", "--reads", reads, out_name="o.parquet")
    p = data["plan"]
    if reads == "auto":
        assert p["reads"] == 1 and 0 < p["spill_points"] <= data["points"] and p["spill_bytes"] > 0
        assert f"reads       1 (candidate spill: {n(p['spill_points'])} points, " \
               f"{100 * p['spill_points'] / data['points']:.1f}% of N, " in text
    else:
        assert p["reads"] == 2 and "spill_points" not in p
        assert "reads       2 (--reads two)" in text


@pytest.mark.parametrize("mode", ["exact", "k"])
def test_plan(capsys, tmp_path, tiles, mode):
    args, rule = MODES[mode]
    code, stdout, err = cli(capsys, tiles / "a.las", *args, "--plan", "--json")
    assert code == 0, err
    data = json.loads(stdout)
    assert data["output"] is None and data["outputs"] == [] and data["expected_output_bytes"] > 0
    code, text, err = cli(capsys, tiles / "a.las", *args, "--plan")
    assert code == 0, err
    check_common(data, text, plan=True)
    assert "kept        " not in text
    assert rule in text and "plan only: nothing was written" in text and "expected    " in text
    assert "output      None" not in text and "time        " not in text


def test_directory_mode(capsys, tmp_path, tiles):
    data, text = both(capsys, tmp_path, tiles, "--ratio", "0.2", out_name="out/")
    check_common(data, text)
    assert len(data["outputs"]) == 3 and all(Path(p).is_file() for p in data["outputs"])


def test_an_output_pattern_is_directory_mode_in_its_format(capsys, tmp_path, tiles):
    """``FOLDER/*.laz`` (the Dask engine's per-tile output) is directory mode in that format, the same points as
    ``FOLDER/ --format laz``; it was written as one file named ``*.laz``. Any other ``*`` in an output, or a
    --format the pattern contradicts, is one line, exit 2, nothing written."""
    import laspy

    code, out, err = cli(capsys, tiles, str(tmp_path / "pat" / "*.laz"), "--ratio", "0.2", "--json")
    assert code == 0, err
    outputs = json.loads(out)["outputs"]
    assert sorted(p.name for p in (tmp_path / "pat").iterdir()) == ["a.laz", "b.laz", "c.laz"]
    assert sorted(outputs) == sorted(str(p) for p in (tmp_path / "pat").iterdir())
    code, _, err = cli(capsys, tiles, str(tmp_path / "fmt") + "/", "--format", "laz", "--ratio", "0.2")
    assert code == 0, err
    for name in ("a.laz", "b.laz", "c.laz"):
        mine, theirs = laspy.read(tmp_path / "pat" / name), laspy.read(tmp_path / "fmt" / name)
        assert np.array_equal(mine.points.array, theirs.points.array)
    assert not any("*" in w for w in json.loads(out)["warnings"])
    for bad, extra in [("x*.laz", []), ("*.foo", []), ("*.las", ["--format", "laz"]), ("d*/*.las", [])]:
        code, _, err = cli(capsys, tiles, str(tmp_path / "bad" / bad), "--ratio", "0.2", *extra)
        assert code == 2 and err.count("\n") == 1 and bad in err and "Traceback" not in err, err
        assert not (tmp_path / "bad").exists()


def test_per_file(capsys, tmp_path, tiles):
    for i, args in enumerate((["--ratio", "0.01"], ["--k", "3"], ["--ratio", "0.5", "--mode", "paper"])):
        (tmp_path / str(i)).mkdir()
        data, text = both(capsys, tmp_path / str(i), tiles, *args, "--per-file", out_name="out/")
        check_common(data, text)
        runs = data["plan"]["per_file"]
        assert [Path(r["inputs"][0]).name for r in runs] == ["a.las", "b.las", "c.las"]
        assert "solved one by one (--per-file)" in text
        for r in runs:
            assert f"  {Path(r['inputs'][0]).name}: {n(r['kept'])} of {n(r['points'])} points" in text
            assert Path(r["output"]).is_file()
        assert data["kept"] == sum(r["kept"] for r in runs)
        assert any("same color" in w for w in data["warnings"])


def test_per_file_plan_is_a_usage_error(capsys, tiles):
    code, _, err = cli(capsys, tiles, "--ratio", "0.1", "--per-file", "--plan")
    assert code == 2 and err.count("\n") == 1


@pytest.fixture(scope="module")
def parquet(tmp_path_factory) -> Path:
    rgb = random_colors(20_000, seed=7, palette=400)
    return write_parquet(tmp_path_factory.mktemp("pq") / "p.parquet",
                         {"x": np.arange(len(rgb), dtype=np.float64), "red": rgb[:, 0].astype(np.uint8),
                          "green": rgb[:, 1].astype(np.uint8), "blue": rgb[:, 2].astype(np.uint8)})


def test_sql(capsys, tmp_path, parquet):
    query = f"SELECT * FROM read_parquet('{parquet}')"
    data, text = both(capsys, tmp_path, "sql", query, "--ratio", "0.1", out_name="q.parquet")
    check_common(data, text)
    assert data["inputs"] == [query] and "inputs      a query, color depth" in text
    code, stdout, err = cli(capsys, "sql", query, "--ratio", "0.1", "--plan", "--json")
    assert code == 0, err
    plan = json.loads(stdout)
    code, text, err = cli(capsys, "sql", query, "--ratio", "0.1", "--plan")
    assert code == 0, err
    check_common(plan, text, plan=True)
    assert "plan only: nothing was written" in text
    assert "output      None" not in text and "time        " not in text


def test_dask(capsys, tmp_path, tiles):
    pytest.importorskip("distributed")
    data, text = both(capsys, tmp_path, tiles / "a.las", tiles / "b.las", "--ratio", "0.1", "--dask", "local:1",
                      out_name="dask_out")
    check_common(data, text)
    assert "exact: K = " in text and data["plan"]["dask"]["units"] >= 2


def test_the_reads_line_of_a_cluster_spill_says_what_it_knows():
    """A Dask run's units compact their spills (spill_compactions, spill_points_written) but no one process
    saw the whole spill at once, so its summary has no spill_points_peak: the line leaves it out (a
    KeyError there ended such runs with exit 70 once they compacted)."""
    from cli.report import _reads

    plan = {"reads": 1, "points": 1000, "spill_points": 120, "spill_bytes": 4096, "spill_points_written": 300,
            "spill_compactions": 2}
    assert _reads(plan) == ("reads       1 (candidate spill: 120 points, 12.0% of N, 4.0 KiB; 300 written, "
                            "2 compactions)")
    line = _reads({**plan, "spill_points_peak": 250, "spill_compactions": 1})
    assert line.endswith("; 300 written, 250 held at most, 1 compaction)")
