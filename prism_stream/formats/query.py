"""A DuckDB query's result as a source (:class:`QuerySource`), and the DuckDB plumbing the SQL engine and
the batch jobs share: connecting, one-line errors, the checks of a query's globbed files, the spool.

The result is one source (ordinal 0; a row's record index is its position in
the result), read as Arrow record batches, never materialized in Python. No
value of ours is ever pasted into SQL text: paths and settings are bound as
parameters or passed as DuckDB ``config``; the one thing that must be written
into a statement, a column name, goes through :func:`identifier`.
"""

from __future__ import annotations

import json
import os
import re
from typing import Iterator

import duckdb
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from ..errors import CorruptInput, InputNotFound, StorageError, UsageError
from .base import ColorChunk, Source
from .guard import first_line
from .parquet import DEFAULT_RGB, ArrowPointChunk, color_array, find_color_columns
from .arrow import to_numpy

MATERIALIZE = ("rerun", "spool")
LABEL = "query"
FILE_COLUMN = "filename"  # read_parquet(..., filename = true): the file a row came from


def identifier(name: str) -> str:
    """``name`` as a quoted DuckDB identifier: the one escaping function of the package."""
    return '"' + str(name).replace('"', '""') + '"'


# DuckDB's words for a query's input pattern that matches no file: the README's exit 3, as for a file input
# (not its words for a file it cannot open, which may be its own spill or the spool: those stay exit 6)
_NOT_FOUND = ("No files found that match",)


# DuckDB's words for an extension it could not download (offline, or its server unreachable): exit 10, the
# store's, with the whole reason on one line (its message's first line ends in the middle of a quote)
_EXTENSION = re.compile(r'Failed to download extension "(\w+)"')


# DuckDB's words for files of one glob whose columns differ (it reads a glob by the first file's columns)
_MISMATCH = ("schema mismatch in glob",)
_UNION_HINT = "read_parquet(..., union_by_name = true) reads files whose columns differ"


def duckdb_error(exc: Exception, label: str = LABEL):
    """A DuckDB failure as a one-line prism-stream error: the query's fault (exit 2, files of one glob whose
    columns differ included), a file it names that is missing or unreadable (3), or the data's fault (6).
    ``exc`` may also be DuckDB's failure as the Arrow stream of its result raises it (an OSError or an
    ArrowException carrying DuckDB's message): the words decide then, as they do for the glob's files."""
    first = first_line(exc)
    missing = _EXTENSION.search(str(exc))
    if missing:  # DuckDB's generic Error for an extension it could not download (a remote path needs httpfs)
        why = re.findall(r"\((ERROR [^)]*)\)", str(exc))
        return StorageError(f"DuckDB could not download its {missing.group(1)} extension, which the query's "
                            f"remote input needs{f' ({why[-1]})' if why else ''}: install it once where the "
                            f"network is reachable (INSTALL {missing.group(1)}) or query a local copy", label)
    if isinstance(exc, (duckdb.ParserException, duckdb.BinderException, duckdb.CatalogException)):
        return UsageError(f"the query is not valid: {first}", label)
    if any(words in str(exc) for words in _MISMATCH):
        return UsageError(f"the query's files differ: {first} ({_UNION_HINT})", label)
    if isinstance(exc, (duckdb.IOException, OSError, pa.ArrowException)) \
            and any(words in str(exc) for words in _NOT_FOUND):
        return InputNotFound(f"the query's input: {first}", label)
    return CorruptInput(f"the query failed: {first}", label)


_PARQUET_SCANS = ("read_parquet", "parquet_scan")


