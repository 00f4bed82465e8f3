"""What a newcomer trips on in the first hour (issue 28): each slip, as it was met, must not come back.

Run in this process through the command line's entry point (``run``): the
exit code, stdout and stderr are what a user sees.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

import prism_stream

from conftest import cli, random_colors, real_file, write_las


@pytest.fixture
def cloud(tmp_path) -> Path:
    return write_las(tmp_path / "cloud.las", random_colors(4_000, seed=3, palette=300))


# -- 1. --plan and an output ------------------------------------------------------------------------

def test_plan_with_the_runs_output_plans_the_input_alone(capsys, tmp_path, cloud):
    """`IN OUT --plan`: the output was once read as a second input (a new name: `no such file`)."""
    code, out, err = cli(capsys, cloud, tmp_path / "new.parquet", "--plan", "--ratio", "0.1", "--json")
    assert code == 0, err
    d = json.loads(out)
    assert d["points"] == 4_000 and d["inputs"] == [str(cloud)] and d["output"] is None
    assert d["planned_output"] == str(tmp_path / "new.parquet")
    code, text, err = cli(capsys, cloud, tmp_path / "new.parquet", "--plan", "--ratio", "0.1")
    assert code == 0 and f"output      {tmp_path / 'new.parquet'} (checked as the run checks it)" in text
    assert sorted(os.listdir(tmp_path)) == ["cloud.las"]  # nothing written


def test_plan_refuses_an_existing_output_as_the_run_does(capsys, tmp_path, cloud):
    """An existing output was counted as an input, with no warning (the N of both files)."""
    existing = tmp_path / "out.parquet"
    code, _, err = cli(capsys, cloud, existing, "--ratio", "0.1")
    assert code == 0, err
    before = existing.read_bytes()
    code, out, err = cli(capsys, cloud, existing, "--plan", "--ratio", "0.1")
    assert code == 7 and out == "" and err.count("\n") == 1
    assert f"{existing}: already exists (use --overwrite" in err
    assert "the last of several paths is the run's OUTPUT" in err
    code, out, err = cli(capsys, cloud, existing, "--plan", "--ratio", "0.1", "--overwrite", "--json")
    assert code == 0 and json.loads(out)["points"] == 4_000, err
    assert existing.read_bytes() == before  # --overwrite in a plan replaces nothing


def test_plan_refuses_an_output_it_cannot_write(capsys, tmp_path, cloud):
    code, _, err = cli(capsys, cloud, tmp_path / "out.pcd", "--plan", "--ratio", "0.1")
    assert code == 4 and "out.pcd: unknown output extension '.pcd'" in err and "ends with /" not in err
    code, _, err = cli(capsys, cloud, tmp_path / "out", "--plan", "--ratio", "0.1")  # a folder meant, without /
    assert code == 4 and "unknown output extension '(none)'" in err and "a folder for one output per input ends " \
        "with /" in err, err
    code, _, err = cli(capsys, cloud, cloud, "--plan", "--ratio", "0.1", "--overwrite")
    assert code == 2 and "the output would overwrite an input" in err


def test_plan_of_several_inputs_alone_is_a_folder_or_a_glob(capsys, tmp_path):
    (tmp_path / "in").mkdir()
    write_las(tmp_path / "in" / "a.las", random_colors(1_000, seed=1))
    write_las(tmp_path / "in" / "b.las", random_colors(2_000, seed=2))
    for given in (tmp_path / "in", tmp_path / "in" / "*.las"):
        code, out, err = cli(capsys, given, "--plan", "--ratio", "0.1", "--json")
        assert code == 0 and json.loads(out)["points"] == 3_000, err


def test_plan_with_an_output_refuses_what_the_run_refuses_and_no_more(capsys, tmp_path, monkeypatch):
    """The plan checked the output's name only: `--flag` into LAS from a PLY passed the plan and failed the run;
    and directory mode's --format failed the plan and passed the run (the review of issue 28)."""
    ply = real_file("odm__option-0000.ply")
    _no_decoding(monkeypatch)
    code, _, err = cli(capsys, ply, tmp_path / "fl.las", "--plan", "--ratio", "0.1", "--flag", "keep")
    assert code == 2 and "--flag with LAS output needs LAS/LAZ inputs" in err
    assert "with --plan the last of several paths is the run's OUTPUT" in err
    code, _, err = cli(capsys, ply, tmp_path / "g.ply", "--plan", "--ratio", "0.1", "--geometry")
    assert code == 2 and "--geometry adds a GeoParquet geometry column" in err
    monkeypatch.undo()
    (tmp_path / "in").mkdir()
    write_las(tmp_path / "in" / "a.las", random_colors(1_000, seed=1))
    code, out, err = cli(capsys, tmp_path / "in", str(tmp_path / "out") + os.sep, "--format", "laz", "--plan",
                         "--ratio", "0.1", "--json")
    assert code == 0 and json.loads(out)["points"] == 1_000, err
    code, _, err = cli(capsys, tmp_path / "in", str(tmp_path / "out") + os.sep, "--per-file", "--plan", "--ratio",
                       "0.1")
    assert code == 2 and "plan each file alone" in err
    assert sorted(os.listdir(tmp_path)) == ["in"]


