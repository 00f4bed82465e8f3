"""What each Dask worker's store holds when the worker's RSS is at its largest, during a run.

    python bench/worker_store.py bench/data/b2p24/e01.parquet bench/data/b2p24/e02.parquet --ratio 0.05 \
        --reads one --out /tmp/store_out --temp-dir /tmp/t

Runs ``prism_stream.engines.dask.driver.sample`` on ``local:2`` and, every second, asks each worker for its
RSS, the keys in its store with the bytes of the numpy arrays each value holds (Dask's own ``sizeof`` counts
a dataclass such as a prior or a histogram as a few bytes), and the task it is running. Prints, per worker,
the snapshot at its largest RSS, the keys grouped by task name (``prism-prior``: the priors; ``prism-scans``:
the units' pass-one results; ``prism-hist`` and ``prism-hsum``: the running histogram's parts and folds).
"""

from __future__ import annotations

import argparse
import collections
import re
import threading
import time


def snapshot(dask_worker):
    import dataclasses
    import os

    import numpy as np
    import psutil

    def size(v, depth=0):
        if isinstance(v, np.ndarray):
            return v.nbytes
        if depth > 4:
            return 0
        if dataclasses.is_dataclass(v):
            return sum(size(getattr(v, f.name), depth + 1) for f in dataclasses.fields(v))
        if isinstance(v, (tuple, list)):
            return sum(size(x, depth + 1) for x in v)
        if isinstance(v, dict):
            return sum(size(x, depth + 1) for x in v.values())
        return 0

    store = {str(k): size(v) for k, v in list(dask_worker.data.items())}
    return psutil.Process(os.getpid()).memory_info().rss, store, [str(t) for t in dask_worker.state.executing]


def main() -> None:
    from prism_stream.engines.dask.driver import connect, sample

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("inputs", nargs="+")
    ap.add_argument("--ratio", type=float, required=True)
    ap.add_argument("--reads", default="one")
    ap.add_argument("--out", required=True)
    ap.add_argument("--temp-dir", required=True)
    a = ap.parse_args()
    with connect("local:2") as client:
        best: dict = {}
        done = threading.Event()

        def poll():
            while not done.is_set():
                try:
                    for w, (rss, store, running) in client.run(snapshot).items():
                        if rss > best.get(w, (0,))[0]:
                            best[w] = (rss, store, running, time.time())
                except Exception:  # a worker between tasks or shutting down: the next poll
                    pass
                done.wait(1.0)

        th = threading.Thread(target=poll, daemon=True)
        th.start()
        t0 = time.time()
        summary = sample(client, a.inputs, a.out, ratio=a.ratio, reads=a.reads, temp_dir=a.temp_dir)
        done.set()
        th.join()
    for w, (rss, store, running, t) in sorted(best.items()):
        groups, counts = collections.Counter(), collections.Counter()
        for k, n in store.items():
            g = re.sub(r"\d+$", "", re.sub(r"-[0-9a-f]{6,}.*", "", k.strip("()'\" ")).split(",")[0])
            groups[g] += n
            counts[g] += 1
        print(f"{w}: RSS {rss / 2**20:,.0f} MiB at {t - t0:.0f} s; store {sum(store.values()) / 2**20:,.0f} MiB; "
              f"running {running}")
        for g, n in groups.most_common(8):
            print(f"    {g}: {counts[g]} keys, {n / 2**20:,.0f} MiB")
    bound = summary.plan["dask"].get("temp", {}).get("spill_points_bound")
    print(f"spill points {summary.plan.get('spill_points')}, bound {bound}")


if __name__ == "__main__":
    main()
