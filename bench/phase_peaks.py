"""Each process's peak RSS in each phase of a run, from ``peak_by_process.py --timeline``.

    python bench/peak_by_process.py --timeline /tmp/tl.csv -- python -m prism_stream a.parquet b.parquet \
        out.parquet --ratio 0.05 --json --dask local:2 > /tmp/run.out
    python bench/phase_peaks.py /tmp/run.out /tmp/tl.csv

``run.out`` holds the run's ``--json`` summary followed by peak_by_process's JSON. The phases (the summary's
``seconds``: scan, solve, cutoffs, select, commit) are placed back from the end of the timeline, so a poll
belongs to the phase the run was in within a poll's interval (0.1 s); "startup" is before pass one
(imports, the cluster's start), "end" after the commit (the summary, the cluster's shutdown).
"""

from __future__ import annotations

import collections
import csv
import json
import sys

PHASES = ["scan", "solve", "cutoffs", "select", "commit"]


def main(run_out: str, timeline: str, smallest_mib: float = 200) -> None:
    text = open(run_out).read()
    decoder = json.JSONDecoder()
    run, at = decoder.raw_decode(text)
    peaks, _ = decoder.raw_decode(text[at:].lstrip())
    seconds = run["seconds"]
    rows = list(csv.DictReader(open(timeline)))
    end = max(float(r["seconds"]) for r in rows)
    start = t = end - seconds["total"]
    spans = []
    for phase in PHASES:
        spans.append((phase, t, t + seconds.get(phase, 0.0)))
        t += seconds.get(phase, 0.0)
    roles = {p["pid"]: p["role"][:20] for p in peaks["processes"]}
    table: dict = collections.defaultdict(dict)
    for r in rows:
        t, pid, rss = float(r["seconds"]), int(r["pid"]), float(r["rss_mib"])
        phase = "startup" if t < start else next((p for p, a, b in spans if a <= t < b), "end")
        table[pid][phase] = max(table[pid].get(phase, 0.0), rss)
    columns = ["startup", *PHASES, "end"]
    print(f"wall {peaks['wall_s']} s; phases (s): " + ", ".join(f"{p} {seconds.get(p, 0):.1f}" for p in PHASES))
    print(f"{'pid':>8} {'role':20} " + " ".join(f"{c:>8}" for c in columns))
    for pid, by in sorted(table.items(), key=lambda kv: -max(kv[1].values())):
        if max(by.values()) >= smallest_mib:
            print(f"{pid:>8} {roles.get(pid, '?'):20} " + " ".join(f"{by.get(c, 0):>8.0f}" for c in columns))


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
