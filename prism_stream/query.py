"""A SQL query as the input: its result streamed through the engine's two passes.

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
import numpy as np
import pyarrow as pa

from .bins import decided_keys
from .cutoff import Rules, find_cutoffs
from .engine import KeyCache, Summary, provenance, scan_source, summarize, warn_about
from .errors import CorruptInput, Interrupted, UnsupportedFormat, UsageError
from .formats.base import ColorChunk, Source
from .formats.guard import first_line
from .formats.parquet import DEFAULT_RGB, ArrowPointChunk, ParquetSink, ParquetSource, color_array, find_color_columns
from .layout import check_output_file
from .plan import Options, Plan, solve
from .progress import Progress
from .scan import HistogramAccumulator
from .select import Selector

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
        from .errors import InputNotFound

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


def sample_query(
    query: str,
    output: str | None = None,
    *,
    ratio: float | None = None,
    count: int | None = None,
    k: int | None = None,
    mode: str = "exact",
    color_space: str = "rgb",
    quant_bits: int = 0,
    quant_step: float | None = None,
    color_depth: str = "auto",
    seed: int = 0,
    chunk_size: int = 1 << 20,
    rgb_columns=None,
    overwrite: bool = False,
    progress: bool = False,
    temp_dir: str | None = None,
    materialize: str = "rerun",
    database: str | None = None,
    connection: duckdb.DuckDBPyConnection | None = None,
    memory_limit: str | None = None,
    threads: int | None = None,
) -> Summary:
    """Sample the result of a DuckDB ``query`` into ``output`` (Parquet) with PRISM; return the summary.

    Parameters
    ----------
    query : str
        Any DuckDB SELECT (``read_parquet``, ``read_csv``, tables of ``database``...).
    output : str or None
        A ``.parquet`` file; None runs pass one and the solve only.
    materialize : {"rerun", "spool"}
        How the result is read twice (see the module docstring).
    database : str or None
        A DuckDB database file to open read-only (for queries over its tables).
    connection : duckdb.DuckDBPyConnection or None
        Use this connection instead of opening one (``database`` is then ignored).
    memory_limit, threads
        DuckDB settings for the query (the key cache and spool go in ``temp_dir``).

    The other options are those of :func:`prism_stream.sample`.
    """
    options = Options(ratio=ratio, count=count, k=k, mode=mode, color_space=color_space, bits=int(quant_bits),
                      quant_step=quant_step,
                      color_depth=color_depth, seed=int(seed))
    if materialize not in MATERIALIZE:
        raise UsageError(f"--materialize must be one of {', '.join(MATERIALIZE)}, not {materialize!r}")
    if chunk_size < 1:
        raise UsageError(f"--chunk-size must be positive, not {chunk_size}")
    if output is not None:
        _check_output(output, overwrite)
    t0 = time.perf_counter()
    seconds: dict = {}
    own = connection is None
    con = connect(database, memory_limit, threads) if own else connection
    sink = None
    try:
        with tempfile.TemporaryDirectory(prefix="prism-stream-", dir=temp_dir) as tmp:
            if own:  # DuckDB spills into the run's temporary folder, removed with it
                con.execute(f"SET temp_directory = '{os.path.join(tmp, 'duckdb')}'")
            if materialize == "spool":
                src = ParquetSource(spool(con, query, tmp), 0, rgb_columns=rgb_columns or DEFAULT_RGB)
                src.path = LABEL
                seconds["spool"] = time.perf_counter() - t0
            else:
                src = QuerySource(con, query, 0, rgb_columns=rgb_columns)
            cache = KeyCache(tmp)
            try:
                acc = HistogramAccumulator(options.spec)
                with Progress("pass 1/2 histogram", None, progress) as bar:
                    scanned = scan_source(src, options.spec, options.color_depth, chunk_size, acc, cache, bar)
                src.count = scanned.points
                seconds["scan"] = time.perf_counter() - t0
                t1 = time.perf_counter()
                plan = solve(acc.histogram(), options, (scanned.as_dict(),))
                del acc
                seconds["solve"] = time.perf_counter() - t1
                caught = warn_about(plan, "the query returned no rows; the output is empty")
                if output is None:
                    return summarize(plan, [query], None, seconds, caught)
                t2 = time.perf_counter()
                rules = Rules(plan)
                cutoffs = find_cutoffs(rules, [src], chunk_size, lambda _, a, n: cache.read(a, n))
                seconds["cutoffs"] = time.perf_counter() - t2
                t3 = time.perf_counter()
                selector = Selector(plan, cutoffs, rules)
                sink = ParquetSink(output, [src], provenance(plan, []) | {"inputs": [], "query": query})
                with Progress("pass 2/2 select", src.count, progress) as bar:
                    _select(src, plan, chunk_size, selector, cache, sink, bar)
                if sink.written != plan.kept:
                    raise AssertionError(f"wrote {sink.written} points, the plan keeps {plan.kept}")
                sink.commit()
                sink = None
                seconds["select"] = time.perf_counter() - t3
            finally:
                cache.close()
                if isinstance(src, ParquetSource):
                    src.close()
    except KeyboardInterrupt:
        if sink is not None:
            sink.abort()
        raise Interrupted("interrupted; no output was written", output) from None
    except BaseException:
        if sink is not None:
            sink.abort()
        raise
    finally:
        if own:
            con.close()
    seconds["total"] = time.perf_counter() - t0
    return summarize(plan, [query], output, seconds, caught)


def _check_output(output: str, overwrite: bool) -> None:
    if not output.lower().endswith((".parquet", ".pq")):
        raise UnsupportedFormat("a query's sample is written as Parquet (.parquet)", output)
    check_output_file(output, [], overwrite)


def _select(src, plan: Plan, chunk_size: int, selector: Selector, cache, sink, bar) -> None:
    decision = plan.sources[0]["color_depth"]
    seen = 0
    for chunk in src.point_chunks(chunk_size):
        n = len(chunk)
        keys = cache.read(chunk.start, n)
        again = decided_keys(plan.spec, chunk.rgb, decision, src.path)
        if len(keys) != n or not np.array_equal(keys, again):
            raise CorruptInput("the query returned different rows on its second run (make its order "
                               "deterministic with ORDER BY, or use --materialize spool)", src.path)
        sink.write(chunk, selector.mask(keys, src.ordinal, chunk.start))
        seen += n
        bar.update(n)
    if seen != src.count:
        raise CorruptInput(f"the query returned {seen} rows on its second run, {src.count} on its first "
                           "(use --materialize spool)", src.path)


