"""Issue 26's scale runs: a billion points and more, in tiles, with every output checked independently.

    python bench/make_data.py --sizes 60M --inputs parquet pf7_laz
    mkdir -p bench/data/b1pq bench/data/b1laz
    for i in $(seq -w 1 17); do cp bench/data/pf7_60M.parquet bench/data/b1pq/t$i.parquet; \
        cp bench/data/pf7_60M.laz bench/data/b1laz/t$i.laz; done
    python bench/billion.py --tiles 'bench/data/b1pq/*.parquet' --runs floor plan one two --json bench/out/b1pq.json
    python bench/billion.py --tiles 'bench/data/b1laz/*.laz' --runs floor one --truth 'bench/data/b1pq/*.parquet' \
        --json bench/out/b1laz.json

Seventeen distinct copies of one 60M-point tile are 1.02 billion points (the engine refuses one file given
twice, not two files with the same points). Each run is a child process, measured from outside: wall time,
the peak RSS of its whole process tree (Dask workers included) and of each process in it, and the peak of
the temporary disk (every file under the run's --temp-dir and beside the output, polled every half second).
Runs:

- ``floor``: one bare decode of every tile (pyarrow ``iter_batches`` of every column; laspy's chunk reader);
- ``plan``: ``--plan`` (pass one over the colors with the run's candidate filter: the spill it predicts);
- ``one``: the default run (one read and a candidate spill); ``two``: ``--reads two``;
- ``dask``: ``--dask local:2`` into a Parquet dataset; ``dask-two``: the same with ``--reads two``;
  ``dask-one``: with ``--reads one`` (Parquet inputs read once on Dask too: ``--reads auto`` reads them twice);
- ``rank``: ``prism-stream rank --max-ratio R`` (the sample for R N, ranked; its ranks checked to be 0..T-1).

Every output is checked with DuckDB against a histogram of the input (``--truth``: Parquet tiles holding the
same points, for LAZ): rows = round(r N), every bin's count within [min(n_b, K), min(n_b, K + 1)], and exactly
E bins at K + 1 (exact mode).
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import os
import shutil
import subprocess
import sys
import threading
import time

import psutil

from peak_by_process import role  # bench/ is the script's folder: a process's part in the run, named once

HERE = os.path.dirname(os.path.abspath(__file__))
CLI = [sys.executable, "-m", "prism_stream"]

FLOOR = r"""
import sys, laspy, pyarrow.parquet as pq
n = 0
for f in sys.argv[1:]:
    if f.endswith(".parquet"):
        for b in pq.ParquetFile(f).iter_batches(batch_size=1 << 20):
            n += b.num_rows
    else:
        with laspy.open(f) as r:
            for c in r.chunk_iterator(1 << 20):
                n += len(c)
print(n)
"""


def tree_bytes(paths) -> int:
    total = 0
    for top in paths:
        for root, _, files in os.walk(top):
            for name in files:
                try:
                    total += os.lstat(os.path.join(root, name)).st_size
                except OSError:
                    pass
    return total


def measure(cmd, watch, log, interval: float = 0.5, env=None) -> dict:
    """Run ``cmd`` (in ``env``); its wall time, peak tree RSS, and the peak bytes under ``watch`` (folders),
    sampled every ``interval`` seconds."""
    peak = {"rss": 0, "disk": 0}
    each: dict = {}  # pid -> (its peak RSS, its role): one process's peak is what the 1 GiB bound is about
    base = tree_bytes(watch)  # what was there before (earlier runs' outputs): not this run's
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    done = threading.Event()

    def poll():
        ps = psutil.Process(proc.pid)
        while not done.is_set():
            rss = 0
            try:
                procs = [ps, *ps.children(recursive=True)]
            except psutil.Error:
                procs = []
            for p in procs:
                try:
                    mine = p.memory_info().rss
                    if mine > each.get(p.pid, (0, ""))[0]:
                        each[p.pid] = (mine, role(p.cmdline(), p.pid == proc.pid))
                except psutil.Error:
                    continue
                rss += mine
            peak["rss"] = max(peak["rss"], rss)
            peak["disk"] = max(peak["disk"], tree_bytes(watch))
            done.wait(interval)

    th = threading.Thread(target=poll, daemon=True)
    th.start()
    out, err = proc.communicate()
    done.set()
    th.join()
    wall = time.perf_counter() - t0
    if proc.returncode:
        log(f"FAILED ({proc.returncode}): {' '.join(cmd)}\n{err[-2000:]}")
    return {"command": cmd, "returncode": proc.returncode, "wall_s": round(wall, 1),
            "peak_rss_mib": round(peak["rss"] / 2**20),
            "process_peaks_mib": sorted(([round(m / 2**20, 1), role] for m, role in each.values()), reverse=True),
            "temp_peak_bytes": max(0, peak["disk"] - base),
            "stdout": out[-4000:]}


def truth_histogram(tiles: list, depth: str, cache: str) -> dict:
    """The input's bin counts, by DuckDB (8-bit keys: 16-bit colors shifted down, as SPEC 1 bins them)."""
    if os.path.exists(cache):
        with open(cache) as f:
            return {int(k): v for k, v in json.load(f).items()}
    import duckdb

    shift = 8 if str(depth).startswith("16") else 0
    con = duckdb.connect()
    files = ", ".join(f"'{t}'" for t in tiles)
    rows = con.execute(f"SELECT ((red::INTEGER >> {shift}) << 16) | ((green::INTEGER >> {shift}) << 8) | (blue::INTEGER >> {shift}) AS k, "
                       f"count(*) FROM read_parquet([{files}]) GROUP BY 1").fetchall()
    hist = {int(k): int(n) for k, n in rows}
    with open(cache, "w") as f:
        json.dump(hist, f)
    return hist


