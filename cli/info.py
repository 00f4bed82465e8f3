"""``prism-stream info``: what a cloud is, from its headers; with a target, what a run would keep."""

from __future__ import annotations

import json
import sys

import click

from . import options as o


@click.command("info", short_help="Describe clouds from their headers: points, bounds, CRS, colors.")
@click.argument("inputs", nargs=-1, required=True, metavar="INPUT...")
@o.request_options(only=("ratio", "count", "k", "mode", "color_space", "quant_bits", "quant_step", "color_depth",
                         "rgb_columns", "threads"))
@o.as_json
def info(inputs, as_json, **options):
    """Describe INPUT... (files, globs, folders) from their headers: format and version, points, bounds,
    CRS, the color columns and the color depth their types allow, every column, and for a file prism-stream
    wrote its provenance. Nothing is decoded.

    With --ratio, --count or --k, pass one also runs over the colors (as `sample --plan` does): each file's
    color depth as decided by its values, the distinct bins, K and T.

    \b
    Examples:
      prism-stream info big.laz
      prism-stream info 'tiles/*.laz' --ratio 0.01 --json
    """
    o.small_pages()  # before pyarrow loads (run.info loads it)
    from prism_stream.run.info import info as describe, text

    from prism_stream.run.request import split_columns

    if any(options.get(k) is not None for k in ("ratio", "count", "k")):
        data = describe(inputs, o.request_of(options))
    else:  # the headers alone: the options that say how to read them
        columns = options.get("rgb_columns")
        data = describe(inputs, None, open_options={"threads": options.get("threads") or 1,
                                                    "rgb_columns": split_columns(columns) if columns else None})
    failed = data.pop("errors", [])
    if as_json and failed:
        data["errors"] = [{"path": e.path, "error": e.message, "exit_code": e.exit_code} for e in failed]
    click.echo(json.dumps(data, indent=2, default=str) if as_json else text(data))
    for e in failed:  # what could not be described, after what could (as `check` goes on past a file)
        click.echo(f"prism-stream: error: {e}", err=True)
    if failed:
        sys.exit(failed[-1].exit_code)
