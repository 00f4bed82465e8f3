"""``prism-stream rank``: every point's PRISM rank, so that any prefix of the ranks is an exact sample."""

from __future__ import annotations

import re

import click

from prism_stream.errors import UsageError

from . import options as o
from .report import check_summary_file, emit
from .sample import _paths

RANK_COLUMN = "prism_rank"


@click.command("rank", short_help="Rank every point: ranks below T are the sample of T.")
@click.argument("paths", nargs=-1, required=True, metavar="INPUT... OUTPUT")
@click.option("--max-ratio", type=float, metavar="R", help="Keep only the points of rank < floor(R N + 0.5): the "
              "sample for that ratio, ranked (default: every point).")
@click.option("--max-count", type=int, metavar="T", help="Keep only the points of rank < T.")
@o.request_options(exclude=("ratio", "count", "k", "mode", "flag", "per_file"), helps={
    "temp_dir": "Folder for the key cache and the ranks' sort (default: system temp; with --dask the units' "
                "spills go beside the output)."})
@click.option("--dask", metavar="ADDRESS|local:N", help="Run on a Dask cluster (see `sample --help`); OUTPUT is a "
              "Parquet dataset folder.")
@o.report_options
def rank(paths, max_ratio, max_count, dask, as_json, summary_file, quiet, **options):
    """Rank every point (exact mode): the points of rank < T are exactly the sample for T.

    Writes the points with a `prism_rank` column (Parquet), int64 extra-bytes
    dimension (LAS/LAZ) or vertex property (PLY). For a fixed seed exact-mode
    samples nest, so one ranked file holds every ratio at once:
    `SELECT * EXCLUDE (prism_rank) FROM 'ranked.parquet' WHERE prism_rank <
    floor(0.01 * N + 0.5)` is the same rows as `prism-stream IN OUT --ratio
    0.01`, with N the input's points (the summary's `points`). Exact mode
    only.

    \b
    Examples:
      prism-stream rank big.laz ranked.parquet
      prism-stream rank big.laz preview.laz --max-ratio 0.1 --order rank
    """
    if len(paths) < 2:
        raise click.UsageError("give at least one input and the output")
    if max_ratio is not None and max_count is not None:
        raise click.UsageError("give --max-ratio or --max-count, not both")
    if max_ratio is not None and not 0 < max_ratio <= 1:  # NaN fails too
        raise click.UsageError(f"--max-ratio must be in (0, 1], not {max_ratio}")
    if max_count is not None and max_count < 1:
        raise click.UsageError(f"--max-count must be a positive integer, not {max_count}")
    target = {"count": max_count} if max_count is not None else {"ratio": max_ratio if max_ratio is not None else 1.0}
    inputs, output = list(paths[:-1]), paths[-1]
    request = o.request_of(options, progress=not quiet and not as_json, rank=RANK_COLUMN, **target)
    if summary_file is not None:
        check_summary_file(summary_file, *_paths(inputs, output, request, dask), request.overwrite)
    engine = o.engine(dask)
    try:
        summary = engine(inputs, output, request)
    except UsageError as exc:  # the target options are named --max-* here
        exc.message = re.sub(r"(?<![\w-])--(ratio|count)\b", r"--max-\1", str(exc.message))
        raise
    emit(summary.as_dict(), as_json=as_json, summary_file=summary_file, quiet=quiet, overwrite=request.overwrite)