def check(output: str, summary: dict, truth: dict) -> dict:
    import duckdb

    depth = summary["sources"][0]["color_depth"]
    shift = 8 if str(depth).startswith("16") else 0
    src = f"read_parquet('{output}/*.parquet')" if os.path.isdir(output) else f"read_parquet('{output}')"
    rows = duckdb.connect().execute(f"SELECT ((red::INTEGER >> {shift}) << 16) | ((green::INTEGER >> {shift}) << 8) | "
                                    f"(blue::INTEGER >> {shift}) AS k, count(*) FROM {src} GROUP BY 1").fetchall()
    out = {int(k): int(n) for k, n in rows}
    n, k, t = summary["points"], summary["k"], summary["kept"]
    ok = sum(out.values()) == t and sum(truth.values()) == n and set(out) <= set(truth)
    at_k1 = 0
    for key, nb in truth.items():
        q = out.get(key, 0)
        ok &= min(nb, k) <= q <= min(nb, k + 1)
        at_k1 += q == k + 1
    ok &= at_k1 == summary["extra"]
    return {"ok": bool(ok), "rows": sum(out.values()), "bins_at_k1": at_k1}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tiles", required=True, help="a glob of the tiles")
    ap.add_argument("--truth", help="Parquet tiles with the same points, for the check (default: --tiles)")
    ap.add_argument("--ratio", type=float, default=0.01)
    ap.add_argument("--runs", nargs="+", default=["floor", "plan", "one", "two"],
                    choices=["floor", "plan", "one", "two", "dask", "dask-two", "dask-one", "rank"])
    ap.add_argument("--work", default=os.path.join(HERE, "data", "billion_work"), help="outputs and temp folder")
    ap.add_argument("--json", required=True)
    args = ap.parse_args()
    tiles = sorted(glob.glob(args.tiles))
    truth_tiles = sorted(glob.glob(args.truth or args.tiles))
    os.makedirs(args.work, exist_ok=True)
    tmp = os.path.join(args.work, "tmp")
    results = {"machine": {"cpus": os.cpu_count(), "memory_gib": round(psutil.virtual_memory().total / 2**30, 1)},
               "tiles": tiles, "ratio": args.ratio, "runs": {}}

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    for run in args.runs:
        shutil.rmtree(tmp, ignore_errors=True)
        os.makedirs(tmp)
        out = os.path.join(args.work, "out_dask" if run.startswith("dask") else "out.parquet")
        shutil.rmtree(out, ignore_errors=True) if os.path.isdir(out) else (os.path.exists(out) and os.unlink(out))
        summary_file = os.path.join(args.work, f"summary_{run}.json")
        if os.path.exists(summary_file):
            os.unlink(summary_file)
        if run == "floor":
            cmd = [sys.executable, "-c", FLOOR, *tiles]
        elif run == "plan":
            cmd = [*CLI, "--plan", *tiles, "--ratio", str(args.ratio)]
        elif run == "rank":
            cmd = [*CLI, "rank", *tiles, out, "--max-ratio", str(args.ratio)]
        else:
            cmd = [*CLI, *tiles, out, "--ratio", str(args.ratio)]
            if run in ("two", "dask-two"):
                cmd += ["--reads", "two"]
            if run == "dask-one":
                cmd += ["--reads", "one"]
            if run.startswith("dask"):
                cmd += ["--dask", "local:2"]
        if run != "floor":
            cmd += ["--temp-dir", tmp, "--summary", summary_file, "--quiet"]
        log(f"{run}: {' '.join(cmd[:6])} ...")
        r = measure(cmd, [args.work], log)  # the temp folder is inside it
        if run != "floor" and r["returncode"] == 0:
            with open(summary_file) as f:
                s = json.load(f)
            r["summary"] = {k: s[k] for k in ("points", "target", "kept", "k", "extra", "bins", "seconds",
                                              "peak_rss_bytes")}
            r["plan"] = {k: v for k, v in s["plan"].items() if k in ("reads", "why", "spill_points", "spill_bytes",
                                                                     "spill_points_written", "spill_compactions",
                                                                     "temp")}
            if run.startswith("dask"):
                r["plan"]["dask"] = s["plan"].get("dask")
            n, t = s["points"], s["kept"]
            r["bound"] = math.ceil(min(n, 2 * t * (1 + math.log(n / t)))) if t else 0
            if run != "plan":
                truth = truth_histogram(truth_tiles, s["sources"][0]["color_depth"],
                                        os.path.join(args.work, "truth_" + os.path.basename(truth_tiles[0]) +
                                                     f"_{len(truth_tiles)}.json"))
                r["check"] = check(out, s, truth)
                if run == "rank":  # the ranks of the sample for T are 0..T-1, each once
                    import duckdb

                    lo, hi, distinct = duckdb.connect().execute(
                        f"SELECT min(prism_rank), max(prism_rank), count(DISTINCT prism_rank) FROM '{out}'").fetchone()
                    r["check"]["ranks_ok"] = (lo, hi, distinct) == (0, t - 1, t)
                    r["check"]["ok"] &= r["check"]["ranks_ok"]
        results["runs"][run] = r
        log(f"{run}: {json.dumps({k: v for k, v in r.items() if k not in ('command', 'stdout')})}")
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
