"""Passes over the spill's index in the compactions of one simulator case, timed, with the counted cuts or without.

    python bench/compaction_passes.py after --case 1e9,10000,0.05,sorted --json /tmp/ab_after.json
    python bench/compaction_passes.py before --case 1e9,10000,0.05,sorted --json /tmp/ab_before.json

Runs ``bench/spill_sim.py`` (its arguments after the variant) with ``cutoffs.standing_cuts`` wrapped so that
every pass over the index (each ``feed``) is timed and printed (``PASS <finder> <seconds>``), and at the end the
run's time, the passes and the bytes it read (``/proc/self/io``). ``before`` sets ``cutoffs.EXACT_PASSES``
past any number of groups: every capped bin in exact heaps, a pass for each group, as before 7fd3e81.
Results: bench/RESULTS_SCALE.md.
"""
from __future__ import annotations

import os
import runpy
import sys
import time

from prism_stream.core import cutoffs


def main() -> None:
    variant = sys.argv[1]
    if variant not in ("before", "after"):
        raise SystemExit("usage: compaction_passes.py before|after SPILL_SIM_ARGS...")
    sys.argv = ["bench/spill_sim.py"] + sys.argv[2:]
    if variant == "before":
        cutoffs.EXACT_PASSES = 10**9  # never counted: a pass for each group of heaps, as before 7fd3e81
    passes = [0]
    real = cutoffs.standing_cuts

    def timed(rules, feed, words=cutoffs.STANDING_WORDS):
        def fed(finder):
            passes[0] += 1
            t0 = time.perf_counter()
            feed(finder)
            print(f"PASS {type(finder).__name__} {time.perf_counter() - t0:.2f} s", flush=True)
        return real(rules, fed, words)

    cutoffs.standing_cuts = timed  # the spill imports it from the module at each compaction
    t = time.perf_counter()
    try:
        runpy.run_path(os.path.join(os.path.dirname(os.path.abspath(__file__)), "spill_sim.py"), run_name="__main__")
    finally:
        io = dict(line.split(": ") for line in open("/proc/self/io").read().splitlines())
        print(f"{variant}: {time.perf_counter() - t:.1f} s, passes over the index in compactions {passes[0]}, "
              f"read {int(io['rchar']) / 1e9:.1f} GB", flush=True)


if __name__ == "__main__":
    main()
