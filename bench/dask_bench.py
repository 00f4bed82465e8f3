"""Dask engine vs the local engine: wall time, peak RSS per worker, measured per-unit costs.

    python bench/dask_bench.py bench/data/pf7_100M.laz --workers 1 2 --memory-limit 400MB

For each worker count, a fresh LocalCluster (processes, one thread each) runs
``prism_stream.engines.dask.sample`` into a Parquet dataset; the local engine
runs in its own process on the same input. Per-task times come from the
scheduler's task stream, grouped by step (scan, decide, hmerge, bottoms,
bmerge, select). Prints a Markdown table and the JSON it was made from;
``--json`` appends the record to a file. Inputs: bench/make_data.py builds
bench/data; without it, ``--generate N`` writes a LAS tile set under
bench/data/dask/.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict

HERE = os.path.dirname(os.path.abspath(__file__))


def worker_peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run_local(inputs, out, ratio) -> dict:
    code = ("import json, sys, prism_stream; s = prism_stream.sample(sys.argv[1:-1], sys.argv[-1], ratio=%r, "
            "overwrite=True); print(json.dumps({'seconds': s.seconds, 'peak_rss_mib': s.peak_rss_bytes / 2**20, "
            "'kept': s.kept, 'points': s.points}))" % ratio)
    t = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", code, *inputs, out], capture_output=True, text=True, check=True)
    rec = json.loads(done.stdout.strip().splitlines()[-1])
    rec["wall"] = time.perf_counter() - t
    return rec


def run_dask(inputs, out, ratio, workers, memory_limit, unit_size, reads="auto") -> dict:
    from distributed import Client, LocalCluster, get_task_stream

    from prism_stream.engines import dask as dask_engine

    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, memory_limit=memory_limit,
                      dashboard_address=":0") as cluster, Client(cluster) as client:
        client.run(lambda: __import__("prism_stream.engines.dask"))  # imports and numba caches, outside the timing
        t = time.perf_counter()
        with get_task_stream(client) as ts:
            s = dask_engine.sample(client, inputs, out, ratio=ratio, unit_size=unit_size, overwrite=True,
                                   **({} if reads == "auto" else {"reads": reads}))
        wall = time.perf_counter() - t
        per_step = defaultdict(list)
        for task in ts.data:
            key = str(task["key"])
            step = key.split("-")[1] if key.startswith("prism-") else "other"
            start = min(x["start"] for x in task["startstops"] if x["action"] == "compute")
            stop = max(x["stop"] for x in task["startstops"] if x["action"] == "compute")
            per_step[step].append(stop - start)
        peaks = client.run(worker_peak_mib)
    return {
        "workers": workers, "memory_limit": memory_limit, "unit_size": unit_size, "wall": wall,
        "seconds": s.seconds, "kept": s.kept, "points": s.points, "bins": s.bins, "stats": s.plan["dask"],
        "reads": {k: s.plan[k] for k in ("reads", "why", "spill_points", "spill_bytes", "units_read_again")
                  if k in s.plan},
        "worker_peak_rss_mib": sorted(round(v, 1) for v in peaks.values()),
        "driver_peak_rss_mib": round(s.peak_rss_bytes / 2**20, 1),
        "task_seconds": {k: {"n": len(v), "mean": sum(v) / len(v), "max": max(v), "sum": sum(v)}
                         for k, v in sorted(per_step.items())},
    }


def generate(n: int) -> list[str]:
    sys.path.insert(0, HERE)
    from make_data import synthetic_tile

    folder = os.path.join(HERE, "data", "dask")
    os.makedirs(folder, exist_ok=True)
    paths = []
    per = 10_000_000
    for i, a in enumerate(range(0, n, per)):
        p = os.path.join(folder, f"tile_{i:03d}.las")
        if not os.path.exists(p):
            synthetic_tile(p, min(per, n - a), 100 + i, fmt=2)
        paths.append(p)
    return paths


def markdown(record: dict) -> str:
    lines = [f"Input: {', '.join(record['inputs'])} ({record['dask'][0]['points']:,} points), ratio {record['ratio']}, "
             f"{os.cpu_count()} cores.", "",
             "| engine | wall s | pass 1 s | cutoffs s | pass 2 s | peak RSS per process (MiB) |",
             "| --- | --- | --- | --- | --- | --- |"]
    loc = record["local"]
    if loc is not None:
        sec = loc["seconds"]
        lines.append(f"| local | {loc['wall']:.1f} | {sec.get('scan', 0):.1f} | {sec.get('cutoffs', 0):.1f} | "
                     f"{sec.get('select', 0):.1f} | {loc['peak_rss_mib']:.0f} |")
    for r in record["dask"]:
        sec = r["seconds"]
        lines.append(f"| dask {r['workers']} worker(s), {r['memory_limit']} | {r['wall']:.1f} | {sec['scan']:.1f} | "
                     f"{sec['cutoffs']:.1f} | {sec['select']:.1f} | workers {r['worker_peak_rss_mib']}, "
                     f"driver {r['driver_peak_rss_mib']:.0f} |")
    lines += ["", "Per-task compute time (s), from the scheduler's task stream:", "",
              "| workers | step | tasks | mean | max |", "| --- | --- | --- | --- | --- |"]
    for r in record["dask"]:
        for step, t in r["task_seconds"].items():
            lines.append(f"| {r['workers']} | {step} | {t['n']} | {t['mean']:.3f} | {t['max']:.3f} |")
    st = record["dask"][-1]["stats"]
    lines += ["", f"Sizes: global histogram {st['histogram_bytes'] / 2**20:.1f} MiB ({record['dask'][-1]['bins']:,} "
              f"bins); plan broadcast {st['plan_rules_bytes'] / 2**20:.2f} MiB of rules (the full plan's JSON "
              f"{st['plan_full_json_bytes'] / 2**20:.1f} MiB); unit bottoms sent {st['bottoms_pairs']} pairs "
              f"(12 bytes each) for {record['dask'][-1]['kept']:,} kept; cutoffs {st['cutoffs_bytes'] / 2**20:.2f} MiB; "
              f"{st['units']} units."]
    for r in record["dask"]:
        rd = r.get("reads", {})
        if "spill_points" in rd:
            lines.append(f"Reads ({r['workers']} workers): {rd['reads']}; spill {rd['spill_points']:,} points "
                         f"({rd['spill_points'] / r['points']:.1%} of N), {rd['spill_bytes'] / 2**20:.1f} MiB; "
                         f"units started with a prior: {r['stats'].get('units_with_prior', 0)}.")
        elif rd:
            lines.append(f"Reads ({r['workers']} workers): {rd['reads']} ({rd['why']}).")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("inputs", nargs="*")
    ap.add_argument("--generate", type=float, help="write this many points of LAS tiles under bench/data/dask/")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--memory-limit", default="400MB")
    ap.add_argument("--unit-size", type=int, default=1 << 22)
    ap.add_argument("--ratio", type=float, default=0.01)
    ap.add_argument("--reads", default="auto", choices=("auto", "two"), help="the engine's --reads")
    ap.add_argument("--no-local", action="store_true", help="skip the local engine's run")
    ap.add_argument("--json", help="append the record (one JSON line) to this file")
    args = ap.parse_args(argv)
    inputs = args.inputs or generate(int(args.generate or 20_000_000))
    tmp = tempfile.mkdtemp(prefix="dask-bench-", dir=os.path.join(HERE, "out") if os.path.isdir(
        os.path.join(HERE, "out")) else None)
    try:
        record = {"inputs": inputs, "ratio": args.ratio, "when": time.strftime("%Y-%m-%dT%H:%M:%S"),
                  "load1": os.getloadavg()[0]}
        record["reads"] = args.reads
        record["local"] = (None if args.no_local else
                           run_local(inputs, os.path.join(tmp, "local.parquet"), args.ratio))
        record["dask"] = [run_dask(inputs, os.path.join(tmp, f"dask{w}"), args.ratio, w, args.memory_limit,
                                   args.unit_size, args.reads) for w in args.workers]
        record["load1_after"] = os.getloadavg()[0]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(markdown(record))
    print(json.dumps(record))
    if args.json:
        with open(args.json, "a") as f:
            f.write(json.dumps(record) + "\n")


if __name__ == "__main__":
    main()
