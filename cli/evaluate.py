"""``prism-stream eval``: PRISM against Random, Voxel grid and NSS, as the paper's Table 1."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import List, Optional

import typer

from . import options as o


def _floats(text: str, name: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise typer.BadParameter(f"give comma-separated numbers, not {text!r}", param_hint=name) from None


def _ints(text: Optional[str], name: str) -> list[int]:
    if not text:
        return []
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise typer.BadParameter(f"give comma-separated integers, not {text!r}", param_hint=name) from None


def evaluate(
    inputs: List[str] = typer.Argument(..., metavar="INPUT...",
                                       help="Datasets: each argument (a file, glob or Parquet folder) is one cloud."),
    ratio: str = typer.Option("0.01", "--ratio", "-r", help="Target ratio(s), comma-separated, e.g. 0.01,0.05,0.1."),
    methods: str = typer.Option("prism,random,voxel,nss", "--methods", help="Methods, comma-separated."),
    mode: str = typer.Option("exact", "--mode", help="PRISM quota rule(s): exact, paper, or exact,paper."),
    seed: int = o.Seed,
    ablation: bool = typer.Option(False, "--ablation", help="Also run the paper's ablation (Table 3): chroma and "
                                  "rgb x quantization 1, 2, 4 (as steps and as bits), k fixed."),
    ablation_protocol: str = typer.Option("paper", "--ablation-protocol", help="paper: k fixed (--ablation-k); "
                                          "ratio: each --ratio in exact mode, rgb/chroma x bits 0/1/2/4."),
    ablation_k: int = typer.Option(10, "--ablation-k", help="The fixed k of the paper-protocol ablation."),
    entropy_bins: str = typer.Option("rgb8", "--entropy-bins", help="Entropy histogram(s): rgb8, sampler, "
                                     "rgb-grid, hue-sat, comma-separated, or all (first = headline)."),
    color_space: Optional[str] = typer.Option(None, "--color-space", help="PRISM's color space: rgb (default) "
                                              "or chroma."),
    quant_bits: Optional[int] = typer.Option(None, "--quant-bits", help="PRISM: low bits dropped per channel."),
    quant_step: Optional[float] = typer.Option(None, "--quant-step", help="PRISM: float quantization step q "
                                               "(the authors' script's -q), >= 1."),
    k: Optional[int] = typer.Option(None, "--k", help="PRISM at a fixed bin capacity k instead of the ratio; "
                                    "equal-T baselines then aim at PRISM's count."),
    baselines: str = typer.Option("equal-t", "--baselines", help="equal-t: baselines aim at PRISM's T; paper: "
                                  "centroid voxel grid at --voxel-size, NSS at --nss-per-bin."),
    nss_per_bin: Optional[int] = typer.Option(None, "--nss-per-bin", help="NSS at its own size: points kept "
                                              "per normal bin (--baselines paper)."),
    denoise: Optional[str] = typer.Option(None, "--denoise", help="Remove statistical outliers first: sor:K,STD "
                                          "(Open3D's rule; in memory)."),
    preset: Optional[str] = typer.Option(None, "--preset", help="authors: the authors' script (sor:100,2.0, "
                                         "chroma, step 1, k = 1) for whatever is not given."),
    k_sweep: Optional[str] = typer.Option(None, "--k-sweep", help="Fixed bin capacities, e.g. 1,2,5,10,20: "
                                          "the k-sensitivity series (ratio against k)."),
    plots_dir: Optional[Path] = typer.Option(None, "--plots", help="Write PNG figures into this folder "
                                             "(needs matplotlib: prism-stream[eval])."),
    out: Optional[List[Path]] = typer.Option(None, "--out", help="Write the tables to .csv, .json or .md (repeatable)."),
    voxel_size: Optional[float] = typer.Option(None, "--voxel-size", help="Fixed voxel size for the voxel grid "
                                               "(default: searched to land near each target)."),
    nss_k: int = typer.Option(10, "--nss-k", min=3, help="Neighbours per normal estimate (NSS)."),
    tile_points: int = typer.Option(2_000_000, "--tile-points", min=1000, help="Points per NSS normal tile."),
    no_distances: bool = typer.Option(False, "--no-distances", help="Skip Chamfer and Hausdorff (one input "
                                      "pass per row)."),
    color_depth: str = o.ColorDepth,
    chunk_size: int = o.ChunkSize,
    threads: int = o.Threads,
    rgb_columns: Optional[str] = o.RgbColumns,
    temp_dir: Optional[str] = o.TempDir,
    as_json: bool = typer.Option(False, "--json", help="Print the tables as JSON instead of text."),
    quiet: bool = o.Quiet,
):
    """Evaluate PRISM against Random, Voxel grid and NSS: CD, HD, color entropy gain, time, memory.

    Example: prism-stream eval cloud.laz --ratio 0.01,0.05 --out table.csv --plots figs/
    """
    # here, not at the top: scipy and matplotlib load only for `eval`
    from prism_stream.evaluate import plots, report
    from prism_stream.evaluate.run import evaluate as run_evaluation

    for path in out or []:
        report.check_out(str(path))  # fail before the work, not after it
    if plots_dir is not None:
        plots._pyplot()

    def log(msg: str) -> None:
        if not quiet:
            sys.stderr.write(msg + "\n")

    result = run_evaluation(
        inputs, ratios=_floats(ratio, "--ratio"), methods=methods.split(","), modes=mode.split(","), seed=seed,
        ablation=ablation, ablation_protocol=ablation_protocol, ablation_k=ablation_k,
        entropy_bins=entropy_bins, color_space=color_space, quant_bits=quant_bits, quant_step=quant_step, k=k,
        baselines=baselines, nss_per_bin=nss_per_bin, denoise=denoise, preset=preset, previews=plots_dir is not None,
        k_sweep=_ints(k_sweep, "--k-sweep"), voxel_size=voxel_size, nss_k=nss_k,
        tile_points=tile_points, metrics=not no_distances, chunk_size=chunk_size, threads=threads,
        rgb_columns=o.split_columns(rgb_columns), color_depth=color_depth, temp_dir=temp_dir, log=log,
    )
    for path in out or []:
        report.write(result, str(path))
        log(f"wrote {path}")
    if plots_dir is not None:
        for path in plots.write_figures(result, str(plots_dir)):
            log(f"wrote {path}")
    if as_json:
        typer.echo(json.dumps(result.as_dict(), indent=2))
    elif not quiet:
        typer.echo(report.render(result))
