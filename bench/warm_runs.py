"""Runs in a warm process: what a run costs once the imports and the kernels are loaded.

    python bench/warm_runs.py data/autzen_trim.laz --repeats 9

What the suite's test workers, a Dask worker running unit after unit, and a batch of small files pay per run
(the command line pays the imports on top: bench/startup.py). The streaming path is forced
(PRISM_STREAM_MEMORY_POINTS=0), since small inputs are otherwise held in memory. Prints the median seconds
per run and where it goes (the one-read filter's standing rules, the histogram, pass two's write), and the
file the engine was imported from (to compare a revision checked out elsewhere through PYTHONPATH).
"""

from __future__ import annotations

import argparse
import collections
import functools
import os
import statistics
import sys
import tempfile
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("input")
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--ratio", type=float, default=0.01)
    args = ap.parse_args()
    os.environ["PRISM_STREAM_MEMORY_POINTS"] = "0"
    import prism_stream
    from prism_stream.core import candidates
    from prism_stream.engines import reads

    spent = collections.Counter()

    def timed(owner, name):
        real = getattr(owner, name)

        @functools.wraps(real)
        def wrapper(*a, **k):
            t = time.perf_counter()
            try:
                return real(*a, **k)
            finally:
                spent[f"{owner.__name__}.{name}"] += time.perf_counter() - t
        setattr(owner, name, wrapper)

    for name in ("standing_rules", "chunk"):
        timed(candidates.CandidateFilter, name)
    for name in ("scan", "histogram", "select", "write"):
        timed(reads.Spilled, name)
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "out.parquet")
        prism_stream.sample(args.input, out, ratio=args.ratio, overwrite=True)  # the warm-up
        spent.clear()
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            prism_stream.sample(args.input, out, ratio=args.ratio, overwrite=True)
            times.append(time.perf_counter() - t)
    print(f"engine: {os.path.dirname(prism_stream.__file__)}")
    print(f"{args.input}: median {statistics.median(times):.3f} s a run (min {min(times):.3f}, max {max(times):.3f}), "
          f"{args.repeats} runs")
    for name, s in spent.most_common():
        print(f"  {name}: {s / args.repeats:.3f} s a run")


if __name__ == "__main__":
    sys.exit(main())
