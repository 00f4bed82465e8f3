"""``prism-stream sql``: sample the result of a DuckDB query."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from . import options as o
from .report import print_summary


def sql(
    query: str = typer.Argument(..., help="A DuckDB SELECT, e.g. \"SELECT * FROM read_parquet('tiles/*.parquet') "
                                "WHERE classification <> 7\"."),
    output: Optional[str] = typer.Argument(None, help="The output (.parquet). Omit with --plan."),
    ratio: Optional[float] = o.Ratio,
    count: Optional[int] = o.Count,
    k: Optional[int] = o.K,
    mode: str = o.Mode,
    color_space: str = o.ColorSpace,
    quant_bits: int = o.QuantBits,
    quant_step: Optional[float] = o.QuantStep,
    color_depth: str = o.ColorDepth,
    seed: int = o.Seed,
    plan: bool = typer.Option(False, "--plan", help="Pass one and the solve only; write nothing."),
    chunk_size: int = o.ChunkSize,
    rgb_columns: Optional[str] = o.RgbColumns,
    materialize: str = typer.Option("rerun", "--materialize", help="rerun: run the query once per pass (pass one "
                                    "reads only the color columns); spool: write its result once to a Parquet "
                                    "file in --temp-dir and read that twice (for queries whose row order is not "
                                    "deterministic)."),
    database: Optional[str] = typer.Option(None, "--database", help="A DuckDB database file to query "
                                           "(opened read-only)."),
    memory_limit: Optional[str] = typer.Option(None, "--memory-limit", help="DuckDB memory_limit, e.g. 4GB."),
    threads: Optional[int] = typer.Option(None, "--threads", min=1, help="DuckDB threads."),
    as_json: bool = o.Json,
    summary_file: Optional[Path] = o.SummaryFile,
    overwrite: bool = o.Overwrite,
    quiet: bool = o.Quiet,
    temp_dir: Optional[str] = o.TempDir,
):
    """Sample the rows a SQL query returns (DuckDB), streaming its result twice.

    Example: prism-stream sql "SELECT * FROM read_parquet('tiles/*.parquet')" out.parquet --ratio 0.01
    """
    if not plan and output is None:
        raise typer.BadParameter("give the output file (or --plan)", param_hint="OUTPUT")
    from prism_stream.query import sample_query  # here, not at the top: `prism-stream` starts without DuckDB

    summary = sample_query(
        query, None if plan else output, ratio=ratio, count=count, k=k, mode=mode, color_space=color_space,
        quant_bits=quant_bits, quant_step=quant_step, color_depth=color_depth, seed=seed, chunk_size=chunk_size,
        rgb_columns=o.split_columns(rgb_columns), overwrite=overwrite, progress=not quiet and not as_json,
        temp_dir=temp_dir, materialize=materialize, database=database, memory_limit=memory_limit, threads=threads,
    )
    data = summary.as_dict()
    if summary_file:
        summary_file.write_text(json.dumps(data, indent=2) + "\n")
    if as_json:
        typer.echo(json.dumps(data, indent=2))
    elif not quiet:
        print_summary(data)
