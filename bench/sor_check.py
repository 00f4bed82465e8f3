"""The streamed statistical outlier removal against the in-memory one on every real cloud (same mask?).

    python bench/sor_check.py [--tile-points 20000]

Prints, per cloud: points, whether the masks are equal, points removed, tiles, points redone against
every tile, and the seconds of each (in memory, streamed).
"""

from __future__ import annotations

import argparse
import glob
import tempfile
import time
from pathlib import Path

import numpy as np

from prism_stream.evaluate import Cloud
from prism_stream.evaluate.denoise import sor_keep, sor_keep_streamed

REAL = Path(__file__).resolve().parent.parent / "tests" / "data" / "real"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tile-points", type=int, default=20_000)
    a = ap.parse_args()
    for f in sorted(glob.glob(str(REAL / "*"))):
        with Cloud(f) as cloud:
            xyz = np.concatenate([c.xyz for c in cloud.chunks()])
            t = time.perf_counter()
            want = sor_keep(xyz, 100, 2.0)
            t1 = time.perf_counter() - t
            with tempfile.TemporaryDirectory() as tmp:
                t = time.perf_counter()
                got, info = sor_keep_streamed(cloud, tmp, 100, 2.0, tile_points=a.tile_points)
                t2 = time.perf_counter() - t
                same = bool(np.array_equal(np.asarray(got), want))
        print(f"{Path(f).name}: {len(xyz):,} points, same mask {same}, removed {int((~want).sum()):,}, "
              f"tiles {info['tiles']}, redone {info['redone_points']:,}, {t1:.2f} s in memory, {t2:.2f} s streamed")


if __name__ == "__main__":
    main()
