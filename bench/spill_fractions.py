"""How much of each real cloud the one-read path spills (candidates / N), by ratio and mode.

    python bench/spill_fractions.py

Runs ``prism_stream.sample`` on every cloud in tests/data/real at ratio 0.01 and 0.05 (exact mode) and
0.01 (paper mode), and prints the summary's ``plan.spill_points`` over N.
"""

from __future__ import annotations

import glob
import os
import tempfile
import warnings
from pathlib import Path

from prism_stream import sample

REAL = Path(__file__).resolve().parent.parent / "tests" / "data" / "real"
RUNS = {"exact 0.01": dict(ratio=0.01), "exact 0.05": dict(ratio=0.05), "paper 0.01": dict(ratio=0.01, mode="paper")}


def main() -> None:
    warnings.simplefilter("ignore")
    print("| cloud | points | " + " | ".join(RUNS) + " |")
    print("| --- | --- | " + " | ".join("---" for _ in RUNS) + " |")
    for f in sorted(glob.glob(str(REAL / "*"))):
        cells, n = [], 0
        for kw in RUNS.values():
            with tempfile.TemporaryDirectory() as d:
                s = sample(f, os.path.join(d, "o.parquet"), **kw)
                n = s.points
                cells.append(f"{100 * s.plan['spill_points'] / s.points:.1f}%")
        print(f"| {os.path.basename(f)} | {n:,} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
