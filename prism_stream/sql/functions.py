"""PRISM inside DuckDB: scalar functions and the ``prism_sample`` table macros.

``register(con)`` adds to a connection:

- ``prism_bin_key(r, g, b, shift, color_space, bits)``: the SPEC 2 bin key;
  ``prism_bin_key_q(..., bits, step)`` the same with a float step q (or NULL)
  (UINTEGER). ``shift`` is the source's color-depth decision: 0 (8-bit
  values), 8 (16-bit values, ``v >> 8``) or -1 (float colors in [0, 1]).
- ``prism_priority(id, seed)`` and ``prism_bin_priority(key, seed)``: the
  SPEC 3 hashes (UBIGINT). DuckDB's own ``hash()`` changes between versions
  and is never used.
- ``prism_quotas(keys, counts, ratio, count, k, mode, seed)``: the SPEC 4
  quota of every bin, solved by :func:`prism_stream.core.quotas.solve` itself.
- ``prism_sample(table, ratio := ..., ...)``: the sample of a table or view,
  and ``prism_sample_parquet(files, ...)`` of Parquet files (a path, glob or
  list), with the rows the streaming engine keeps for the same input,
  options and seed.
- ``prism_rank(table, ...)`` and ``prism_rank_parquet(files, ...)``: every
  row with its PRISM rank (``prism_rank``, exact mode), so that
  ``WHERE prism_rank < floor(r * N + 0.5)`` is the sample at ratio r.

All functions are vectorized over Arrow with the numba kernels inside.

Row ids (SPEC 3): with ``id := NULL`` (the default) the table must carry
``read_parquet``'s ``filename`` and ``file_row_number`` columns, and a row's
id is ``(file ordinal in sorted path order << 40) | file_row_number``; the
color depth is then decided per file, as the file command does. With
``id := 'col'`` the id is that column (a non-negative integer) and the
whole table is one source for the color-depth decision.

The macro's own columns (``__prism_*``) never share a scope with the
user's: each row travels whole as one struct column (``__prism_rec``) and is
unnested only at the end, so a user column of any name (``__prism_r``
included) is data, never one of the macro's values.
"""

from __future__ import annotations

import duckdb
import numpy as np
import pyarrow as pa

from ..core import kernels
from ..core.bins import BinSpec, float_to_8bit
from ..core.histogram import Histogram
from ..core.quotas import Options, solve
from ..errors import CorruptInput, NoColorError, UsageError
from ..formats.arrow import to_numpy

FLOAT_SHIFT = -1
MAX_PRIORITY = (1 << 64) - 1
# a capped bin's prefilter keeps priorities under (q + SLACK_SIGMAS*sqrt(q) + SLACK_POINTS)/n of
# the 64-bit range; a bin that still comes up short keeps every point before the window (exact either way)
SLACK_SIGMAS = 5
SLACK_POINTS = 16


def _first(arr) -> object:
    return arr[0].as_py() if len(arr) else None


def _ints(col: pa.Array, what: str) -> np.ndarray:
    if col.null_count:
        raise NoColorError(f"{col.null_count} points have no {what} (null): points with no color cannot be binned")
    return to_numpy(col)


def bin_key_udf(r: pa.Array, g: pa.Array, b: pa.Array, shift: pa.Array, color_space: pa.Array,
                bits: pa.Array) -> pa.Array:
    """:func:`bin_key_step_udf` without a step (the registered ``prism_bin_key`` keeps its signature)."""
    return bin_key_step_udf(r, g, b, shift, color_space, bits, None)


def bin_key_step_udf(r: pa.Array, g: pa.Array, b: pa.Array, shift: pa.Array, color_space: pa.Array,
                     bits: pa.Array, step: pa.Array | None) -> pa.Array:
    """SPEC 2 bin keys of a vector of points whose sources' color depths are decided."""
    n = len(r)
    if n == 0:
        return pa.array([], type=pa.uint32())
    q = _first(step) if step is not None else None
    spec = BinSpec(_first(color_space) or "rgb", int(_first(bits) or 0), None if q is None else float(q))
    channels = [_ints(c, name) for c, name in ((r, "red"), (g, "green"), (b, "blue"))]
    shifts = to_numpy(shift).astype(np.int64)
    out = np.empty(n, dtype=np.uint32)
    distinct = np.unique(shifts)
    for s in distinct:
        rows = np.flatnonzero(shifts == s) if len(distinct) > 1 else slice(None)
        c = [ch[rows] for ch in channels]
        if s == FLOAT_SHIFT:
            c = [float_to_8bit(x, "prism_bin_key") for x in c]
            out[rows] = spec.keys(*c, 0)
            continue
        c = [np.asarray(x, dtype=np.float64) for x in c]
        lo, hi = min(float(x.min()) for x in c), max(float(x.max()) for x in c)
        if lo < 0 or hi > 65535 or any(np.any(x != np.floor(x)) for x in c):
            raise CorruptInput(f"integer color values must be in 0..65535 (saw {lo:g}..{hi:g})")
        if s == 0 and hi > 255:
            raise UsageError(f"color depth 8 but a color value is {hi:g}; use auto or 16")
        c = [x.astype(np.int64) for x in c]
        out[rows] = spec.keys(*c, int(s))
    return pa.array(out, type=pa.uint32())


