"""The SQL engine: a DuckDB query's result as the input, run through the local engine's passes.

The result of a DuckDB query is one source (ordinal 0; a row's record index
is its position in the result), read as Arrow record batches, never
materialized in Python. Two ways to read it twice:

- ``rerun`` (the default): pass one runs ``SELECT red, green, blue FROM
  (query)``, so DuckDB reads only the color columns; pass two runs the query
  again for every column. The query must return the same rows in the same
  order both times (DuckDB keeps the order of scans, filters and
  projections; add ORDER BY after a join or an aggregate). Pass two checks
  every row's bin key against pass one and fails if they differ.
- ``spool``: the result is written once to a Parquet file in the run's
  temporary folder and both passes read that file. Any query is fine; the
  cost is writing the whole result once (see docs/DUCKDB.md for timings).
"""

from __future__ import annotations

import os
import time

import duckdb

from ..errors import UnsupportedFormat, UsageError
from ..formats.parquet import DEFAULT_RGB, ParquetSource
from ..formats.query import FILE_COLUMN, LABEL, MATERIALIZE, QuerySource, check_globbed_files, connect, spool
from ..run import staging
from ..run.outputs import Layout
from ..run.request import Request
from ..run.summary import Summary
from . import spatial
from .local import execute


def output_layout(output: str | None, overwrite: bool) -> Layout:
    """The layout of a query's sample (one Parquet file, or none for a plan), refused where a run cannot
    write it."""
    if output is not None and not os.fspath(output).lower().endswith((".parquet", ".pq")):
        raise UnsupportedFormat("a query's sample is written as Parquet (.parquet)", output)
    return Layout.single(output, overwrite)


def sample_query(query: str, output: str | None = None, request: Request | None = None, *, materialize: str = "rerun",
                 database: str | None = None, connection: duckdb.DuckDBPyConnection | None = None,
                 memory_limit: str | None = None, **options) -> Summary:
    """Sample the result of a DuckDB ``query`` into ``output`` (Parquet) with PRISM; return the summary.

    Parameters
    ----------
    query : str
        Any DuckDB SELECT (``read_parquet``, ``read_csv``, tables of ``database``...).
    output : str or None
        A ``.parquet`` file; None runs pass one and the solve only.
    request, **options
        As for :func:`prism_stream.sample`; ``threads`` are DuckDB's threads.
    materialize : {"rerun", "spool"}
        How the result is read twice (see the module docstring).
    database : str or None
        A DuckDB database file to open read-only (for queries over its tables).
    connection : duckdb.DuckDBPyConnection or None
        Use this connection instead of opening one (``database`` is then ignored).
    memory_limit : str or None
        DuckDB's memory limit for the query (its spill goes in ``temp_dir``).
    """
    request = Request.of(request, **options)
    for name in ("flag", "output_format"):
        if getattr(request, name) is not None:
            raise UsageError(f"--{name.replace('output_', '')} is not available for a query's sample")
    if request.per_file:
        raise UsageError("--per-file is not available for a query's sample")
    if request.options.denoise is not None:
        raise UsageError("--denoise is not available for a query's sample: the outlier removal reads the cloud "
                         "three times, a query's result once (write the result to a file first)")
    if materialize not in MATERIALIZE:
        raise UsageError(f"--materialize must be one of {', '.join(MATERIALIZE)}, not {materialize!r}")
    layout = output_layout(output, request.overwrite)
    t0 = time.perf_counter()
    own = connection is None
    with staging.work_dir(request.temp_dir) as tmp:
        # DuckDB spills into the run's work folder, removed with it
        con = connect(database, memory_limit, request.workers, os.path.join(tmp, "duckdb")) if own else connection
        try:
            check_globbed_files(con, query)
            if materialize == "spool":
                spooled = spool(con, query, tmp)
                src = ParquetSource(spooled, 0, rgb_columns=request.rgb_columns or DEFAULT_RGB)
                src.path = LABEL
                if request.color_depth == "auto" and FILE_COLUMN in src.arrow_schema().names:
                    # the result names its files: read the spool as a query, to decide the depth per file
                    src.close()
                    con.read_parquet(spooled).create_view("prism_spool", replace=True)
                    src = QuerySource(con, "SELECT * FROM prism_spool", 0, rgb_columns=request.rgb_columns)
            else:
                src = QuerySource(con, query, 0, rgb_columns=request.rgb_columns, color_depth=request.color_depth)
            try:
                spatial.check_coordinates(request.options, [src])  # the result's columns, before pass one
                return execute([src], layout, request, tmp, [query], t0=t0,
                               no_points="the query returned no rows; the output is empty", query=query)
            finally:
                src.close()
        finally:
            if own:
                con.close()
