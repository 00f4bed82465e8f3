"""What a Dask prior holds, and what merging one costs, unit by unit, in one process (no cluster).

    python bench/prior_memory.py bench/data/b2p24/e01.parquet --units 9 --unit-points 3846154 \
        --declared 100000000 --ratio 0.05

Runs ``tasks.scan_unit_spill`` on consecutive units of one file, each with the prior merged from the units
before it (``tasks.merge_prior``, as the driver's merges make it, one unit at a time here), and prints after
each merge the prior's bins and bytes (histogram, bounds, evidence) and the process's RSS before the merge,
its peak during it (``/proc/self/status`` VmHWM, reset before each merge) and after. ``--declared`` is the
run's N (T = ratio x N), as a unit of a larger run sees it.
"""

from __future__ import annotations

import argparse
import tempfile
import time

from prism_stream.engines.dask.tasks import UnitRef, merge_prior, scan_unit_spill
from prism_stream.run.request import Request


def status() -> dict:
    with open("/proc/self/status") as f:
        return {line.split(":")[0]: int(line.split()[1]) // 1024 for line in f if line.startswith(("VmRSS", "VmHWM"))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("path")
    ap.add_argument("--units", type=int, default=9)
    ap.add_argument("--unit-points", type=int, default=3_846_154)
    ap.add_argument("--declared", type=int, required=True)
    ap.add_argument("--ratio", type=float, default=0.05)
    a = ap.parse_args()
    options = Request.of(None, ratio=a.ratio).options
    tmp = tempfile.mkdtemp(prefix="prior_memory.")
    prior = None
    for i in range(a.units):
        ref = UnitRef(a.path, 0, i * a.unit_points, (i + 1) * a.unit_points, (("rgb_columns", None),))
        result = scan_unit_spill(ref, options, a.declared, 1 << 20, tmp, prior)
        print(f"unit {i}: spill {result[1].points:,} points", flush=True)
        before = status()["VmRSS"]
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # VmHWM from here
        t = time.perf_counter()
        new = merge_prior(prior, result)
        s = status()
        mb = [new.histogram.keys.nbytes + new.histogram.counts.nbytes, new.limit_keys.nbytes + new.limits.nbytes,
              sum(x.nbytes for x in new.evidence)]
        print(f"merge {i}: {new.histogram.bins:,} bins, {len(new.limit_keys):,} bounds, {len(new.evidence[0]):,} "
              f"evidence rows; MB histogram/bounds/evidence {[x // 10**6 for x in mb]}; RSS before {before}, peak "
              f"{s['VmHWM']}, after {s['VmRSS']} MiB; {time.perf_counter() - t:.1f} s", flush=True)
        prior, new, result = new, None, None


if __name__ == "__main__":
    main()