def priority_udf(ids: pa.Array, seed: pa.Array) -> pa.Array:
    """SPEC 3 point priorities: splitmix64(id ^ splitmix64(seed))."""
    if ids.null_count:
        raise UsageError(f"{ids.null_count} rows have a null id")
    mix = kernels.seed_mix(int(_first(seed) or 0))
    return pa.array(kernels.priorities_of(to_numpy(ids).astype(np.uint64), mix))


def bin_priority_udf(keys: pa.Array, seed: pa.Array) -> pa.Array:
    """SPEC 3 bin priorities: splitmix64(key ^ splitmix64(seed + 1))."""
    mix = kernels.bin_seed_mix(int(_first(seed) or 0))
    return pa.array(kernels.priorities_of(to_numpy(keys).astype(np.uint64), mix))


def quotas_udf(keys, counts, ratio, count, k, mode, seed) -> pa.Array:
    """Every bin's quota, by :func:`prism_stream.core.quotas.solve` on the histogram the lists hold."""
    out = []
    for i in range(len(keys)):
        ks, ns = keys[i], counts[i]
        if not ks.is_valid:
            out.append(None)
            continue
        options = Options(ratio=ratio[i].as_py(), count=count[i].as_py(), k=k[i].as_py(),
                          mode=mode[i].as_py() or "exact", seed=int(seed[i].as_py() or 0))
        hist = Histogram(to_numpy(ks.values).astype(np.uint32),
                         to_numpy(ns.values).astype(np.int64))
        out.append(solve(hist, options).quotas)
    return pa.array(out, type=pa.list_(pa.int64()))


_SAMPLE_PARAMETERS = "ratio := NULL, count := NULL, k := NULL, mode := 'exact', "
_BINNING_PARAMETERS = """color_space := 'rgb', quant_bits := 0, quant_step := NULL, color_depth := 'auto', seed := 0,
    id := NULL, red := 'red', green := 'green', blue := 'blue'"""

_MACRO = """
CREATE OR REPLACE TEMP MACRO {name}({first}, {parameters}) AS TABLE
WITH
src AS NOT MATERIALIZED (
    SELECT * FROM {source}
),
pts AS NOT MATERIALIZED (
    SELECT src AS __prism_rec,
        CASE WHEN id IS NULL THEN COLUMNS(lambda c: c = coalesce(id, 'filename'))::VARCHAR ELSE '' END AS __prism_src,
        COLUMNS(lambda c: c = coalesce(id, 'file_row_number')) AS __prism_row,
        COLUMNS(lambda c: lower(c) = lower(red)) AS __prism_r,
        COLUMNS(lambda c: lower(c) = lower(green)) AS __prism_g,
        COLUMNS(lambda c: lower(c) = lower(blue)) AS __prism_b
    FROM src
),
files AS (
    SELECT __prism_src,
        (row_number() OVER (ORDER BY __prism_src) - 1)::UBIGINT AS __prism_ordinal,
        CASE
            WHEN any_value(typeof(__prism_r)) IN ('FLOAT', 'DOUBLE') OR any_value(typeof(__prism_g)) IN ('FLOAT', 'DOUBLE')
                OR any_value(typeof(__prism_b)) IN ('FLOAT', 'DOUBLE') THEN -1
            WHEN color_depth = '16' THEN 8
            WHEN color_depth = '8' THEN 0
            WHEN color_depth = 'auto' THEN
                CASE WHEN max(greatest(__prism_r, __prism_g, __prism_b)) > 255 THEN 8 ELSE 0 END
            ELSE error('color_depth must be one of auto, 8, 16, not ' || color_depth)
        END::TINYINT AS __prism_shift
    FROM pts GROUP BY __prism_src
),
keyed AS NOT MATERIALIZED (
    SELECT pts.*,
        prism_bin_key_q(__prism_r, __prism_g, __prism_b, __prism_shift, color_space, quant_bits, quant_step::DOUBLE) AS __prism_bin,
        CASE WHEN id IS NULL THEN (__prism_ordinal << 40) | __prism_row::UBIGINT
             ELSE __prism_row::UBIGINT END AS __prism_id
    FROM pts JOIN files USING (__prism_src)
),
{tail}
"""

