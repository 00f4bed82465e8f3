"""The peak RSS of each step of a run with a spatial share: a thread polls the process's RSS every 20 ms and
notes it under the step the run is in (the spatial read, the order on disk, PRISM's order, the merge, and
what follows each).

    python bench/space_steps.py bench/data/pf7_100M.parquet /tmp/o.parquet --ratio 0.1 --space 0.8 \
        --overwrite --quiet

prints ``{step: MiB}`` to stderr after the run (a step's name with ``+`` after it: what came after it).
"""

from __future__ import annotations

import sys
import threading
import time

import prism_stream.engines.spatial as spatial
import prism_stream.engines.spatial_disk as spatial_disk

step = ["start"]
peaks: dict = {}


def rss_mib() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) // 1024
    return 0


def poll() -> None:
    while True:
        r, s = rss_mib(), step[0]
        peaks[s] = max(peaks.get(s, 0), r)
        time.sleep(0.02)


def named(owner, name: str, label: str, after: str | None = None) -> None:
    f = getattr(owner, name)

    def g(*a, **k):
        prev = step[0]
        step[0] = label
        try:
            return f(*a, **k)
        finally:
            step[0] = after or prev + "+"

    setattr(owner, name, g)


def main() -> None:
    threading.Thread(target=poll, daemon=True).start()
    named(spatial, "prism_order", "prism_order")  # in memory (a target whose scan fits its budget)
    named(spatial.space, "merge", "merge")
    named(spatial.spatial_merge, "prism_order_file", "prism_order")  # on disk (a larger one)
    named(spatial.spatial_merge, "merge_files", "merge")
    named(spatial_disk.DiskScan, "order", "disk_order", after="after_order")
    named(spatial_disk.DiskScan, "add", "spatial_read", after="spatial_read")
    from prism_stream_cli.main import run

    sys.argv = ["prism-stream", *sys.argv[1:]]
    try:
        run()
    except SystemExit:
        pass
    print(peaks, file=sys.stderr)


if __name__ == "__main__":
    main()
