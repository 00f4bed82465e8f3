"""How much two busy processes get done on this machine beside one: its usable parallelism.

    python bench/cores.py

Runs the same pure-Python integer loop in one process, then in two processes
at once, and prints the seconds of each and the throughput ratio (2 x single
time / parallel time; 2.0 on two free cores). A `--threads 2` speed-up above
that ratio is not to be expected from CPU-bound work.
"""

from __future__ import annotations

import subprocess
import sys
import time

LOOP = "import time; t = time.perf_counter(); x = 0\nfor i in range(30_000_000): x += i * i\nprint(time.perf_counter() - t)"


def run(n: int) -> list[float]:
    procs = [subprocess.Popen([sys.executable, "-c", LOOP], stdout=subprocess.PIPE, text=True) for _ in range(n)]
    return [float(p.communicate()[0]) for p in procs]


def main() -> None:
    single = min(run(1)[0] for _ in range(3))
    pairs = [max(run(2)) for _ in range(3)]
    pair = sorted(pairs)[1]
    print(f"one process: {single:.2f} s (best of 3); two at once: {pair:.2f} s (median of 3, the slower of each pair)")
    print(f"throughput of two processes over one: {2 * single / pair:.2f}x")


if __name__ == "__main__":
    main()