_SAMPLE = """hist AS (
    SELECT __prism_bin AS bin, count(*)::BIGINT AS n FROM keyed GROUP BY ALL
),
solved AS (
    SELECT list(bin ORDER BY bin) AS bins, list(n ORDER BY bin) AS ns,
        prism_quotas(list(bin ORDER BY bin), list(n ORDER BY bin), ratio::DOUBLE, count::BIGINT, k::BIGINT,
                     mode::VARCHAR, seed::UBIGINT) AS qs
    FROM hist
),
quota AS (
    SELECT unnest(bins) AS bin, unnest(ns) AS n, unnest(qs) AS q FROM solved
),
prefilter AS (
    SELECT bin, q, n,
        CASE WHEN q >= n OR (q + {sigmas} * sqrt(q) + {points}) / n >= 0.999 THEN {max}::UBIGINT
             ELSE (((q + {sigmas} * sqrt(q) + {points}) / n) * 18446744073709551616.0)::UBIGINT END AS t
    FROM quota WHERE q > 0
),
below AS (
    SELECT __prism_bin AS bin, count(*) AS c
    FROM keyed JOIN prefilter ON __prism_bin = prefilter.bin
    WHERE prism_priority(__prism_id, seed::UBIGINT) <= t
    GROUP BY ALL
),
cutoff AS (
    SELECT prefilter.bin, q, CASE WHEN coalesce(c, 0) >= q THEN t ELSE {max}::UBIGINT END AS t
    FROM prefilter LEFT JOIN below USING (bin)
),
candidates AS (
    SELECT keyed.*, prism_priority(__prism_id, seed::UBIGINT) AS __prism_priority, cutoff.q AS __prism_quota
    FROM keyed JOIN cutoff ON __prism_bin = cutoff.bin
    WHERE prism_priority(__prism_id, seed::UBIGINT) <= cutoff.t
),
kept AS (
    SELECT * FROM candidates
    QUALIFY row_number() OVER (PARTITION BY __prism_bin ORDER BY __prism_priority, __prism_id) <= __prism_quota
)
SELECT unnest(__prism_rec) FROM kept ORDER BY kept.__prism_id"""

# PRISM ranks (exact mode; prism_stream.core.ranks): a point's layer j is its place by priority in its bin, and
# its rank its place when every point is sorted by (j, bin priority); rank < T is the exact sample for T.
_RANK = """layered AS (
    SELECT __prism_rec, __prism_id, prism_bin_priority(__prism_bin, seed::UBIGINT) AS __prism_bp,
        row_number() OVER (PARTITION BY __prism_bin
                           ORDER BY prism_priority(__prism_id, seed::UBIGINT), __prism_id) AS __prism_j
    FROM keyed
),
ranked AS (
    SELECT __prism_rec, __prism_id, row_number() OVER (ORDER BY __prism_j, __prism_bp) - 1 AS __prism_rank
    FROM layered
)
SELECT unnest(__prism_rec), __prism_rank AS prism_rank FROM ranked ORDER BY __prism_id"""


def macro_sql(name: str = "prism_sample", parquet: bool = False, rank: bool = False) -> str:
    """The CREATE MACRO statement of ``prism_sample`` / ``prism_rank`` (a table or view) or of their
    ``_parquet`` forms (files)."""
    if rank:
        parameters, tail = _BINNING_PARAMETERS, _RANK
    else:
        parameters = _SAMPLE_PARAMETERS + _BINNING_PARAMETERS
        tail = _SAMPLE.format(sigmas=SLACK_SIGMAS, points=SLACK_POINTS, max=MAX_PRIORITY)
    if parquet:
        first, source = "files", "read_parquet(files, filename = true, file_row_number = true)"
        head, last = tail.rsplit("\nSELECT ", 1)
        tail = f"{head}\nSELECT * EXCLUDE (filename, file_row_number) FROM (SELECT {last})"
    else:
        first, source = "tbl", "query_table(tbl)"
    return _MACRO.format(name=name, first=first, parameters=parameters, source=source, tail=tail)


def register(con: duckdb.DuckDBPyConnection) -> duckdb.DuckDBPyConnection:
    """Add the PRISM functions and table macros to a DuckDB connection (returned for chaining)."""
    t = duckdb.sqltype
    special = {"type": "arrow", "null_handling": "special"}
    con.create_function("prism_bin_key", bin_key_udf,
                        [t("DOUBLE"), t("DOUBLE"), t("DOUBLE"), t("TINYINT"), t("VARCHAR"), t("INTEGER")],
                        t("UINTEGER"), **special)
    con.create_function("prism_bin_key_q", bin_key_step_udf,
                        [t("DOUBLE"), t("DOUBLE"), t("DOUBLE"), t("TINYINT"), t("VARCHAR"), t("INTEGER"), t("DOUBLE")],
                        t("UINTEGER"), **special)
    con.create_function("prism_priority", priority_udf, [t("UBIGINT"), t("UBIGINT")], t("UBIGINT"), **special)
    con.create_function("prism_bin_priority", bin_priority_udf, [t("UINTEGER"), t("UBIGINT")], t("UBIGINT"),
                        **special)
    con.create_function("prism_quotas", quotas_udf,
                        [t("UINTEGER[]"), t("BIGINT[]"), t("DOUBLE"), t("BIGINT"), t("BIGINT"), t("VARCHAR"),
                         t("UBIGINT")], t("BIGINT[]"), **special)
    con.execute(macro_sql("prism_sample"))
    con.execute(macro_sql("prism_sample_parquet", parquet=True))
    con.execute(macro_sql("prism_rank", rank=True))
    con.execute(macro_sql("prism_rank_parquet", parquet=True, rank=True))
    return con
