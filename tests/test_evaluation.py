"""`prism-stream eval` reproduces the paper's comparison: its qualitative result, its tables, its figures."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys

import numpy as np
import pytest

import prism_stream
from conftest import REAL, real_file
from prism_stream.errors import UnsupportedFormat
from prism_stream.evaluate import Cloud, read_sample
from prism_stream.evaluate.metrics import entropy_bits
from prism_stream.evaluate.run import PeakMemory, evaluate

REAL_CLOUDS = sorted(p.name for p in REAL.iterdir())


def readable(path):
    """The path, once prism_stream has opened it: every committed real cloud must have a reader."""
    try:
        with Cloud(str(path)):
            pass
    except UnsupportedFormat as exc:
        pytest.fail(f"prism_stream cannot read a committed real cloud: {exc}")
    return path


@pytest.mark.parametrize("name", REAL_CLOUDS)
def test_prism_gains_more_color_entropy_than_random_at_equal_size(name):
    """The paper's qualitative result, on every real cloud we can read.

    Exact mode keeps the max-entropy allocation of T points over the color
    bins (every bin min(n_b, K), K or K+1), so it can only tie Random, and
    only when Random's T points also fall in T distinct colors.
    """
    path = readable(real_file(name))
    result = evaluate([str(path)], ratios=(0.01, 0.1), methods=("prism", "random"), metrics=False)
    rows = {(r.method, r.target_ratio): r for r in result.rows}
    for ratio in (0.01, 0.1):
        prism, rand = rows["PRISM (exact)", ratio], rows["Random", ratio]
        assert prism.count == rand.count == prism.target  # equal output size
        assert rand.entropy_gain <= 0.05  # near zero or negative
        assert prism.entropy_gain >= rand.entropy_gain - 1e-12
        if prism.entropy_gain == pytest.approx(rand.entropy_gain, abs=1e-12):
            assert rand.entropy_output == pytest.approx(math.log2(rand.count))  # the tie: both all-distinct
    assert rows["PRISM (exact)", 0.1].entropy_gain > rows["Random", 0.1].entropy_gain


def test_the_command_writes_table_1_ablation_k_sweep_and_figures(tmp_path):
    src = real_file("pdal__warsaw_small.las")
    csv_path, json_path, figs = tmp_path / "t.csv", tmp_path / "t.json", tmp_path / "figs"
    cmd = [sys.executable, "-m", "prism_stream_cli.main", "eval", str(src), "--ratio", "0.05,0.1", "--mode",
           "exact,paper", "--ablation", "--ablation-protocol", "ratio", "--k-sweep", "1,2,5", "--plots", str(figs), "--out", str(csv_path),
           "--out", str(json_path), "--out", str(tmp_path / "t.md"), "--quiet"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    data = json.loads(json_path.read_text())
    methods = {r["method"] for r in data["table"]}
    assert methods == {"PRISM (exact)", "PRISM (paper)", "Random", "Voxel grid", "NSS"}
    assert len(data["table"]) == 2 * 5 and len(data["ablation"]) == 2 * 8 and len(data["k_sweep"]) == 3
    for r in data["table"]:
        assert r["chamfer"] > 0 and r["hausdorff"] >= r["chamfer"] / 2 and r["seconds"] > 0
        assert r["peak_rss_mib"] > 0 and r["count"] > 0
        assert r["entropy_gain"] == pytest.approx(r["entropy_output"] - r["entropy_input"])
        if r["method"] in ("PRISM (exact)", "Random", "NSS"):
            assert r["count"] == r["target"]
    rows = list(csv.DictReader(csv_path.open()))
    assert {r["table"] for r in rows} == {"main", "ablation", "k_sweep"} and len(rows) == 10 + 16 + 3
    md = (tmp_path / "t.md").read_text()
    assert md.count("| PRISM (exact) |") == 2 and "### Ablation" in md and "### k sensitivity" in md
    pngs = sorted(p.name for p in figs.iterdir())
    assert pngs == sorted([f"{kind}_pdal__warsaw_small.las_r{r}.png" for kind in ("chroma", "chroma_bars", "topdown")
                           for r in ("0.05", "0.1")] + ["k_sweep.png", "metrics_pdal__warsaw_small.las.png"])
    assert all((figs / p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)


def test_k_sweep_from_the_plan_equals_a_real_run_with_that_k(tmp_path):
    src = str(real_file("pdal__warsaw_small.las"))
    result = evaluate([src], ratios=(0.1,), methods=("random",), metrics=False, k_sweep=(2,))
    k = result.k_sweep[0]
    out = tmp_path / "k2.parquet"
    prism_stream.sample(src, str(out), k=2)
    with Cloud(src) as cloud:
        s = read_sample(str(out), cloud)
    assert k.count == s.points
    assert k.entropy_output == pytest.approx(entropy_bits(s.histogram.counts))


def test_the_table_text_reads_like_table_1():
    from prism_stream.evaluate.report import render

    src = str(real_file("pdal__warsaw_small.las"))
    text = render(evaluate([src], ratios=(0.1,), methods=("prism", "voxel")))
    header = text.splitlines()[1].split()
    assert header[:6] == ["Method", "Dataset", "Ratio", "CD", "HD", "Entropy"]
    assert "Voxel grid" in text and "PRISM (exact)" in text and "10.000%" in text


@pytest.mark.parametrize("args, code, message", [
    (["--methods", "prism,magic"], 2, "--methods takes"),
    (["--ratio", "2"], 2, "--ratio must be in (0, 1]"),
    (["--out", "table.txt"], 2, "--out must end in .csv, .json or .md"),
    (["--ratio", "0.1,abc"], 2, "--ratio: give comma-separated floats"),
    (["--k-sweep", "1,x"], 2, "--k-sweep: give comma-separated ints"),
])
def test_bad_options_are_one_line_errors(tmp_path, args, code, message):
    src = str(real_file("pdal__warsaw_small.las"))
    done = subprocess.run([sys.executable, "-m", "prism_stream_cli.main", "eval", src, "--methods", "random",
                           "--quiet", *args], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert done.returncode == code
    assert message in done.stderr and "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


def test_plots_naming_a_file_is_refused_before_the_work(tmp_path):
    """It was an internal error (FileExistsError) once every table had been computed and written."""
    (tmp_path / "plotfile").write_text("keep")
    src = str(real_file("pdal__warsaw_small.las"))
    done = subprocess.run([sys.executable, "-m", "prism_stream_cli.main", "eval", src, "--methods", "random",
                           "--plots", "plotfile", "--out", "t.csv"], capture_output=True, text=True, cwd=tmp_path,
                          timeout=120)
    assert done.returncode == 8 and "plotfile: --plots names a file" in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "t.csv").exists() and (tmp_path / "plotfile").read_text() == "keep"


def test_quiet_keeps_the_table_when_it_goes_nowhere_else(tmp_path):
    """`eval -q` without --out printed nothing at all, the evaluation computed and lost; -q now silences the
    progress lines, and the table is printed unless --out writes it."""
    src = str(real_file("pdal__warsaw_small.las"))
    base = [sys.executable, "-m", "prism_stream_cli.main", "eval", src, "--methods", "random", "--ratio", "0.1",
            "--quiet"]
    alone = subprocess.run(base, capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert alone.returncode == 0 and "Random" in alone.stdout and not alone.stderr, alone.stderr
    written = subprocess.run([*base, "--out", "t.csv"], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert written.returncode == 0 and not written.stdout.strip() and (tmp_path / "t.csv").exists()


def test_a_missing_input_is_a_one_line_error(tmp_path):
    done = subprocess.run([sys.executable, "-m", "prism_stream_cli.main", "eval", str(tmp_path / "nope.las")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 3 and "nope.las: no such file" in done.stderr and "Traceback" not in done.stderr


def test_peak_memory_is_the_blocks_own():
    with PeakMemory() as m:
        a = np.ones(40_000_000)  # 305 MiB
        a[::512] = 2
        del a
    # Linux resets the kernel's high-water mark (clear_refs), so the peak is the block's own; elsewhere
    # the fallback is the process's lifetime peak from 0, which still covers the block: no skip either way
    assert m.exact == sys.platform.startswith("linux")
    assert m.peak - m.start >= 250


def test_a_ratio_sweep_from_one_rank_run_gives_each_runs_sample():
    """--sweep ranks (the default) samples every ratio from one rank run: the same rows as one run per ratio."""
    src = str(REAL / "pdal__autzen_trim.las")
    kw = dict(ratios=(0.01, 0.03, 0.2), methods=("prism",), modes=("exact", "paper"), metrics=True, seed=6,
              entropy_bins=("rgb8", "sampler"))
    ranked, runs = evaluate([src], **kw), evaluate([src], sweep="runs", **kw)
    assert ranked.settings["sweep"] == "ranks" and runs.settings["sweep"] == "runs"
    assert len(ranked.rows) == len(runs.rows) == 6
    for a, b in zip(ranked.rows, runs.rows):
        assert (a.method, a.target_ratio, a.count, a.chamfer, a.hausdorff, a.entropy) == \
               (b.method, b.target_ratio, b.count, b.chamfer, b.hausdorff, b.entropy)
        assert a.params.get("from_ranks", False) == (a.params["mode"] == "exact")


def test_the_library_takes_a_request_and_eval_options():
    """evaluate(datasets, Request, EvalOptions): the sampling options declared once (the Request's), the
    evaluation's own beside them; keywords of either override them, as the command line's options do."""
    from prism_stream import Request
    from prism_stream.evaluate.options import EvalOptions

    src = str(real_file("pdal__warsaw_small.las"))
    options = EvalOptions(ratios="0.05,0.1", methods="prism", metrics=False)
    by_objects = evaluate([src], Request(ratio=0.5, color_space="chroma", quant_bits=1, seed=3), options)
    by_keywords = evaluate([src], ratios=(0.05, 0.1), methods=("prism",), metrics=False, color_space="chroma",
                           quant_bits=1, seed=3)
    for a, b in zip(by_objects.rows, by_keywords.rows, strict=True):
        assert (a.target_ratio, a.count, a.entropy) == (b.target_ratio, b.count, b.entropy)
    assert [r.target_ratio for r in by_objects.rows] == [0.05, 0.1]  # the rows' targets, not the Request's
    assert by_objects.settings["strata"]["color_space"] == "chroma" and by_objects.settings["seed"] == 3
    with pytest.raises(TypeError, match="unknown option"):
        evaluate([src], ratioz=0.1)

