"""A local `--space 0.8` run with the spatial scan on disk tracking a given number of cells (``spatial.CAP``),
to weigh the top scan's size (bench/RESULTS_SPACE.md, "On the cluster past the budget"):

    python bench/space_cap.py 0 0.1 bench/data/pf7_10M.parquet        # the default cells
    python bench/space_cap.py 16384 0.1 bench/data/pf7_10M.parquet

Arguments: cells (0: as the code has it), ratio, input. Prints the cells, the wall seconds of the call, the
run's own seconds by step, and a hash of the output's rows (the same for every number of cells). Peak RSS:
run it under ``/usr/bin/time -f %M``. Measured at 3cd2ca8's parent, where ``spatial.CAP`` was every target's.
"""

from __future__ import annotations

import hashlib
import sys
import tempfile
import time
from pathlib import Path

import pyarrow.parquet as pq

import prism_stream
from prism_stream.engines import spatial


def main() -> None:
    cells, ratio, path = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
    if cells:
        spatial.CAP = spatial.PAST_CAP = cells
    with tempfile.TemporaryDirectory(prefix="space-cap-") as tmp:
        out = Path(tmp) / "out.parquet"
        t0 = time.perf_counter()
        s = prism_stream.sample(path, str(out), ratio=ratio, space="0.8")
        wall = time.perf_counter() - t0
        table = pq.read_table(out)
        rows = hashlib.md5(b"".join(c.to_numpy().tobytes() for c in table.columns)).hexdigest()[:16]
    print(f"cells {cells or spatial.CAP} wall {wall:.2f} s seconds {s.seconds} rows {table.num_rows} hash {rows}")


if __name__ == "__main__":
    main()
