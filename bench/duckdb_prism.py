"""PRISM (SPEC.md, exact rule) written as plain DuckDB SQL over one Parquet file.

    python bench/duckdb_prism.py IN.parquet OUT.parquet --ratio 0.01 [--seed 0] [--threads 2]

The comparison point for prism-stream's Parquet -> Parquet path: the same
answer, computed the way a SQL user would write it.

- 64-bit arithmetic. SPEC's splitmix64 works mod 2^64, but DuckDB raises on
  UBIGINT overflow instead of wrapping. The additions and multiplications
  are therefore done in UHUGEINT (unsigned 128-bit: the product of two
  64-bit words always fits) and masked back to the low 64 bits; shifts and
  ``xor()`` stay in UBIGINT (in DuckDB ``^`` is power, not xor).
- Point id: ``file_row_number`` (one source, ordinal 0, so id = record index).
- Color depth ``auto``: one aggregate over the three color columns first.
- Quotas: the exact rule (SPEC 4) in SQL. S(K) = sum(min(n_b, K)) is linear
  between consecutive distinct bin sizes, so the largest K with S(K) <= T is
  found per segment from running sums over the sorted distinct sizes; the
  E = T - S(K) extra points go to the bins with n_b > K of smallest bin
  priority.
- Selection: ``QUALIFY row_number() OVER (PARTITION BY bin ORDER BY priority) <= q``
  (priorities are a bijection of ids, so there are no ties), written in input
  order (``ORDER BY id``) with zstd, as prism-stream writes.

Prints one JSON line: points, bins, K, E, target, kept, seconds per statement.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import duckdb

GOLDEN = 0x9E3779B97F4A7C15
MIX1 = 0xBF58476D1CE4E5B9
MIX2 = 0x94D049BB133111EB

MACROS = [
    "CREATE MACRO m64(x) AS (x & 18446744073709551615::UHUGEINT)::UBIGINT",
    "CREATE MACRO add64(a, b) AS m64(a::UHUGEINT + b::UHUGEINT)",
    "CREATE MACRO mul64(a, b) AS m64(a::UHUGEINT * b::UHUGEINT)",
]


def splitmix64_sql(source: str, x: str, out: str) -> str:
    """``SELECT *, splitmix64(x) AS out FROM (source)`` as explicit steps (each intermediate computed once)."""
    return (
        f"SELECT * EXCLUDE (_z1, _z2, _z3), xor(_z3, _z3 >> 31) AS {out} FROM ("
        f" SELECT *, mul64(xor(_z2, _z2 >> 27), {MIX2}::UBIGINT) AS _z3 FROM ("
        f"  SELECT *, mul64(xor(_z1, _z1 >> 30), {MIX1}::UBIGINT) AS _z2 FROM ("
        f"   SELECT *, add64({x}, {GOLDEN}::UBIGINT) AS _z1 FROM ({source}))))"
    )


def splitmix64_scalar(con, x: int) -> int:
    return con.execute(splitmix64_sql(f"SELECT {x}::UBIGINT AS v", "v", "h")).fetchone()[-1]


def run(path: str, output: str, ratio: float, seed: int = 0, threads: int | None = None) -> dict:
    con = duckdb.connect()
    if threads:
        con.execute(f"SET threads = {int(threads)}")
    con.execute("SET preserve_insertion_order = false")
    for m in MACROS:
        con.execute(m)
    secs = {}
    src = f"read_parquet('{path}', file_row_number = true)"

    t = time.perf_counter()
    shift = con.execute(f"SELECT CASE WHEN max(greatest(red, green, blue)) <= 255 THEN 0 ELSE 8 END "
                        f"FROM read_parquet('{path}')").fetchone()[0]
    secs["color_depth"] = time.perf_counter() - t
    key = (f"((red >> {shift})::UBIGINT << 16) | ((green >> {shift})::UBIGINT << 8) | (blue >> {shift})::UBIGINT")
    seed_mix = splitmix64_scalar(con, seed)
    bin_mix = splitmix64_scalar(con, (seed + 1) % (1 << 64))

    t = time.perf_counter()
    con.execute(f"CREATE TEMP TABLE hist AS SELECT {key} AS bin, count(*) AS n FROM {src} GROUP BY bin")
    secs["histogram"] = time.perf_counter() - t

    t = time.perf_counter()
    con.execute(f"""
        CREATE TEMP TABLE tot AS
        SELECT sum(n)::BIGINT AS big_n, floor({float(ratio)!r} * sum(n) + 0.5)::BIGINT AS t, max(n) AS max_n,
               count(*) AS bins FROM hist""")
    con.execute("""
        CREATE TEMP TABLE kk AS
        WITH sizes AS (SELECT n AS v, count(*) AS c FROM hist GROUP BY n),
        seg AS (
            SELECT v, coalesce(lag(v) OVER (ORDER BY v), 0) AS prev,
                   coalesce(sum(v * c) OVER (ORDER BY v ROWS BETWEEN UNBOUNDED PRECEDING AND 1 PRECEDING), 0)
                       AS p_below,
                   sum(c) OVER (ORDER BY v ROWS BETWEEN CURRENT ROW AND UNBOUNDED FOLLOWING) AS c_ge
            FROM sizes),
        cand AS (
            SELECT least(v - 1, (t - p_below) // c_ge) AS k, prev FROM seg, tot WHERE t >= p_below)
        SELECT greatest((SELECT coalesce(max(k), 0) FROM cand WHERE k >= prev),
                        (SELECT CASE WHEN t >= big_n THEN max_n ELSE 0 END FROM tot))::BIGINT AS k""")
    bins_prio = splitmix64_sql(f"SELECT bin, n, xor(bin, {bin_mix}::UBIGINT) AS bx FROM hist", "bx", "bin_priority")
    con.execute(f"""
        CREATE TEMP TABLE quota AS
        WITH e AS (SELECT (SELECT t FROM tot) - sum(least(n, (SELECT k FROM kk))) AS e FROM hist),
        ranked AS (
            SELECT bin, n, row_number() OVER (ORDER BY (n <= (SELECT k FROM kk)), bin_priority) AS r
            FROM ({bins_prio}))
        SELECT bin, least(n, (SELECT k FROM kk)) + CASE WHEN n > (SELECT k FROM kk) AND r <= (SELECT e FROM e)
                                                   THEN 1 ELSE 0 END AS q
        FROM ranked""")
    con.execute("DELETE FROM quota WHERE q = 0")
    secs["solve"] = time.perf_counter() - t

    t = time.perf_counter()
    keyed = f"SELECT *, {key} AS bin, xor(file_row_number::UBIGINT, {seed_mix}::UBIGINT) AS idx FROM {src}"
    prio = splitmix64_sql(keyed, "idx", "priority")
    con.execute(f"""
        COPY (
            SELECT * EXCLUDE (file_row_number, bin, idx, priority, q) FROM (
                SELECT p.*, quota.q FROM ({prio}) AS p JOIN quota USING (bin)
                QUALIFY row_number() OVER (PARTITION BY bin ORDER BY priority) <= q)
            ORDER BY file_row_number
        ) TO '{output}' (FORMAT parquet, COMPRESSION zstd)""")
    secs["select"] = time.perf_counter() - t

    tot = con.execute("SELECT big_n, t, bins FROM tot").fetchone()
    k = con.execute("SELECT k FROM kk").fetchone()[0]
    extra = con.execute("SELECT count(*) FROM quota JOIN hist USING (bin) WHERE q > least(n, (SELECT k FROM kk))"
                        ).fetchone()[0]
    kept = con.execute(f"SELECT count(*) FROM read_parquet('{output}')").fetchone()[0]
    secs["total"] = sum(secs.values())
    return {"points": tot[0], "target": tot[1], "bins": tot[2], "k": k, "extra": extra, "kept": kept,
            "color_shift": shift, "seconds": {a: round(b, 4) for a, b in secs.items()}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="PRISM in DuckDB SQL (exact rule).")
    ap.add_argument("input")
    ap.add_argument("output")
    ap.add_argument("--ratio", type=float, required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None)
    a = ap.parse_args(argv)
    print(json.dumps(run(a.input, a.output, a.ratio, a.seed, a.threads)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
