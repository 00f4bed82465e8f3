"""Small measurements behind bench/PROFILE.md, each one command.

    python bench/probes.py mask FILE.laz           boolean mask against take, on laspy's structured records
    python bench/probes.py gil FILE.laz            does a lazrs read let another Python thread run?
    python bench/probes.py rss -- ARGS...          prism-stream ARGS, its RSS every 0.25 s (stderr)
    python bench/probes.py chunks -- ARGS...       prism-stream ARGS, seconds per 1M-point chunk of pass one, by tenth

Each prints what it measured; none changes the engine.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time

import numpy as np


def mask(path: str) -> None:
    import laspy

    with laspy.open(path) as r:
        a = r.read_points(1 << 20).array
    keep = np.random.default_rng(0).random(len(a)) < 0.07

    def best(f, n=20):
        ts = []
        for _ in range(n):
            t = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t)
        return 1e3 * float(np.median(ts))

    at = np.flatnonzero(keep)
    print(f"{len(a):,} records of {a.dtype.itemsize} bytes, {len(at):,} kept; median of 20, ms:")
    print(f"  a[bool mask]        {best(lambda: a[keep]):6.2f}")
    print(f"  a[indices]          {best(lambda: a[at]):6.2f}")
    print(f"  a.take(indices)     {best(lambda: a.take(np.flatnonzero(keep))):6.2f}  (flatnonzero included)")


def gil(path: str) -> None:
    import laspy

    def decode():
        with laspy.open(path, laz_backend=(laspy.LazBackend.Lazrs,)) as r:
            for i, _ in enumerate(r.chunk_iterator(1 << 20)):
                if i == 2:
                    break

    t = time.perf_counter()
    decode()
    alone = time.perf_counter() - t
    worker = threading.Thread(target=decode)
    t = time.perf_counter()
    worker.start()
    loops = 0
    while worker.is_alive():
        loops += 1
    beside = time.perf_counter() - t
    t = time.perf_counter()
    for _ in range(loops):
        pass
    free = time.perf_counter() - t
    print(f"3M points decoded alone in {alone:.2f} s, beside a Python loop in {beside:.2f} s; the loop ran "
          f"{loops:,} times meanwhile (alone it runs that many in {free:.3f} s)")


def _cli(args) -> None:
    from prism_stream_cli.main import run

    sys.argv = ["prism-stream", *args]
    try:
        run()
    except SystemExit:
        pass


def rss(args) -> None:
    t0 = time.perf_counter()

    def sample():
        while True:
            with open("/proc/self/status") as f:
                kb = next(int(line.split()[1]) for line in f if line.startswith("VmRSS"))
            print(f"[{time.perf_counter() - t0:6.2f} s {kb >> 10} MiB]", file=sys.stderr, flush=True)
            time.sleep(0.25)

    threading.Thread(target=sample, daemon=True).start()
    _cli(args)


def chunks(args) -> None:
    from prism_stream.core import candidates

    ends: list[float] = []
    real = candidates.CandidateFilter.chunk

    def timed(self, *a, **k):
        out = real(self, *a, **k)
        ends.append(time.perf_counter())
        return out

    candidates.CandidateFilter.chunk = timed
    _cli(args)
    if len(ends) > 3:
        step = max(1, (len(ends) - 2) // 10)
        rows = [(ends[min(i + step, len(ends) - 1)] - ends[i]) / (min(i + step, len(ends) - 1) - i)
                for i in range(2, len(ends) - 1, step)]
        print(f"seconds per chunk after the first two, by tenth of the file: {[round(r, 3) for r in rows]}",
              file=sys.stderr)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("probe", choices=("mask", "gil", "rss", "chunks"))
    ap.add_argument("rest", nargs=argparse.REMAINDER)
    a = ap.parse_args(argv)
    rest = a.rest[1:] if a.rest[:1] == ["--"] else a.rest
    if a.probe in ("mask", "gil"):
        {"mask": mask, "gil": gil}[a.probe](rest[0])
    else:
        {"rss": rss, "chunks": chunks}[a.probe](rest)
    return 0


if __name__ == "__main__":
    sys.exit(main())
