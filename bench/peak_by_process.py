"""The peak RSS of each process of a run, not only of the whole tree: which process holds the memory.

    python bench/peak_by_process.py -- prism-stream t1.parquet t2.parquet out.parquet --ratio 0.01 --dask local:2

``/usr/bin/time -f %M`` reports the largest peak of any process in the tree that was waited for (the kernel
folds reaped children's peaks into their parent's), so for a Dask run it cannot tell the driver from a
worker. This polls every process of the tree (psutil, every 0.1 s) and prints each one's peak RSS with its
role (driver, nanny, worker, ...), the peak of the tree's sum, and the wall time, as JSON on stdout.
``--timeline FILE`` (before ``--``) also writes every poll (seconds, pid, RSS MiB) as CSV, to see which phase
of a run peaks (the run's ``--json`` summary gives each phase's seconds).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import psutil


def role(cmdline: list[str], root: bool) -> str:
    text = " ".join(cmdline)
    if root:
        return "driver"
    if "multiprocessing.forkserver" in text or "forkserver" in text:
        return "forkserver"
    if "spawn_main" in text or "multiprocessing" in text:
        return "worker process"
    return text[:80]


def main(argv: list[str]) -> int:
    timeline = None
    if "--" in argv:
        mine, argv = argv[:argv.index("--")], argv[argv.index("--") + 1:]
        if mine[:1] == ["--timeline"] and len(mine) == 2:
            timeline = open(mine[1], "w")
            timeline.write("seconds,pid,rss_mib\n")
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__, file=sys.stderr)
        return 0 if argv else 2
    start = time.perf_counter()
    proc = subprocess.Popen(argv)
    root = psutil.Process(proc.pid)
    peaks: dict[int, dict] = {}
    total_peak = 0
    while proc.poll() is None:
        total = 0
        try:
            tree = [root, *root.children(recursive=True)]
        except psutil.Error:
            tree = []
        for p in tree:
            try:
                rss = p.memory_info().rss
                if p.pid not in peaks:
                    peaks[p.pid] = {"pid": p.pid, "role": role(p.cmdline(), p.pid == proc.pid), "peak_mib": 0.0,
                                    "first_seen_s": round(time.perf_counter() - start, 1)}
            except psutil.Error:
                continue
            total += rss
            if timeline is not None:
                timeline.write(f"{time.perf_counter() - start:.2f},{p.pid},{rss / 2**20:.1f}\n")
            peaks[p.pid]["peak_mib"] = max(peaks[p.pid]["peak_mib"], round(rss / 2**20, 1))
        total_peak = max(total_peak, total)
        time.sleep(0.1)
    if timeline is not None:
        timeline.close()
    out = {"command": argv, "exit": proc.returncode, "wall_s": round(time.perf_counter() - start, 2),
           "tree_sum_peak_mib": round(total_peak / 2**20, 1),
           "processes": sorted(peaks.values(), key=lambda d: -d["peak_mib"])}
    print(json.dumps(out, indent=1))
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
