"""``prism-stream eval``: PRISM against Random, Voxel grid and NSS, as the paper's Tables 1 and 3."""

from __future__ import annotations

import json
import sys

import click

from prism_stream.run.request import split_columns

from . import options as o


def _numbers(text: str | None, kind, name: str) -> list:
    if not text:
        return []
    try:
        return [kind(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise click.BadParameter(f"give comma-separated {kind.__name__}s, not {text!r}", param_hint=name) from None


@click.command("eval", short_help="Compare PRISM with Random, Voxel and NSS (CD, HD, entropy).")
@click.argument("inputs", nargs=-1, required=True, metavar="INPUT...")
@click.option("--ratio", "-r", default="0.01", show_default=True,
              help="Target ratio(s), comma-separated, e.g. 0.01,0.05,0.1.")
@click.option("--methods", default="prism,random,voxel,nss", show_default=True, help="Methods, comma-separated.")
@click.option("--mode", "modes", default="exact", show_default=True,
              help="PRISM quota rule(s): exact, paper, or exact,paper.")
@o.request_options(only=("color_space", "quant_bits", "quant_step", "k"), unset=("color_space", "quant_bits"))
@click.option("--ablation", is_flag=True, help="Also run the paper's ablation (Table 3): chroma and rgb x "
              "quantization 1, 2, 4 (as steps and as bits), k fixed.")
@click.option("--ablation-protocol", default="paper", show_default=True,
              help="paper: k fixed (--ablation-k); ratio: each --ratio in exact mode, rgb/chroma x bits 0/1/2/4.")
@click.option("--ablation-k", type=click.IntRange(1), default=10, show_default=True,
              help="The fixed k of the paper-protocol ablation.")
@click.option("--entropy-bins", default="rgb8", show_default=True, help="Entropy histogram(s): rgb8, sampler, "
              "rgb-grid, hue-sat, comma-separated, or all (first = headline).")
@click.option("--baselines", default="equal-t", show_default=True,
              help="equal-t: baselines aim at PRISM's T; paper: centroid voxel grid at --voxel-size, NSS at "
                   "--nss-per-bin.")
@click.option("--nss-per-bin", type=click.IntRange(1), help="NSS at its own size: points kept per normal bin "
              "(--baselines paper).")
@click.option("--denoise", metavar="sor:K,STD", help="Remove statistical outliers first (Open3D's rule, streamed in XY tiles of --tile-points).")
@click.option("--preset", help="authors: the authors' script (sor:100,2.0, "
              "chroma, step 1, k = 1) for whatever is not given.")
@click.option("--k-sweep", help="Fixed bin capacities, e.g. 1,2,5,10,20: the k-sensitivity series (ratio against k).")
@click.option("--plots", "plots_dir", metavar="FOLDER", help="Write PNG figures into this folder (needs matplotlib).")
@click.option("--out", multiple=True, metavar="FILE", help="Write the tables to .csv, .json or .md (repeatable).")
@click.option("--voxel-size", type=float, help="Fixed voxel size for the voxel grid (default: searched to land "
              "near each target).")
@click.option("--nss-k", type=click.IntRange(3), default=10, show_default=True,
              help="Neighbours per normal estimate (NSS).")
@click.option("--tile-points", type=click.IntRange(1000), default=2_000_000, show_default=True,
              help="Points per NSS normal tile.")
@click.option("--sweep", type=click.Choice(["ranks", "runs"]), default="ranks", show_default=True,
              help="PRISM exact rows at several ratios: ranks: rank once up to the largest ratio and take each "
                   "sample as the points of rank < T (same rows, one run); runs: one run per ratio.")
@click.option("--no-distances", is_flag=True, help="Skip Chamfer and Hausdorff (one input pass per row).")
@o.request_options(only=("seed", "color_depth", "chunk_size", "threads", "rgb_columns", "temp_dir"), helps={
    "threads": "Decoder threads (LAZ, Parquet) (default: every core).",
    "temp_dir": "Folder for the evaluation's temporary files: the outlier removal's tiles, the ranked copy of "
                "each cloud (default: system temp)."})
@click.option("--json", "as_json", is_flag=True, help="Print the tables as JSON instead of text.")
@o.quiet
def evaluate(inputs, ratio, methods, modes, color_space, quant_bits, quant_step, k, ablation, ablation_protocol,
             ablation_k, entropy_bins, baselines, nss_per_bin, denoise, preset, k_sweep, plots_dir, out, voxel_size,
             nss_k, tile_points, sweep, no_distances, seed, color_depth, chunk_size, threads, rgb_columns, temp_dir, as_json,
             quiet):
    """Evaluate PRISM against Random, Voxel grid and NSS: CD, HD, color entropy gain, time, memory.

    Each INPUT (a file, glob or folder) is one cloud.

    \b
    Examples:
      prism-stream eval cloud.laz --ratio 0.01,0.05 --out table.csv --plots figs/
      prism-stream eval cloud.ply --preset authors --entropy-bins all --ablation
    """
    # here, not at the top: scipy and matplotlib load only for `eval`
    from prism_stream.evaluate import plots, report
    from prism_stream.evaluate.run import evaluate as run_evaluation

    for path in out:
        report.check_out(path)  # fail before the work, not after it
    if plots_dir is not None:
        plots._pyplot()

    def log(msg: str) -> None:
        if not quiet:
            sys.stderr.write(msg + "\n")

    result = run_evaluation(
        list(inputs), ratios=_numbers(ratio, float, "--ratio"), methods=methods.split(","), modes=modes.split(","),
        seed=seed, ablation=ablation, ablation_protocol=ablation_protocol, ablation_k=ablation_k,
        entropy_bins=entropy_bins, color_space=color_space, quant_bits=quant_bits, quant_step=quant_step, k=k,
        baselines=baselines, nss_per_bin=nss_per_bin, denoise=denoise, preset=preset, previews=plots_dir is not None,
        k_sweep=_numbers(k_sweep, int, "--k-sweep"), voxel_size=voxel_size, nss_k=nss_k, tile_points=tile_points,
        metrics=not no_distances, chunk_size=chunk_size, threads=threads,
        rgb_columns=split_columns(rgb_columns) if rgb_columns else None, color_depth=color_depth, temp_dir=temp_dir,
        sweep=sweep, log=log,
    )
    for path in out:
        report.write(result, path)
        log(f"wrote {path}")
    if plots_dir is not None:
        for path in plots.write_figures(result, plots_dir):
            log(f"wrote {path}")
    if as_json:
        click.echo(json.dumps(result.as_dict(), indent=2))
    elif not quiet:
        click.echo(report.render(result))
