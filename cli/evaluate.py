"""``prism-stream eval``: PRISM against Random, Voxel grid and NSS, as the paper's Tables 1 and 3."""

from __future__ import annotations

import json
import sys

import click

from prism_stream.evaluate.options import EvalOptions

from . import options as o


@click.command("eval", short_help="Compare PRISM with Random, Voxel and NSS (CD, HD, entropy).")
@click.argument("inputs", nargs=-1, required=True, metavar="INPUT...")
@o.dataclass_options(EvalOptions)
@o.request_options(only=("color_space", "quant_bits", "quant_step", "k"), unset=("color_space", "quant_bits"))
@click.option("--plots", "plots_dir", metavar="FOLDER", help="Write PNG figures into this folder (needs matplotlib).")
@click.option("--out", multiple=True, metavar="FILE", help="Write the tables to .csv, .json or .md (repeatable; replaces a file of that name).")
@o.request_options(only=("seed", "color_depth", "chunk_size", "threads", "rgb_columns", "temp_dir"), helps={
    "threads": "Decoder threads (LAZ, Parquet) (default: every core it may use).",
    "temp_dir": "Folder for the evaluation's temporary files: the outlier removal's tiles, the ranked copy of "
                "each cloud (default: system temp)."})
@click.option("--json", "as_json", is_flag=True, help="Print the tables as JSON instead of text.")
@o.quiet
def evaluate(inputs, plots_dir, out, as_json, quiet, **values):
    """Evaluate PRISM against Random, Voxel grid and NSS: CD, HD, color entropy gain, time, memory.

    Each INPUT (a file, glob or folder) is one cloud. The table goes to stdout (with --quiet too, unless --out
    writes it); progress to stderr.

    \b
    Examples:
      prism-stream eval cloud.laz --ratio 0.01,0.05 --out table.csv --plots figs/
      prism-stream eval cloud.ply --preset authors --entropy-bins all --ablation
    """
    o.small_pages()  # before pyarrow loads (the imports below load it)
    # here, not at the top: scipy and matplotlib load only for `eval`
    from prism_stream.evaluate import plots, report
    from prism_stream.evaluate.run import evaluate as run_evaluation

    for path in out:
        report.check_out(path)  # fail before the work, not after it
    if plots_dir is not None:
        report.check_folder(plots_dir)  # a file of that name: said now, not after the whole evaluation
        plots._pyplot()

    def log(msg: str) -> None:
        if not quiet:
            sys.stderr.write(msg + "\n")

    result = run_evaluation(list(inputs), log=log, previews=plots_dir is not None, **values)
    for path in out:
        report.write(result, path)
        log(f"wrote {path}")
    if plots_dir is not None:
        for path in plots.write_figures(result, plots_dir):
            log(f"wrote {path}")
    if as_json:
        click.echo(json.dumps(result.as_dict(), indent=2))
    elif not quiet or not out:  # --quiet keeps the table when it is written nowhere else (the result itself)
        click.echo(report.render(result))