def _parquet_scans(node, select=None) -> Iterator[tuple[list[str], set | None]]:
    """(file patterns, columns read by name) of each Parquet scan in a parsed query (``json_serialize_sql``)
    that reads its files by the first one's columns: ``read_parquet``/``parquet_scan`` of constant strings
    without ``union_by_name``, and a quoted ``'tiles/*.parquet'`` in FROM. The columns are those its
    SELECT returns under their own name (None: ``*``, every column); ``select``: the enclosing SELECT list."""
    if isinstance(node, list):
        for item in node:
            yield from _parquet_scans(item, select)
        return
    if not isinstance(node, dict):
        return
    if node.get("type") == "SELECT_NODE":
        select = node.get("select_list") or []
    if node.get("type") == "TABLE_FUNCTION" and isinstance(node.get("function"), dict):
        fn = node["function"]
        args = [a.get("expression") or {} for a in fn.get("arguments") or []]
        named = dict(_named_argument(a) for a in args[1:])  # name = value: a comparison in the parse tree
        union = str(named.get("union_by_name", "false")).lower()
        if fn.get("function_name", "").lower() in _PARQUET_SCANS and args and union in ("false", "0"):
            patterns = _constant_strings(args[0])
            if patterns:
                yield patterns, _read_by_name(select, node.get("alias", ""))
    elif node.get("type") == "BASE_TABLE" and not node.get("schema_name") and \
            str(node.get("table_name", "")).lower().endswith((".parquet", ".pq")):
        yield [node["table_name"]], _read_by_name(select, node.get("alias", ""))
    for value in node.values():
        if isinstance(value, (dict, list)):
            yield from _parquet_scans(value, select)


def _read_by_name(select, alias: str) -> set | None:
    """The columns a SELECT list returns from the scan named ``alias`` under their own names: None for ``*``
    (or ``alias.*``), else the lower-case names of its plain column references (``x``, ``alias.x``); a
    computed or renamed column is not one (``1 AS extra`` does not read ``extra``)."""
    names = set()
    for item in select or []:
        if item.get("class") == "STAR" and item.get("relation_name", "") in ("", alias):
            return None
        if item.get("class") == "COLUMN_REF":
            path = item.get("column_names") or []
            if not path or item.get("alias", "") not in ("", path[-1]):
                continue
            if len(path) == 1 or (len(path) == 2 and alias and path[0].lower() == alias.lower()):
                names.add(path[-1].lower())
    return names


def _named_argument(expr: dict) -> tuple[str, object]:
    """(name, constant text or None) of a table function's ``name = value`` argument."""
    left, right = expr.get("left") or {}, expr.get("right") or {}
    if expr.get("type") != "COMPARE_EQUAL" or left.get("class") != "COLUMN_REF":
        return "", None
    value = (right.get("literal") or {}).get("text") if right.get("class") == "CONSTANT" else "computed"
    return ".".join(left.get("column_names") or []).lower(), value


def _constant_strings(expr) -> list[str] | None:
    """A constant string, or a list of them, as a list; None for anything computed."""
    if not isinstance(expr, dict):
        return None
    if expr.get("class") == "CONSTANT":
        lit = expr.get("literal") or {}
        return [lit["text"]] if lit.get("kind") == "STRING" else None
    if expr.get("class") == "FUNCTION" and expr.get("function_name") == "list_value":
        out = [_constant_strings(a.get("expression")) for a in expr.get("arguments") or []]
        return None if not out or None in out else [p for part in out for p in part]
    return None