def test_plan_says_when_its_output_folder_holds_clouds(capsys, tmp_path):
    """`a/ b/ --plan` once planned both; now b/ is the OUTPUT, and the plan says it holds readable files."""
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        write_las(tmp_path / name / f"{name}.las", random_colors(1_000, seed=len(name)))
    code, out, err = cli(capsys, tmp_path / "a", tmp_path / "b", "--plan", "--ratio", "0.1", "--json")
    assert code == 0 and json.loads(out)["points"] == 1_000
    assert f"{tmp_path / 'b'}: taken as the run's OUTPUT folder, though it holds 1 readable file(s)" in err


def test_per_file_refusals_come_before_the_first_file_and_name_the_output(capsys, tmp_path, monkeypatch):
    (tmp_path / "in").mkdir()
    write_las(tmp_path / "in" / "a.las", random_colors(1_000, seed=1))
    os.symlink(real_file("odm__option-0000.ply"), tmp_path / "in" / "c.ply")
    from prism_stream.formats.las import LasSource

    def decoded(*_, **__):
        raise AssertionError("a file was sampled before the refusal")

    monkeypatch.setattr(LasSource, "color_chunks", decoded)
    monkeypatch.setattr(LasSource, "point_chunks", decoded)
    code, _, err = cli(capsys, tmp_path / "in", str(tmp_path / "pf") + os.sep, "--per-file", "--format", "laz",
                       "--flag", "keep", "--ratio", "0.1")
    assert code == 2 and err.count("\n") == 1, err
    assert f"{tmp_path / 'pf' / 'c.laz'}: --flag with LAS output needs LAS/LAZ inputs" in err
    assert sorted(os.listdir(tmp_path)) == ["in"]


def test_sql_plan_checks_its_output(capsys, tmp_path, cloud):
    from prism_stream import sample

    sample(str(cloud), str(tmp_path / "c.parquet"), ratio=1.0)
    query = f"SELECT * FROM read_parquet('{tmp_path / 'c.parquet'}')"
    code, out, err = cli(capsys, "sql", query, tmp_path / "c.parquet", "--plan", "--ratio", "0.1")
    assert code == 7 and "c.parquet: already exists" in err
    code, out, err = cli(capsys, "sql", query, tmp_path / "s.parquet", "--plan", "--ratio", "0.1", "--json")
    assert code == 0 and json.loads(out)["planned_output"] == str(tmp_path / "s.parquet"), err
    assert not (tmp_path / "s.parquet").exists()
    code, out, err = cli(capsys, "sql", query, tmp_path / "s.laz", "--plan", "--ratio", "0.1")
    assert code == 4 and "s.laz: a query's sample is written as Parquet" in err


def test_dask_plan_checks_its_output_before_any_cluster(capsys, tmp_path, cloud):
    """Refused from the options alone: no cluster is started (an address nothing listens on is never tried)."""
    (tmp_path / "out").mkdir()
    code, _, err = cli(capsys, cloud, tmp_path / "out", "--plan", "--ratio", "0.1", "--dask", "tcp://127.0.0.1:9")
    assert code == 7 and "out: already exists" in err
    code, _, err = cli(capsys, cloud, tmp_path / "x.laz", "--plan", "--ratio", "0.1", "--dask", "tcp://127.0.0.1:9")
    assert code == 2 and "give FOLDER/*.laz" in err


# -- 2. what a writer refuses is refused before pass one, naming the output --------------------------

def _no_decoding(monkeypatch):
    from prism_stream.formats.ply import PlySource

    def decoded(*_, **__):
        raise AssertionError("the input was decoded before the refusal")

    monkeypatch.setattr(PlySource, "color_chunks", decoded)
    monkeypatch.setattr(PlySource, "point_chunks", decoded)


@pytest.mark.parametrize("streaming", [False, True], ids=["in-memory", "streaming"])
def test_flag_into_las_from_other_formats_is_refused_first(capsys, tmp_path, monkeypatch, streaming):
    """It decoded the whole cloud first (13 s on a PCD) and named the temporary path."""
    if not streaming:
        monkeypatch.delenv("PRISM_STREAM_MEMORY_POINTS", raising=False)
    ply = real_file("odm__option-0000.ply")
    _no_decoding(monkeypatch)
    for out in ("fl.laz", "fl.las", "fl.copc.laz"):
        code, _, err = cli(capsys, ply, tmp_path / out, "--ratio", "0.1", "--flag", "keep")
        assert code == 2 and err.count("\n") == 1, err
        assert err == (f"prism-stream: error: {tmp_path / out}: --flag with LAS output needs LAS/LAZ inputs; write "
                       "Parquet for a flag column\n")
    (tmp_path / "in").mkdir()
    os.symlink(ply, tmp_path / "in" / "cloud.ply")
    code, _, err = cli(capsys, tmp_path / "in", str(tmp_path / "out") + os.sep, "--format", "laz", "--ratio", "0.1",
                       "--flag", "keep")
    assert code == 2 and f"{tmp_path / 'out' / 'cloud.laz'}: --flag with LAS output" in err
    assert sorted(os.listdir(tmp_path)) == ["in"]


