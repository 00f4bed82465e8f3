"""``prism-stream sql``: sample the result of a DuckDB query."""

from __future__ import annotations

import click

from . import options as o
from .report import check_summary_file, emit


@click.command("sql", short_help="Sample the rows of a DuckDB SQL query.")
@click.argument("query")
@click.argument("output", required=False)
# a query is read twice (its size is not known up front) and has one schema: --reads and --columns do not apply
@o.request_options(exclude=("flag", "output_format", "per_file", "order", "denoise", "preset", "reads", "columns"),
                   helps={
    "threads": "DuckDB's threads for the query, and read-ahead (default: every core it may use).",
    "temp_dir": "Folder for the key cache, DuckDB's own spill and --materialize spool's copy of the result "
                "(default: system temp)."})
@click.option("--plan", "plan_only", is_flag=True, help="Pass one and the solve only; write nothing (an OUTPUT "
              "given is checked as the run checks it).")
@click.option("--materialize", type=click.Choice(("rerun", "spool")), default="rerun", show_default=True,
              help="rerun: run the query once per pass (pass one reads only the color columns); spool: write its "
                   "result once to a Parquet file in --temp-dir and read that twice (for queries whose row order "
                   "is not deterministic).")
@click.option("--database", metavar="FILE", help="A DuckDB database file to query (opened read-only).")
@click.option("--memory-limit", metavar="SIZE", help="DuckDB memory_limit, e.g. 4GB.")
@o.report_options
def sql(query, output, plan_only, as_json, summary_file, quiet, **options):
    """Sample the rows a SQL query returns (DuckDB), streaming its result twice (three times with --space).

    \b
    Example:
      prism-stream sql "SELECT * FROM read_parquet('tiles/*.parquet') WHERE classification <> 7" \\
          out.parquet --ratio 0.01
    """
    if not plan_only and output is None:
        raise click.UsageError("give the output file (or --plan)")
    duckdb = {name: options.pop(name) for name in ("materialize", "database", "memory_limit")}
    request = o.request_of(options, progress=not quiet and not as_json)
    check_summary_file(summary_file, [duckdb["database"]], [output], request.overwrite)
    # here, not at the top: `prism-stream` starts without DuckDB
    from prism_stream.engines.sql import output_layout, sample_query

    if plan_only and output is not None:  # the run's OUTPUT: checked as the run checks it, not written
        output_layout(output, request.overwrite)
    summary = sample_query(query, None if plan_only else output, request, **duckdb)
    data = summary.as_dict()
    if plan_only and output is not None:
        data["planned_output"] = output
    emit(data, as_json=as_json, summary_file=summary_file, quiet=quiet, plan=plan_only, overwrite=request.overwrite)
