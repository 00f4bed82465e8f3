"""The temporary disk a compacting run takes: the spill's compactions written beside the old files, or in place.

    python bench/compaction_disk.py bench/data/eq_20M_10000_sorted.parquet --ratio 0.05 \
        --rev before=/tmp/wt_5f47532 --rev after=. --runs 3 --json bench/out/compaction_disk.json

Each revision (a checkout: its ``prism_stream`` comes first on the path, so a worktree of an older commit runs
its own code) samples the cloud through the library (``prism_stream.sample``, one read, nothing else changed)
in a child process, the revisions interleaved run by run. ``billion.measure`` samples the temporary folder's
bytes every 0.05 s (a compaction of a few million candidates lasts a second or more), the process tree's RSS
and the wall time; the run's own summary gives the spill (candidates written, the most held at once, left,
compactions) and its bytes. Medians over the runs; every run's output is checked to be the same bytes.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import statistics
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import billion  # noqa: E402

CHILD = """
import json, sys
import prism_stream
src, out, ratio, temp = sys.argv[1:5]
s = prism_stream.sample(src, out, ratio=float(ratio), temp_dir=temp, reads="one")
print(json.dumps({k: s.plan.get(k) for k in ("reads", "spill_points", "spill_points_peak", "spill_points_written",
                                             "spill_bytes", "spill_compactions")}))
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
    digests = set()
    for i in range(a.runs):
        for label, checkout in revs:
            shutil.rmtree(a.work, ignore_errors=True)
            temp = os.path.join(a.work, "tmp")
            os.makedirs(temp)
            out = os.path.join(a.work, "out.parquet")
            env = {**os.environ, "PYTHONPATH": os.path.abspath(checkout)}
            m = billion.measure([sys.executable, "-c", CHILD, a.cloud, out, str(a.ratio), temp], [temp],
                                lambda msg: print(msg, file=sys.stderr), interval=0.05, env=env)
            if m["returncode"]:
                return 1
            m["summary"] = json.loads(m.pop("stdout").strip().splitlines()[-1])
            with open(out, "rb") as f:
                digests.add(hashlib.sha256(f.read()).hexdigest())
            rows[label].append(m)
            print(f"{label} run {i + 1}: {m['wall_s']} s, temp peak {m['temp_peak_bytes'] / 2**20:.1f} MiB, "
                  f"RSS {m['peak_rss_mib']} MiB, {m['summary']}", file=sys.stderr, flush=True)
    # outputs carry provenance (the revision's version, a run time): same bytes within a revision at least
    summary = {"cloud": a.cloud, "ratio": a.ratio, "runs": a.runs, "distinct_outputs": len(digests), "revisions": {}}
    for label, checkout in revs:
        ms = rows[label]
        summary["revisions"][label] = {
            "checkout": checkout,
            "wall_s_median": statistics.median(m["wall_s"] for m in ms),
            "temp_peak_mib_median": round(statistics.median(m["temp_peak_bytes"] for m in ms) / 2**20, 1),
            "temp_peak_mib_max": round(max(m["temp_peak_bytes"] for m in ms) / 2**20, 1),
            "peak_rss_mib_median": statistics.median(m["peak_rss_mib"] for m in ms),
            "spill": ms[0]["summary"], "runs": ms}
    with open(a.json, "w") as f:
        json.dump(summary, f, indent=1)
    for label, r in summary["revisions"].items():
        print(f"{label:>8}: wall {r['wall_s_median']} s, temp peak {r['temp_peak_mib_median']} MiB "
              f"(max {r['temp_peak_mib_max']}), RSS {r['peak_rss_mib_median']} MiB, spill {r['spill']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