def test_geometry_and_columns_into_non_parquet_are_refused_first(capsys, tmp_path, monkeypatch):
    ply = real_file("odm__option-0000.ply")
    _no_decoding(monkeypatch)
    code, _, err = cli(capsys, ply, tmp_path / "g.ply", "--ratio", "0.1", "--geometry")
    assert code == 2 and f"{tmp_path / 'g.ply'}: --geometry adds a GeoParquet geometry column" in err
    code, _, err = cli(capsys, ply, tmp_path / "c.las", "--ratio", "0.1", "--columns", "union")
    assert code == 2 and f"{tmp_path / 'c.las'}: --columns union writes inputs" in err
    assert os.listdir(tmp_path) == []


# -- 4. sql's exit codes are the README's ------------------------------------------------------------

@pytest.mark.parametrize("source", ["read_parquet('nothere/*.parquet')", "read_parquet('nothere.parquet')",
                                    "read_csv('nothere.csv')"])
def test_sql_on_files_that_are_not_there_is_exit_3(capsys, tmp_path, monkeypatch, source):
    monkeypatch.chdir(tmp_path)
    code, _, err = cli(capsys, "sql", f"SELECT * FROM {source}", "out.parquet", "--ratio", "0.1")
    assert code == 3 and err.count("\n") == 1 and "No files found" in err, err
    assert os.listdir(tmp_path) == []


