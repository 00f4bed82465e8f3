"""The fixed cost of a streamed run: small inputs, many runs in one process, as a per-file batch or the test
suite makes them (each Dask unit pays the same scans at its end).

For each input and read method, ``--runs`` streamed runs in this process (the first, which loads the
kernels, left out), each timed for its wall time, CPU time and the page faults the OS took for it (minor
faults: pages mapped for the first time). Medians printed, and written with ``--json``.

    python bench/fixed_cost.py                        # the bundled files, one and two reads
    python bench/fixed_cost.py --json bench/out/fixed_cost.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FILES = ["tests/data/real/pdal__warsaw_small.las", "tests/data/real/pdal__autzen_trim.las",
         "tests/data/real/laspy__fullwave.laz"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=15)
    ap.add_argument("--ratio", type=float, default=0.05)
    ap.add_argument("--json")
    ap.add_argument("files", nargs="*", default=[str(ROOT / f) for f in FILES])
    args = ap.parse_args()
    os.environ["PRISM_STREAM_MEMORY_POINTS"] = "0"  # streamed, as a file past the in-memory limit is
    import prism_stream

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for path in args.files:
            for reads in ("one", "two"):
                walls, cpus, faults = [], [], []
                for i in range(args.runs + 1):
                    a, t = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
                    prism_stream.sample([path], os.path.join(tmp, "out.parquet"), ratio=args.ratio, reads=reads,
                                        overwrite=True)
                    w, b = time.perf_counter() - t, resource.getrusage(resource.RUSAGE_SELF)
                    if i:
                        walls.append(w)
                        cpus.append(b.ru_utime + b.ru_stime - a.ru_utime - a.ru_stime)
                        faults.append(b.ru_minflt - a.ru_minflt)
                row = {"file": Path(path).name, "reads": reads, "runs": args.runs,
                       "wall_ms": round(1e3 * statistics.median(walls), 1),
                       "cpu_ms": round(1e3 * statistics.median(cpus), 1),
                       "page_faults": int(statistics.median(faults))}
                rows.append(row)
                print(f"{row['file']:32} {reads:4} wall {row['wall_ms']:7.1f} ms  cpu {row['cpu_ms']:7.1f} ms  "
                      f"faults {row['page_faults']:7d}", flush=True)
    if args.json:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
        Path(args.json).write_text(json.dumps({"machine": platform.processor() or platform.machine(),
                                               "cpus": os.cpu_count(), "revision": rev.stdout.strip(),
                                               "python": sys.version.split()[0], "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
