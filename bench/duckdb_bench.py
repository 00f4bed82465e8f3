"""The DuckDB paths against the streaming engine, on the big Parquet inputs.

    python bench/duckdb_bench.py --sizes 20M 100M [--ratio 0.01] [--memory-limit 4GB]

Methods, each in a fresh process (wall time, and peak RSS from
``RUSAGE_CHILDREN``, i.e. that process alone):

- ``engine``: ``prism-stream sample IN OUT --ratio R`` (the file command);
- ``macro``: ``COPY (SELECT * FROM prism_sample_parquet(IN, ratio := R)) TO OUT``
  in DuckDB with ``memory_limit`` and a ``temp_directory`` under bench/out;
- ``sql-rerun`` / ``sql-spool``: ``prism-stream sql "SELECT * FROM read_parquet(IN)" OUT``
  with each way of reading the result twice.

Inputs are ``bench/data/pf7_<N>.parquet`` from bench/make_data.py (built if
missing). Every output is checked equal to the engine's (same rows, same
order, via DuckDB). Prints a Markdown table; ``--write`` puts it in
bench/RESULTS_DUCKDB.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DATA = HERE / "data"
OUT = HERE / "out" / "duckdb"
PY = sys.executable

MACRO = """
import duckdb, sys
from prism_stream.sql import functions as prism_duckdb
src, out, ratio, mem, tmp = sys.argv[1:6]
con = prism_duckdb.register(duckdb.connect())
con.execute(f"SET memory_limit = '{mem}'")
con.execute(f"SET temp_directory = '{tmp}'")
con.execute(f"COPY (SELECT * FROM prism_sample_parquet('{src}', ratio := {ratio})) TO '{out}' (FORMAT parquet, COMPRESSION zstd)")
con.close()
"""

SAME = """
import duckdb, sys
a, b = sys.argv[1:3]
con = duckdb.connect()
n = con.execute(f"SELECT count(*) FROM '{a}'").fetchone()[0]
m = con.execute(f"SELECT count(*) FROM '{b}'").fetchone()[0]
cols = ', '.join(c for c in con.execute(f"SELECT * FROM '{b}' LIMIT 0").to_arrow_table().column_names)
diff = con.execute(f"SELECT count(*) FROM (SELECT row_number() OVER () AS i, {cols} FROM '{a}' "
                   f"EXCEPT SELECT row_number() OVER () AS i, {cols} FROM '{b}')").fetchone()[0]
con.close()
print(int(n == m and diff == 0))
"""


def parse_size(text: str) -> int:
    t = text.strip().lower()
    mult = {"k": 10**3, "m": 10**6}.get(t[-1:], 1)
    return int(float(t[:-1] if mult != 1 else t) * mult)


def measure(cmd: list[str]) -> dict:
    """Run one method in a child process wrapper so RUSAGE_CHILDREN holds that child's peak alone."""
    wrapper = ("import resource, subprocess, sys, time, json; t = time.perf_counter(); "
               "r = subprocess.run(sys.argv[1:]); s = time.perf_counter() - t; "
               "print(json.dumps({'rc': r.returncode, 'seconds': s, "
               "'rss': resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024}))")
    res = subprocess.run([PY, "-c", wrapper, *cmd], capture_output=True, text=True, cwd=ROOT)
    last = res.stdout.strip().splitlines()[-1] if res.stdout.strip() else "{}"
    out = json.loads(last)
    if out.get("rc") != 0:
        out["error"] = res.stderr.strip().splitlines()[-1:] or ["?"]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", default=["20M", "100M"])
    ap.add_argument("--ratio", type=float, default=0.01)
    ap.add_argument("--memory-limit", default="4GB")
    ap.add_argument("--methods", nargs="+", default=["engine", "macro", "sql-rerun", "sql-spool"])
    ap.add_argument("--write", action="store_true", help="write bench/RESULTS_DUCKDB.md")
    args = ap.parse_args(argv)
    OUT.mkdir(parents=True, exist_ok=True)
    rows = []
    for size in args.sizes:
        src = DATA / f"pf7_{size}.parquet"
        if not src.exists():
            subprocess.run([PY, str(HERE / "make_data.py"), "--sizes", size], check=True)
        n = parse_size(size)
        outs = {}
        for method in args.methods:
            out = OUT / f"{method}_{size}.parquet"
            if out.exists():
                out.unlink()
            tmp = OUT / f"tmp_{method}"
            tmp.mkdir(exist_ok=True)
            if method == "engine":
                cmd = [PY, "-m", "prism_stream_cli.main", "sample", str(src), str(out), "--ratio", str(args.ratio),
                       "-q", "--temp-dir", str(tmp)]
            elif method == "macro":
                cmd = [PY, "-c", MACRO, str(src), str(out), str(args.ratio), args.memory_limit, str(tmp)]
            else:
                cmd = [PY, "-m", "prism_stream_cli.main", "sql", f"SELECT * FROM read_parquet('{src}')", str(out),
                       "--ratio", str(args.ratio), "-q", "--materialize", method.split("-")[1], "--temp-dir",
                       str(tmp), "--memory-limit", args.memory_limit]
            r = measure(cmd)
            outs[method] = out
            same = "-"
            if method != "engine" and "engine" in outs and out.exists() and outs["engine"].exists():
                same = "yes" if subprocess.run([PY, "-c", SAME, str(out), str(outs["engine"])], capture_output=True,
                                               text=True).stdout.strip() == "1" else "NO"
            row = dict(size=size, points=n, method=method, seconds=round(r.get("seconds", 0), 1),
                       peak_rss_mib=round(r.get("rss", 0) / 2**20), same_as_engine=same, error=r.get("error"))
            rows.append(row)
            print(json.dumps(row), flush=True)
    table = ["| input | points | method | wall s | peak RSS MiB | rows equal the engine's |",
             "| --- | ---: | --- | ---: | ---: | --- |"]
    for r in rows:
        table.append(f"| pf7_{r['size']}.parquet | {r['points']:,} | {r['method']} | {r['seconds']} | "
                     f"{r['peak_rss_mib']:,} | {r['same_as_engine'] if not r['error'] else 'failed: ' + r['error'][0]} |")
    text = "\n".join(table)
    print(text)
    if args.write:
        header = (f"# DuckDB paths vs the streaming engine\n\n`python bench/duckdb_bench.py --sizes "
                  f"{' '.join(args.sizes)} --ratio {args.ratio} --memory-limit {args.memory_limit} --write`\n\n"
                  f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
                  f"run {time.strftime('%Y-%m-%d %H:%M')}.\n\n")
        (HERE / "RESULTS_DUCKDB.md").write_text(header + text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
