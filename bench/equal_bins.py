"""Issue 26's cloud: N points in B distinct random 24-bit colors of equal expected size, as Parquet.

    python bench/equal_bins.py bench/data/eq_52M_10k.parquet --points 52000000 --bins 10000
    python bench/equal_bins.py bench/data/eq_52M_10k_sorted.parquet --points 52000000 --bins 10000 --sorted

x/y/z float64, red/green/blue uint8, random order (``--sorted``: the colors in order of x, so each color's
points arrive together, one color after another). Written a row group at a time (memory: one group).
Then, for instance:

    prism-stream bench/data/eq_52M_10k.parquet /tmp/o.parquet --ratio 0.05 --json --overwrite
    # plan.spill_points against 2 T (1 + ln(N / T))
"""

from __future__ import annotations

import argparse

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

GROUP = 1_000_000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out")
    ap.add_argument("--points", type=int, required=True)
    ap.add_argument("--bins", type=int, required=True)
    ap.add_argument("--sorted", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    palette = rng.choice(1 << 24, size=a.bins, replace=False)
    schema = pa.schema([("x", pa.float64()), ("y", pa.float64()), ("z", pa.float64()), ("red", pa.uint8()),
                        ("green", pa.uint8()), ("blue", pa.uint8())])
    with pq.ParquetWriter(a.out, schema) as w:
        for start in range(0, a.points, GROUP):
            m = min(GROUP, a.points - start)
            if a.sorted:  # color b holds rows [b N / B, (b + 1) N / B)
                idx = (np.arange(start, start + m, dtype=np.int64) * a.bins) // a.points
                x = np.arange(start, start + m, dtype=np.float64) / a.points * 1000
            else:
                idx = rng.integers(0, a.bins, m)
                x = rng.uniform(0, 1000, m)
            c = palette[idx]
            w.write_table(pa.table({"x": x, "y": rng.uniform(0, 1000, m), "z": rng.uniform(0, 50, m),
                                    "red": (c >> 16).astype(np.uint8), "green": ((c >> 8) & 255).astype(np.uint8),
                                    "blue": (c & 255).astype(np.uint8)}, schema=schema), row_group_size=GROUP)


if __name__ == "__main__":
    main()
