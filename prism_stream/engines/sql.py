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
import tempfile
import time
from typing import Iterator

import duckdb
import pyarrow as pa

from ..errors import CorruptInput, InputNotFound, UnsupportedFormat, UsageError
from ..formats.base import ColorChunk, Source
from ..formats.guard import first_line
from ..formats.parquet import DEFAULT_RGB, ArrowPointChunk, ParquetSource, color_array, find_color_columns
from ..run.outputs import Layout
from ..run.request import Request
from ..run.summary import Summary
from .local import execute

MATERIALIZE = ("rerun", "spool")
LABEL = "query"


def duckdb_error(exc: duckdb.Error, label: str = LABEL):
    """A DuckDB failure as a one-line prism-stream error: the query's fault (exit 2) or the data's (6)."""
    first = first_line(exc)
    if isinstance(exc, (duckdb.ParserException, duckdb.BinderException, duckdb.CatalogException)):
        return UsageError(f"the query is not valid: {first}", label)
    return CorruptInput(f"the query failed: {first}", label)


class QuerySource(Source):
    """The result of a query, re-executed for each pass (record ranges skip and stop in the stream)."""

    format = "sql"
    changed = ("the query returned different rows on its second run (make its order deterministic with "
               "ORDER BY, or use --materialize spool)")
    reread_may_differ = True

    def __init__(self, con: duckdb.DuckDBPyConnection, query: str, ordinal: int = 0, rgb_columns=DEFAULT_RGB,
                 label: str = LABEL):
        self.con = con
        self.query = query.strip().rstrip(";")
        self.ordinal = ordinal
        self.path = label
        try:
            self.schema = arrow_reader(con, f"SELECT * FROM ({self.query}) LIMIT 0", 1).schema
        except duckdb.Error as exc:
            raise duckdb_error(exc, label) from None
        self.rgb_names = find_color_columns(self.schema, rgb_columns or DEFAULT_RGB, label)
        self.count = None  # known once pass one has streamed the result

    def _batches(self, columns: str, chunk_size: int, start: int, stop: int | None) -> Iterator[tuple[int, pa.RecordBatch]]:
        try:
            reader = arrow_reader(self.con, f"SELECT {columns} FROM ({self.query})", chunk_size)
            pos = 0
            for batch in reader:
                end = pos + batch.num_rows if stop is None else min(pos + batch.num_rows, stop)
                a, b = max(pos, start), end
                if b > a:
                    yield a, batch.slice(a - pos, b - a)
                pos += batch.num_rows
                if stop is not None and pos >= stop:
                    break
        except duckdb.Error as exc:
            raise duckdb_error(exc, self.path) from None

    def color_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[ColorChunk]:
        cols = ", ".join(_quote(n) for n in self.rgb_names)
        for pos, batch in self._batches(cols, chunk_size, start, stop):
            yield ColorChunk(pos, tuple(color_array(batch.column(i), n, self.path) for i, n in enumerate(self.rgb_names)))

    def point_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[ArrowPointChunk]:
        for pos, batch in self._batches("*", chunk_size, start, stop):
            yield ArrowPointChunk(pos, batch, self.rgb_names, self.path)

    def arrow_schema(self) -> pa.Schema:
        return self.schema

    def describe(self) -> dict:
        return {"format": "sql", "query": self.query, "color_columns": list(self.rgb_names)}


def arrow_reader(con: duckdb.DuckDBPyConnection, sql: str, batch_size: int) -> pa.RecordBatchReader:
    """The result of ``sql`` as a stream of Arrow record batches of at most ``batch_size`` rows."""
    rel = con.sql(sql)
    if hasattr(rel, "to_arrow_reader"):
        return rel.to_arrow_reader(batch_size)
    return rel.fetch_arrow_reader(batch_size)  # duckdb 1.x


def _quote(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def spool(con: duckdb.DuckDBPyConnection, query: str, folder: str, label: str = LABEL) -> str:
    """Write the query's result once to a Parquet file in ``folder``; return its path."""
    path = os.path.join(folder, "spool.parquet")
    try:
        con.execute(f"COPY ({query.strip().rstrip(';')}) TO '{path}' (FORMAT parquet, COMPRESSION zstd, "
                    "ROW_GROUP_SIZE 1048576)")
    except duckdb.Error as exc:
        raise duckdb_error(exc, label) from None
    return path


def connect(database: str | None = None, memory_limit: str | None = None, threads: int | None = None,
            temp_directory: str | None = None) -> duckdb.DuckDBPyConnection:
    """A DuckDB connection for reading queries: in memory, or a database file opened read-only."""
    if database is not None and not os.path.exists(database):
        raise InputNotFound("no such database file", database)
    try:
        con = duckdb.connect(database or ":memory:", read_only=database is not None)
        if memory_limit:
            con.execute(f"SET memory_limit = '{memory_limit}'")
        if threads:
            con.execute(f"SET threads = {int(threads)}")
        if temp_directory:
            con.execute(f"SET temp_directory = '{temp_directory}'")
    except duckdb.Error as exc:
        raise duckdb_error(exc, database or "duckdb") from None
    return con


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
    if materialize not in MATERIALIZE:
        raise UsageError(f"--materialize must be one of {', '.join(MATERIALIZE)}, not {materialize!r}")
    if output is not None and not os.fspath(output).lower().endswith((".parquet", ".pq")):
        raise UnsupportedFormat("a query's sample is written as Parquet (.parquet)", output)
    layout = Layout.single(output, request.overwrite)
    t0 = time.perf_counter()
    own = connection is None
    con = connect(database, memory_limit, request.threads) if own else connection
    try:
        with tempfile.TemporaryDirectory(prefix="prism-stream-", dir=request.temp_dir) as tmp:
            if own:  # DuckDB spills into the run's temporary folder, removed with it
                con.execute(f"SET temp_directory = '{os.path.join(tmp, 'duckdb')}'")
            if materialize == "spool":
                src = ParquetSource(spool(con, query, tmp), 0, rgb_columns=request.rgb_columns or DEFAULT_RGB)
                src.path = LABEL
            else:
                src = QuerySource(con, query, 0, rgb_columns=request.rgb_columns)
            try:
                return execute([src], layout, request, tmp, [query], t0=t0,
                               no_points="the query returned no rows; the output is empty", query=query)
            finally:
                src.close()
    finally:
        if own:
            con.close()