def check_globbed_files(con: duckdb.DuckDBPyConnection, query: str, label: str = LABEL) -> None:
    """Refuse, before pass one, a query whose Parquet glob holds a file without a column of the first file.

    DuckDB reads a glob by its first file's columns and fails on a file that
    lacks one, but only when it reads that column: pass one reads the colors
    alone, so the failure came in pass two, after the whole of pass one. The
    files' footers (one small read each) settle it up front, for the columns
    the query returns from the scan under their own names (``*``, ``x``,
    ``t.x``; not ``1 AS x``). Queries this cannot read (computed paths, views, a
    column used under another name) are left to DuckDB's own error, which
    says the same (exit 2).
    """
    try:
        tree = json.loads(con.execute("SELECT json_serialize_sql(?)", [query]).fetchall()[0][0])
    except (duckdb.Error, ValueError, IndexError, TypeError):
        return
    if tree.get("error"):
        return
    try:  # the columns pass two reads: a file may lack a column the query never returns
        returned = {n.lower() for n in arrow_reader(con, f"SELECT * FROM ({query.strip().rstrip(';')}) LIMIT 0",
                                                    1).schema.names}
    except duckdb.Error:
        return  # an invalid query: its own run says why
    for patterns, read in _parquet_scans(tree.get("statements")):
        try:
            rows = con.execute("SELECT file_name, name, num_children FROM parquet_schema(?)", [patterns]).fetchall()
        except duckdb.Error:
            continue  # no file, an unreadable one: the query's own run says which
        files: dict[str, list[str]] = {}
        for file, columns in _top_level_columns(rows):
            files.setdefault(file, columns)
        if len(files) < 2:
            continue
        first, *others = files
        want = files[first]
        for other in others:
            have = {c.lower() for c in files[other]}
            missing = [c for c in want if c.lower() not in have and c.lower() in returned
                       and (read is None or c.lower() in read)]
            if missing:
                raise UsageError(f"the query's files differ: {other} has no column {missing[0]!r}, which "
                                 f"{first} (the first file of its glob) has, so DuckDB would fail on it after "
                                 f"pass one ({_UNION_HINT})", label)


def _top_level_columns(rows) -> Iterator[tuple[str, list[str]]]:
    """(file, its top-level column names) from ``parquet_schema`` rows (each file's schema in pre-order: the
    root, then every element, a group followed by its ``num_children`` children)."""
    i = 0
    while i < len(rows):
        file, _, top = rows[i]
        i += 1
        top, names, pending = top or 0, [], []  # pending: the children still expected at each open group's level
        while i < len(rows) and rows[i][0] == file and (top or pending):
            _, name, n = rows[i]
            i += 1
            if pending:
                pending[-1] -= 1
            else:
                names.append(name)
                top -= 1
            if n:
                pending.append(n)
            while pending and pending[-1] == 0:
                pending.pop()
        yield file, names


class QuerySource(Source):
    """The result of a query, re-executed for each pass (record ranges skip and stop in the stream)."""

    format = "sql"
    changed = ("the query returned different rows on a later run (make its order deterministic with "
               "ORDER BY columns that tell every row apart, or use --materialize spool)")
    reread_may_differ = True

    def __init__(self, con: duckdb.DuckDBPyConnection, query: str, ordinal: int = 0, rgb_columns=DEFAULT_RGB,
                 label: str = LABEL, color_depth: str = "auto"):
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
        self.sixteen = self._sixteen_bit_files(color_depth)

    def _sixteen_bit_files(self, color_depth: str) -> pa.Array | None:
        """The files of a result that names them (``filename``) whose colors are 16-bit, when files differ.

        ``auto`` decides the color depth per file, as the file command does:
        a result that mixes 8-bit and 16-bit files has the 16-bit files'
        colors read as ``v >> 8``. None when the result does not name its
        files, every file has the same depth, or the depth is forced.
        """
        if color_depth != "auto" or FILE_COLUMN not in self.schema.names:
            return None
        if not all(pa.types.is_integer(self.schema.field(n).type) for n in self.rgb_names):
            return None
        r, g, b = (identifier(n) for n in self.rgb_names)
        try:
            rows = self.con.execute(f"SELECT {identifier(FILE_COLUMN)}, max(greatest({r}, {g}, {b})) > 255 "
                                    f"FROM ({self.query}) GROUP BY ALL").fetchall()
        except duckdb.Error as exc:
            raise duckdb_error(exc, self.path) from None
        self.depths = {str(f): 16 if wide else 8 for f, wide in rows}
        if len(set(self.depths.values())) < 2:
            return None
        return pa.array([f for f, d in self.depths.items() if d == 16], type=pa.string())

    def _decided(self, rgb: tuple, files: pa.Array) -> tuple:
        """The colors of a batch with the 16-bit files' values shifted to 8 bits."""
        if self.sixteen is None:
            return rgb
        wide = to_numpy(pc.is_in(files.cast(pa.string()), value_set=self.sixteen))
        if not wide.any():
            return rgb
        out = []
        for c in rgb:
            c = np.array(c, dtype=np.int64)
            c[wide] >>= 8
            out.append(c)
        return tuple(out)

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
        except (duckdb.Error, pa.ArrowException, OSError) as exc:
            # a failure inside the stream (a glob's later file read in a worker thread) reaches the reader
            # as Arrow's error carrying DuckDB's message, not as duckdb.Error (1 run in 30 here)
            raise duckdb_error(exc, self.path) from None

    def color_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[ColorChunk]:
        names = [*self.rgb_names, *([FILE_COLUMN] if self.sixteen is not None else [])]
        cols = ", ".join(identifier(n) for n in names)
        for pos, batch in self._batches(cols, chunk_size, start, stop):
            rgb = tuple(color_array(batch.column(i), n, self.path) for i, n in enumerate(self.rgb_names))
            yield ColorChunk(pos, self._decided(rgb, batch.column(3)) if self.sixteen is not None else rgb)

    def point_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[ArrowPointChunk]:
        for pos, batch in self._batches("*", chunk_size, start, stop):
            chunk = ArrowPointChunk(pos, batch, self.rgb_names, self.path)
            if self.sixteen is not None:
                chunk.rgb = self._decided(chunk.rgb, batch.column(batch.schema.get_field_index(FILE_COLUMN)))
            yield chunk

    def arrow_schema(self) -> pa.Schema:
        return self.schema

    def describe(self) -> dict:
        d = {"format": "sql", "query": self.query, "color_columns": list(self.rgb_names)}
        if self.sixteen is not None:
            d["color_depth_per_file"] = self.depths
        return d


