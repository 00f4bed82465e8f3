"""The spatial share's scan alone (``core/space.SpatialScan``), on coordinates already in memory: what the
spatial read costs beyond decoding.

    python bench/space_scan.py bench/data/b2p24/e01.parquet --points 40000000 --target 500000

Reads x, y, z of the first ``--points`` rows (pyarrow), draws rarities, then times ``add`` over chunks of
2^20 points and ``order``; prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import pyarrow.parquet as pq

from prism_stream.core import space
from prism_stream.core.kernels import priorities_of_np, seed_mix


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("parquet")
    ap.add_argument("--points", type=int, default=40_000_000)
    ap.add_argument("--target", type=int, default=500_000)
    a = ap.parse_args()
    pf = pq.ParquetFile(a.parquet)
    groups, n = [], 0
    for g in range(pf.metadata.num_row_groups):
        if n >= a.points:
            break
        groups.append(g)
        n += pf.metadata.row_group(g).num_rows
    table = pf.read_row_groups(groups, columns=["x", "y", "z"]).slice(0, a.points)
    xyz = np.column_stack([table.column(c).to_numpy() for c in "xyz"])
    n = len(xyz)
    rarity = np.random.default_rng(0).integers(1, 4096, n).astype(np.uint64)
    ids = np.arange(n, dtype=np.uint64)
    prio = priorities_of_np(ids, seed_mix(0))
    step = 1 << 20
    t0 = time.perf_counter()
    scan = space.SpatialScan(a.target)
    for s in range(0, n, step):
        scan.add(xyz[s:s + step], rarity[s:s + step], prio[s:s + step], ids[s:s + step])
    scan.settled()
    t1 = time.perf_counter()
    order = scan.order(0)
    t2 = time.perf_counter()
    print(json.dumps({"points": n, "target": a.target, "scan_s": round(t1 - t0, 2), "order_s": round(t2 - t1, 2),
                      "ns_per_point": round((t1 - t0) / n * 1e9), "cells": int(len(scan.state[0])),
                      "order": int(len(order))}))


if __name__ == "__main__":
    main()