def test_sql_on_a_file_that_is_no_parquet_is_exit_6(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bad.parquet").write_bytes(b"PAR1 not really")
    code, _, err = cli(capsys, "sql", "SELECT * FROM read_parquet('bad.parquet')", "out.parquet", "--ratio", "0.1")
    assert code == 6 and err.count("\n") == 1, err


# -- 3. no arguments, a typo, `help` ----------------------------------------------------------------

def test_no_arguments_prints_the_help_not_one_squashed_line(capsys):
    code, out, err = cli(capsys)
    assert code == 2 and out == ""
    assert err.startswith("Usage: prism-stream [OPTIONS] COMMAND") and "prism-stream: error" not in err
    assert "\n  sample " in err and err.count("\n") > 10


@pytest.mark.parametrize("typo,meant", [("smaple", "sample"), ("rnak", "rank"), ("sqll", "sql"), ("Sample", "sample"),
                                        ("evl", "eval")])
def test_a_typo_of_a_command_is_named(capsys, tmp_path, monkeypatch, typo, meant):
    monkeypatch.chdir(tmp_path)
    code, out, err = cli(capsys, typo, "in.laz", "out.parquet", "--ratio", "0.1")
    assert code == 2 and err.count("\n") == 1
    assert f"no command '{typo}'; did you mean '{meant}'?" in err
    assert "prism-stream prism-stream" not in err and err.rstrip().endswith("(see prism-stream --help)")


def test_a_file_named_like_a_command_is_an_input(capsys, tmp_path, monkeypatch):
    """An existing file is never taken for a typo: `smaple` (no extension) reaches the sampler, which names it."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "smaple").write_bytes(b"not a cloud")
    code, _, err = cli(capsys, "smaple", "out.parquet", "--ratio", "0.1")
    assert code == 4 and err.startswith("prism-stream: error: smaple:") and "did you mean" not in err
    code, _, err = cli(capsys, "nothing_like_it", "out.parquet", "--ratio", "0.1")  # no near command: a path
    assert code == 3 and "nothing_like_it" in err and "did you mean" not in err


def test_help_command(capsys):
    code, out, _ = cli(capsys, "help")
    assert code == 0 and out.startswith("Usage: prism-stream [OPTIONS] COMMAND")
    code, out, _ = cli(capsys, "help", "sample")
    assert code == 0 and out.startswith("Usage: prism-stream sample [OPTIONS] INPUT... OUTPUT")
    code, out, err = cli(capsys, "help", "smaple")
    assert code == 2 and "did you mean 'sample'?" in err
    code, out, err = cli(capsys, "help", "nope")
    assert code == 2 and "commands: batch, check, eval, help, info, rank, sample, sql" in err


# -- 5. --per-file's times ----------------------------------------------------------------------------

def test_per_file_summary_sums_each_step(capsys, tmp_path):
    (tmp_path / "in").mkdir()
    write_las(tmp_path / "in" / "a.las", random_colors(3_000, seed=1))
    write_las(tmp_path / "in" / "b.las", random_colors(2_000, seed=2))
    code, out, err = cli(capsys, tmp_path / "in", str(tmp_path / "out") + os.sep, "--ratio", "0.1", "--per-file",
                         "--json")
    assert code == 0, err
    d = json.loads(out)
    runs = d["plan"]["per_file"]
    for step in ("scan", "cutoffs", "select"):
        assert d["seconds"][step] == pytest.approx(sum(r["seconds"].get(step, 0) for r in runs), abs=1e-3)
    assert d["seconds"]["scan"] > 0 and d["seconds"]["total"] >= d["seconds"]["scan"]


# -- 11. help slips -----------------------------------------------------------------------------------

def _option_help(capsys, command: str, option: str) -> str:
    code, out, _ = cli(capsys, command, "--help")
    assert code == 0
    lines = out.splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip().startswith(option + " "))
    block = [lines[start]] + [ln for ln in lines[start + 1:start + 6] if ln.startswith(" " * 20)]
    return " ".join(" ".join(block).split())


def test_each_command_says_what_its_options_do_there(capsys):
    assert "DuckDB" in _option_help(capsys, "sql", "--threads")
    for command in ("sample", "rank", "eval"):
        assert "DuckDB" not in _option_help(capsys, command, "--threads"), command
    assert "--dask" not in _option_help(capsys, "eval", "--temp-dir")
    assert "--dask" not in _option_help(capsys, "sql", "--temp-dir")
    assert "--dask" in _option_help(capsys, "sample", "--temp-dir")
    code, out, _ = cli(capsys, "sql", "--help")  # a query is read twice and has one schema: neither applies
    assert code == 0 and "--reads" not in out and "--columns" not in out


def test_the_command_list_is_not_cut(capsys):
    code, out, _ = cli(capsys, "--help")
    commands = out.split("Commands:")[1]
    assert "..." not in commands
    for name in ("batch", "eval", "help", "info", "rank", "sample", "sql"):
        assert f"\n  {name} " in commands


def test_the_readme_names_the_eval_extra():
    readme = (Path(__file__).resolve().parent.parent / "README.md").read_text()
    assert "pip install '.[eval]'" in readme
    pyproject = (Path(__file__).resolve().parent.parent / "pyproject.toml").read_text()
    assert "\neval = [" in pyproject.split("[project.optional-dependencies]")[1].split("\n[")[0]


def test_real_cloud_plan_with_output(capsys, tmp_path):
    """The report's example: the bundled cloud with its output named, as a user types it."""
    autzen = real_file("pdal__autzen_trim.las")
    code, out, err = cli(capsys, autzen, tmp_path / "out.parquet", "--plan", "--ratio", "0.01", "--json")
    assert code == 0, err
    d = json.loads(out)
    assert d["points"] == 110_000 and d["target"] == 1_100 and len(d["inputs"]) == 1


# -- 9. --scale and --offset for LAS output converted from other formats ----------------------------

def _ply_xyz():
    import numpy as np
    import plyfile

    v = plyfile.PlyData.read(str(real_file("odm__option-0000.ply")))["vertex"].data
    return np.column_stack([np.asarray(v[a], dtype=np.float64) for a in "xyz"])


def test_a_converted_las_gets_a_decimal_grid_with_room_around_the_cloud(capsys, tmp_path):
    """Without --scale: the photogrammetry PLY (float32, about 2 m across) got scales near 1e-9 and a few
    metres of range; now a decimal scale no coarser than the input's float32 spacing, and hundreds of metres."""
    import laspy
    import numpy as np

    code, _, err = cli(capsys, real_file("odm__option-0000.ply"), tmp_path / "s.laz", "--ratio", "1")
    assert code == 0, err
    las = laspy.read(str(tmp_path / "s.laz"))
    assert list(las.header.scales) == [1e-07, 1e-07, 1e-07]
    want = _ply_xyz()
    for axis in range(3):
        reach = (2 ** 31 - 1) * las.header.scales[axis]
        assert np.abs(want[:, axis] - las.header.offsets[axis]).max() < reach / 50
    assert "grid of 1e-07, 1e-07, 1e-07 (x, y, z)" in err and "--scale and --offset choose another" in err


@pytest.mark.parametrize("out", ["s.laz", "s.las", "s.copc.laz"])
def test_scale_and_offset_set_the_grid_of_a_converted_las(capsys, tmp_path, out):
    """PLY/PCD -> LAS picked scales near 1e-9 (a few metres of range) and warned every run; PDAL and LAStools
    let the user choose, as here."""
    import laspy
    import numpy as np

    ply = real_file("odm__option-0000.ply")
    code, _, err = cli(capsys, ply, tmp_path / out, "--ratio", "1", "--scale", "0.01,0.01,0.001", "--offset",
                       "100,-200,0.5", "--json")
    assert code == 0, err
    assert "coordinates stored as LAS 32-bit integers" not in err  # the user chose the grid: nothing to say
    las = laspy.read(str(tmp_path / out))
    assert list(las.header.scales) == [0.01, 0.01, 0.001] and list(las.header.offsets) == [100, -200, 0.5]
    want = _ply_xyz()
    got = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    # every point: the input's value rounded to the grid (the order: sort both by the rounded values)
    grid = np.round((want - [100, -200, 0.5]) / [0.01, 0.01, 0.001]) * [0.01, 0.01, 0.001] + [100, -200, 0.5]
    order = lambda a: a[np.lexsort(a.T[::-1])]  # noqa: E731
    assert np.allclose(order(got), order(grid), rtol=0, atol=1e-9)
    from prism_stream.formats.las import read_provenance

    conversion = read_provenance(str(tmp_path / out))["las_conversion"]
    assert conversion["scales_from_options"] and conversion["scales"] == [0.01, 0.01, 0.001]


def test_scale_alone_puts_the_offset_mid_extent_on_the_grid(capsys, tmp_path):
    import laspy
    import numpy as np

    code, _, err = cli(capsys, real_file("odm__option-0000.ply"), tmp_path / "s.laz", "--ratio", "1", "--scale",
                       "0.001")
    assert code == 0, err
    h = laspy.read(str(tmp_path / "s.laz")).header
    xyz = _ply_xyz()
    mid = (xyz.min(axis=0) + xyz.max(axis=0)) / 2
    assert list(h.scales) == [0.001] * 3
    assert np.allclose(h.offsets, np.round(mid / 0.001) * 0.001, rtol=0, atol=1e-12)


@pytest.mark.parametrize("args,message", [
    (["--scale", "0.001"], "s.parquet: --scale and --offset set the coordinate grid of LAS, LAZ or COPC output"),
    (["--offset", "1,2,3"], "--offset needs --scale"),
    (["--scale", "0,1,1"], "--scale takes positive finite numbers, not '0,1,1'"),
    (["--scale", "1,2"], "--scale takes 1 or 3 value(s), not 2"),
    (["--scale", "nan"], "--scale takes positive finite numbers"),
    (["--scale", "0.1", "--offset", "x,1,2"], "--offset takes numbers separated by commas"),
])
def test_grid_options_are_refused_before_reading(capsys, tmp_path, monkeypatch, args, message):
    _no_decoding(monkeypatch)
    code, _, err = cli(capsys, real_file("odm__option-0000.ply"), tmp_path / "s.parquet", "--ratio", "0.5", *args)
    assert code == 2 and err.count("\n") == 1 and message in err, err
    assert os.listdir(tmp_path) == []


def test_grid_options_on_las_inputs_or_dask_are_refused(capsys, tmp_path):
    las = real_file("pdal__warsaw_small.las")
    code, _, err = cli(capsys, las, tmp_path / "s.laz", "--ratio", "0.5", "--scale", "0.001")
    assert code == 2 and "LAS inputs keep their own scale and offset" in err
    code, _, err = cli(capsys, las, str(tmp_path / "out") + "/*.laz", "--ratio", "0.5", "--scale", "0.001",
                       "--dask", "local:1")
    assert code == 2 and "--scale is not available with --dask" in err
    assert os.listdir(tmp_path) == []


def test_a_grid_too_fine_for_the_extent_is_one_line_and_leaves_nothing(capsys, tmp_path):
    code, _, err = cli(capsys, real_file("odm__option-0000.ply"), tmp_path / "s.laz", "--ratio", "0.5", "--scale",
                       "1e-12")
    assert code == 2 and err.count("\n") == 1
    assert "does not fit a LAS 32-bit integer at --scale 1e-12" in err and "choose a coarser --scale" in err
    assert os.listdir(tmp_path) == []


# -- 8. eval --plots: one tick where methods reach nearly the same ratio --------------------------------

def test_ratio_ticks_are_spaced():
    from prism_stream.evaluate.plots import spaced_ticks

    assert spaced_ticks([5.01, 1.0, 5.0, 5.02, 10.0, 0.99]) == [0.99, 5.0, 10.0]  # 1.0 too close to 0.99
    assert spaced_ticks([0.5, 1.0, 5.0]) == [0.5, 1.0, 5.0]
    assert spaced_ticks([]) == []


def test_equal_entropy_gains_are_explained():
    """warsaw at 1%: every method's 30 points hold 30 distinct colors, so every gain was -6.209 and nothing
    said why."""
    from prism_stream.errors import PrismWarning
    from prism_stream.evaluate.run import evaluate

    with pytest.warns(PrismWarning, match="holds as many distinct colors as points"):
        res = evaluate([str(real_file("pdal__warsaw_small.las"))], ratios=(0.01,), methods=("prism", "random"),
                       metrics=False)
    gains = {round(r.entropy_gain, 9) for r in res.rows}
    assert len(gains) == 1 and all(r.count == 30 for r in res.rows)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", PrismWarning)  # at 50% the samples differ: nothing to explain
        evaluate([str(real_file("pdal__warsaw_small.las"))], ratios=(0.5,), methods=("prism", "random"), metrics=False)


# -- -v/--verbose ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("reads", ["auto", "two"])
def test_verbose_says_each_step_as_it_happens(capsys, tmp_path, cloud, reads):
    code, out, err = cli(capsys, cloud, tmp_path / "v.parquet", "--ratio", "0.1", "--reads", reads, "-v", "--quiet")
    assert code == 0 and out == ""
    lines = err.splitlines()
    assert all(line.startswith("prism-stream: ") for line in lines), err
    steps = [line.split(": ")[1] for line in lines]
    assert steps[0].startswith("pass 1/2") and any(s.startswith("pass 2/2") for s in steps)
    assert "solve: N = 4,000" in err and "T = 400" in err and "keeps 400" in err
    assert sum("done" in line for line in lines) >= 2  # each step's end, with its points and seconds
    code, _, err = cli(capsys, cloud, tmp_path / "q.parquet", "--ratio", "0.1", "--quiet")  # off again
    assert code == 0 and err == ""


# -- peers: --keep and --drop choose what a Parquet output keeps ------------------------------------

@pytest.mark.parametrize("args,gone", [(["--drop", "gps_time,Intensity"], {"gps_time", "intensity"}),
                                       (["--keep", "classification"], None)])
def test_keep_and_drop_choose_the_columns_of_a_parquet_output(capsys, tmp_path, args, gone):
    import pyarrow.parquet as pq

    autzen = real_file("pdal__autzen_trim.las")
    code, _, err = cli(capsys, autzen, tmp_path / "all.parquet", "--ratio", "0.01", "-q")
    assert code == 0, err
    code, _, err = cli(capsys, autzen, tmp_path / "some.parquet", "--ratio", "0.01", "-q", *args)
    assert code == 0, err
    every, some = pq.read_table(tmp_path / "all.parquet"), pq.read_table(tmp_path / "some.parquet")
    want = [n for n in every.column_names if n not in gone] if gone else \
        ["x", "y", "z", "classification", "red", "green", "blue"]  # the coordinates and colors stay
    assert some.column_names == want
    assert some.equals(every.select(want).replace_schema_metadata(some.schema.metadata))


@pytest.mark.parametrize("args,message", [
    (["--drop", "diffuse_red"], "--drop 'diffuse_red': the output keeps its coordinates and colors"),
    (["--drop", "y"], "--drop 'y': the output keeps its coordinates and colors"),
    (["--keep", "nope"], "--keep 'nope': the inputs have no such column (columns: x, y, z"),
    (["--drop", "nx", "--keep", "nx"], "give --keep or --drop, not both"),
    (["--drop", ","], "--drop needs column names"),
])
def test_keep_and_drop_refusals_come_before_reading(capsys, tmp_path, monkeypatch, args, message):
    _no_decoding(monkeypatch)
    code, _, err = cli(capsys, real_file("odm__option-0000.ply"), tmp_path / "s.parquet", "--ratio", "0.5", *args)
    assert code == 2 and err.count("\n") == 1 and message in err, err
    for out in ("s.laz", "s.ply", "s.copc.laz"):  # the same refusals for every output format
        code, _, err = cli(capsys, real_file("odm__option-0000.ply"), tmp_path / out, "--ratio", "0.5", *args)
        assert code == 2 and err.count("\n") == 1 and message in err, (out, err)
    assert os.listdir(tmp_path) == []


EXTRA_BYTES_TILE = "pdal__las_with_several_extra_byte_bloc.laz"  # point format 8, extra bytes Deviation, ExtraBytes


@pytest.mark.parametrize("out", ["s.laz", "s.las", "s.copc.laz"])
def test_drop_in_las_output_leaves_extra_bytes_out_and_zeroes_the_formats_own(capsys, tmp_path, out):
    """LAS records always hold their point format's dimensions: a dropped one (gps_time) is written as 0 and
    said; a dropped extra-bytes dimension (Deviation) is not in the records nor the header's descriptors;
    everything else is the undropped run's, record for record."""
    import laspy
    import numpy as np

    tile = real_file(EXTRA_BYTES_TILE)
    code, _, err = cli(capsys, tile, tmp_path / ("all" + out[1:]), "--ratio", "0.02", "-q")
    assert code == 0, err
    code, _, err = cli(capsys, tile, tmp_path / out, "--ratio", "0.02", "--drop", "gps_time,Deviation")
    assert code == 0, err
    assert "--drop: gps_time written as 0 in every record" in err, err
    every, some = laspy.read(tmp_path / ("all" + out[1:])), laspy.read(tmp_path / out)
    assert list(some.point_format.extra_dimension_names) == ["confidence"]  # the second record's name, kept
    assert "Deviation" in every.point_format.extra_dimension_names
    assert some.header.point_count == every.header.point_count > 0
    assert not np.any(some.gps_time) and np.any(every.gps_time)
    for dim in ("X", "Y", "Z", "intensity", "classification", "red", "green", "blue", "nir", "confidence"):
        assert np.array_equal(np.asarray(some[dim]), np.asarray(every[dim])), dim


def test_keep_in_las_output_keeps_the_named_extra_bytes(capsys, tmp_path):
    import laspy
    import numpy as np

    tile = real_file(EXTRA_BYTES_TILE)
    code, _, err = cli(capsys, tile, tmp_path / "k.laz", "--ratio", "0.02", "--keep", "intensity,deviation")
    assert code == 0, err
    las = laspy.read(tmp_path / "k.laz")
    assert list(las.point_format.extra_dimension_names) == ["Deviation"]  # matched case-insensitively
    assert np.any(las.intensity) and not np.any(las.gps_time) and not np.any(las.classification)


def test_las_keeps_the_return_numbers_and_the_withheld_flag(capsys, tmp_path, monkeypatch):
    """Return numbers start at 1 in LAS, and --flag withheld writes the withheld bit: a --keep keeps them, a --drop
    of one is refused before a point is read."""
    import laspy
    import numpy as np

    tile = real_file(EXTRA_BYTES_TILE)
    code, _, err = cli(capsys, tile, tmp_path / "f.laz", "--ratio", "0.02", "--keep", "intensity", "--flag",
                       "withheld", "-q")
    assert code == 0, err
    every, flagged = laspy.read(tile), laspy.read(tmp_path / "f.laz")
    assert len(flagged.points) == len(every.points)  # flag mode: every point, the dropped ones withheld
    assert 0 < int(np.count_nonzero(flagged.withheld)) < len(flagged.points)
    assert np.array_equal(flagged.return_number, every.return_number) and not np.any(flagged.gps_time)
    _no_decoding(monkeypatch)
    for args, name in ((["--drop", "return_number"], "return_number"),
                       (["--drop", "withheld", "--flag", "withheld"], "withheld")):
        code, _, err = cli(capsys, tile, tmp_path / "r.laz", "--ratio", "0.02", *args)
        assert code == 2 and err.count("\n") == 1 and f"--drop {name!r}: a LAS output keeps it" in err, err
    assert not (tmp_path / "r.laz").exists()


@pytest.mark.parametrize("out", ["p.ply", "p.laz", "p.parquet"])
def test_keep_and_drop_from_ply_into_every_format(capsys, tmp_path, out):
    """A converted output is built from the columns left: a dropped PLY property is in no output."""
    import laspy
    import pyarrow.parquet as pq
    from plyfile import PlyData

    ply = real_file("odm__option-0000.ply")
    code, _, err = cli(capsys, ply, tmp_path / out, "--ratio", "0.1", "--drop", "nx,ny", "-q")
    assert code == 0, err
    path = tmp_path / out
    if out.endswith(".ply"):
        names = [p.name for p in PlyData.read(path)["vertex"].properties]
    elif out.endswith(".laz"):
        names = list(laspy.read(path).point_format.dimension_names)
    else:
        names = pq.read_schema(path).names
    assert "nz" in names and "nx" not in names and "ny" not in names, names


def test_drop_lets_a_clashing_extra_bytes_dimension_out_of_copc(tmp_path):
    """COPC refuses a LAS input whose extra bytes are named as its own fields; leaving them out is the way."""
    import numpy as np

    from prism_stream.errors import UsageError

    rng = np.random.default_rng(6)
    src = write_las(tmp_path / "clash.las", rng.integers(0, 256, (500, 3)), point_format=3,
                    extra={"scanner_channel": rng.random(500)})
    with pytest.raises(UsageError, match="--drop scanner_channel"):
        prism_stream.sample(str(src), str(tmp_path / "c.copc.laz"), ratio=0.5)
    s = prism_stream.sample(str(src), str(tmp_path / "c.copc.laz"), ratio=0.5, drop=("scanner_channel",))
    assert s.kept == 250


def test_an_output_folder_takes_each_inputs_own_names(capsys, tmp_path):
    """One output per input: a name only some inputs have applies to those; a name none has is refused."""
    import shutil

    import laspy

    folder = tmp_path / "tiles"
    folder.mkdir()
    shutil.copy(real_file(EXTRA_BYTES_TILE), folder / "a.laz")
    shutil.copy(real_file("pdal__autzen_trim.las"), folder / "b.las")
    code, _, err = cli(capsys, folder, str(tmp_path / "out") + "/", "--ratio", "0.01", "--drop", "Deviation", "-q")
    assert code == 0, err
    assert list(laspy.read(tmp_path / "out" / "a.laz").point_format.extra_dimension_names) == ["confidence"]
    code, _, err = cli(capsys, folder, str(tmp_path / "out2") + "/", "--ratio", "0.01", "--drop", "Devation")
    assert code == 2 and "--drop 'Devation': the inputs have no such column" in err, err
    assert not (tmp_path / "out2").exists()


# every input format of tests/data: --drop leaves out one column that is neither a coordinate nor a color, and
# the rest is the undropped run's, row for row
EVERY_FORMAT = [real_file(n) for n in ("pdal__autzen_trim.las", "laspy__fullwave.laz", "potree__lion_takanawa.copc.laz",
                                       "odm__option-0000.ply", "pcl__office1.pcd")]


@pytest.mark.parametrize("path", EVERY_FORMAT + ["edge:e57data__ColourRepresentation.e57",
                                                 "edge:trimesh__points_agisoft.xyz", "edge:pdal__1.2-with-color.parquet"],
                         ids=lambda p: str(p).rsplit("/", 1)[-1])
def test_drop_on_every_input_format(tmp_path, path):
    import warnings

    import pyarrow.parquet as pq

    from conftest import edge_file
    from prism_stream.formats import open_source
    from prism_stream.formats.conversion import color_fields

    path = edge_file(path[5:]) if isinstance(path, str) else path
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prism_stream.sample(str(path), str(tmp_path / "all.parquet"), ratio=0.5, seed=3)
        every = pq.read_table(tmp_path / "all.parquet")
        with open_source(str(path), 0) as src:
            keep = {*color_fields(src), "red", "green", "blue", "x", "y", "z", "xyz", "geometry"}
        name = next((n for n in every.column_names if n.lower() not in keep), None)
        if name is None:  # coordinates and colors only (PCD's office1, XYZ): nothing to drop, and they stay
            with pytest.raises(prism_stream.PrismError, match="--drop 'red': the output keeps its coordinates"):
                prism_stream.sample(str(path), str(tmp_path / "some.parquet"), ratio=0.5, drop=("red",))
            return
        prism_stream.sample(str(path), str(tmp_path / "some.parquet"), ratio=0.5, seed=3, drop=(name,))
    some = pq.read_table(tmp_path / "some.parquet")
    assert name not in some.column_names and some.num_rows == every.num_rows > 0
    assert some.equals(every.drop_columns([name]).replace_schema_metadata(some.schema.metadata))


def test_the_python_keywords_are_the_command_lines(tmp_path):
    """README: every keyword of `sample` is a field of Request, named as its command-line option. `format=`
    (--format) was a TypeError (only `output_format` was known), and `scale=0.001` (--scale 0.001) a bare
    TypeError from inside the request."""
    import warnings

    import laspy

    from prism_stream.errors import UsageError

    src = str(real_file("pdal__autzen_trim.las"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = prism_stream.sample(src, str(tmp_path / "d") + "/", ratio=0.1, format="laz")
        assert [os.path.basename(p) for p in s.outputs] == ["pdal__autzen_trim.laz"]
        prism_stream.sample(str(real_file("pcl__office1.pcd")), str(tmp_path / "o.las"), ratio=0.1, scale=0.001)
    assert list(laspy.read(tmp_path / "o.las").header.scales) == [0.001] * 3
    assert prism_stream.Request(ratio=0.1, scale=0.01).scale == (0.01,)
    import numpy as np

    assert prism_stream.Request(ratio=0.1, scale=np.int64(1)).scale == (1.0,)  # a numpy number too
    assert prism_stream.Request(ratio=0.1, scale=[0.01, 0.01, 0.1]).scale == (0.01, 0.01, 0.1)
    with pytest.raises(UsageError, match="positive"):
        prism_stream.Request(ratio=0.1, scale=0)
    with pytest.raises(TypeError, match="not both"):
        prism_stream.sample(src, str(tmp_path / "e") + "/", ratio=0.1, format="laz", output_format="las")


def test_plan_of_a_small_input_says_why_it_has_no_temporary_disk(capsys, monkeypatch):
    """README: --plan prints the expected spill and the free space; a small input held in memory printed
    neither, leaving a user in doubt. It now says there is none, and why."""
    monkeypatch.delenv("PRISM_STREAM_MEMORY_POINTS", raising=False)  # the default: held in memory
    code, out, err = cli(capsys, real_file("pdal__autzen_trim.las"), "--plan", "--ratio", "0.01")
    assert code == 0 and "temp        none: a small input" in out and "held in memory" in out, out + err
    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", "0")  # streamed: the forecast, as before
    code, out, err = cli(capsys, real_file("pdal__autzen_trim.las"), "--plan", "--ratio", "0.01")
    assert code == 0 and "temp        none" not in out and "free in" in out, out + err


# -- a hostile tester: an output a later run over the same inputs would read as one more input ---------------

def test_an_output_inside_its_input_folder_or_pattern_is_said(tmp_path):
    """``prism-stream tiles tiles/sample.parquet`` (or ``'tiles/*.laz' tiles/s.laz``): the next run over tiles
    would sample this run's sample too; the run says so before pass one. Outside the folder, or in a hidden
    folder (which a folder input skips), nothing is said."""
    import shutil
    import warnings

    from prism_stream.errors import PrismWarning

    (tmp_path / "tiles").mkdir()
    shutil.copy(real_file("laspy__fullwave.laz"), tmp_path / "tiles" / "a.laz")
    tiles = tmp_path / "tiles"
    with pytest.warns(PrismWarning, match=f"is inside the input folder {tiles}: a later run over {tiles} reads it"):
        prism_stream.sample(str(tiles), str(tiles / "sample.parquet"), ratio=0.1)
    with pytest.warns(PrismWarning, match=r"matches the input pattern .*tiles/\*\.laz: a later run"):
        prism_stream.sample(str(tiles / "*.laz"), str(tiles / "s.laz"), ratio=0.1)
    (tiles / ".hidden").mkdir()
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        prism_stream.sample(str(tiles / "a.laz"), str(tmp_path / "out.parquet"), ratio=0.1)
        prism_stream.sample(str(tiles), str(tiles / ".hidden" / "out.parquet"), ratio=0.1)
    assert not [w for w in said if "one more input" in str(w.message)]