def arrow_reader(con: duckdb.DuckDBPyConnection, sql: str, batch_size: int) -> pa.RecordBatchReader:
    """The result of ``sql`` as a stream of Arrow record batches of at most ``batch_size`` rows."""
    rel = con.sql(sql)
    if hasattr(rel, "to_arrow_reader"):
        return rel.to_arrow_reader(batch_size)
    return rel.fetch_arrow_reader(batch_size)  # duckdb 1.x


def spool(con: duckdb.DuckDBPyConnection, query: str, folder: str, label: str = LABEL) -> str:
    """Write the query's result once to a Parquet file in ``folder``; return its path (never pasted into SQL)."""
    path = os.path.join(folder, "spool.parquet")
    try:
        con.sql(query.strip().rstrip(";")).write_parquet(path, compression="zstd", row_group_size=1 << 20)
    except duckdb.Error as exc:
        raise duckdb_error(exc, label) from None
    return path


def connect(database: str | None = None, memory_limit: str | None = None, threads: int | None = None,
            temp_directory: str | None = None) -> duckdb.DuckDBPyConnection:
    """A DuckDB connection for reading queries: in memory, or a database file opened read-only.

    The settings go in DuckDB's ``config`` (values, never SQL text), so no
    option value can add a statement.
    """
    if database is not None and not os.path.exists(database):
        raise InputNotFound("no such database file", database)
    if database is not None and os.path.isdir(database):
        raise UsageError("--database names a folder; give a DuckDB database file", database)
    if database is not None and not os.access(database, os.R_OK):
        raise InputNotFound("cannot be read (permission denied)", database)
    config = {}
    if memory_limit:
        config["memory_limit"] = str(memory_limit)
    if threads:
        config["threads"] = int(threads)
    if temp_directory:
        config["temp_directory"] = str(temp_directory)
    try:
        return duckdb.connect(database or ":memory:", read_only=database is not None, config=config)
    except duckdb.Error as exc:
        first = first_line(exc)
        if memory_limit and "memory" in first.lower():
            raise UsageError(f"--memory-limit {memory_limit!r} is not a size DuckDB takes: {first}") from None
        raise duckdb_error(exc, database or "duckdb") from None
