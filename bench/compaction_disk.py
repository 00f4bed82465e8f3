"""The temporary disk a compacting run takes: the spill's compactions written beside the old files, or in place.

    python bench/compaction_disk.py bench/data/eq_20M_10000_sorted.parquet --ratio 0.05 \
        --rev before=/tmp/wt_5f47532 --rev after=. --runs 3 --json bench/out/compaction_disk.json

Each revision (a checkout: its ``prism_stream`` comes first on the path, and ``python -P`` keeps the current
folder off it, so a worktree of an older commit runs its own code) samples the cloud through the library
(``prism_stream.sample``, one read, nothing else changed) in a child process, the revisions interleaved run by
run. ``billion.measure`` samples the temporary folder's bytes every 0.05 s, the process tree's RSS and the wall
time; in the child, the folder's bytes after every write of a temporary file (``staging.mark``, which each
write calls: a peak polling can miss in a compaction that lasts a fraction of a second; the old rewrite's new
frames file was marked only once complete, so its peak there leaves that file out); the run's own summary
gives the spill (candidates written, the most held at once, left, compactions). Medians over the runs; every
run's rows (the output less its provenance) are checked to be the first run's (``same_rows``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import billion  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402

CHILD = """
import json, os, sys
import prism_stream
from prism_stream.run import staging
src, out, ratio, temp = sys.argv[1:5]
peak = [0]
mark = staging.mark

def tracked(path, fd):  # after every write of a temporary file: the folder's bytes, exactly (no polling)
    mark(path, fd)
    peak[0] = max(peak[0], sum(os.lstat(os.path.join(r, n)).st_size for r, _, fs in os.walk(temp) for n in fs))

staging.mark = tracked
s = prism_stream.sample(src, out, ratio=float(ratio), temp_dir=temp, reads="one")
print(json.dumps({"temp_peak_at_writes": peak[0], **{k: s.plan.get(k) for k in (
    "reads", "spill_points", "spill_points_peak", "spill_points_written", "spill_compactions")}}))
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cloud")
    ap.add_argument("--ratio", type=float, default=0.05)
    ap.add_argument("--rev", action="append", required=True, help="LABEL=CHECKOUT (repeat)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--work", default="/tmp/compaction_disk")
    ap.add_argument("--json", required=True)
    a = ap.parse_args()
    revs = [r.split("=", 1) for r in a.rev]
    rows: dict = {label: [] for label, _ in revs}
    first, same = None, []
    for i in range(a.runs):
        for label, checkout in revs:
            shutil.rmtree(a.work, ignore_errors=True)
            temp = os.path.join(a.work, "tmp")
            os.makedirs(temp)
            out = os.path.join(a.work, "out.parquet")
            env = {**os.environ, "PYTHONPATH": os.path.abspath(checkout)}
            m = billion.measure([sys.executable, "-P", "-c", CHILD, a.cloud, out, str(a.ratio), temp], [temp],
                                lambda msg: print(msg, file=sys.stderr), interval=0.05, env=env)
            if m["returncode"]:
                return 1
            m["summary"] = json.loads(m.pop("stdout").strip().splitlines()[-1])
            table = pq.read_table(out).replace_schema_metadata(None)  # the rows, without the run's provenance
            first = first if first is not None else table
            same.append(table.equals(first))
            rows[label].append(m)
            print(f"{label} run {i + 1}: {m['wall_s']} s, temp peak {m['temp_peak_bytes'] / 2**20:.1f} MiB, "
                  f"RSS {m['peak_rss_mib']} MiB, {m['summary']}", file=sys.stderr, flush=True)
    summary = {"cloud": a.cloud, "ratio": a.ratio, "runs": a.runs, "same_rows": all(same), "revisions": {}}
    for label, checkout in revs:
        ms = rows[label]
        summary["revisions"][label] = {
            "checkout": checkout,
            "wall_s_median": statistics.median(m["wall_s"] for m in ms),
            "temp_peak_mib_median": round(statistics.median(m["temp_peak_bytes"] for m in ms) / 2**20, 1),
            "temp_peak_mib_max": round(max(m["temp_peak_bytes"] for m in ms) / 2**20, 1),
            "temp_peak_at_writes_mib": round(max(m["summary"]["temp_peak_at_writes"] for m in ms) / 2**20, 1),
            "peak_rss_mib_median": statistics.median(m["peak_rss_mib"] for m in ms),
            "spill": ms[0]["summary"], "runs": ms}
    with open(a.json, "w") as f:
        json.dump(summary, f, indent=1)
    print(f"same rows in every run: {summary['same_rows']}")
    for label, r in summary["revisions"].items():
        print(f"{label:>8}: wall {r['wall_s_median']} s, temp peak {r['temp_peak_mib_median']} MiB "
              f"(max {r['temp_peak_mib_max']}; at writes {r['temp_peak_at_writes_mib']}), "
              f"RSS {r['peak_rss_mib_median']} MiB, spill {r['spill']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
