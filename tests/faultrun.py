"""Run the command line with temporary data damaged at a phase, in a process of its own (for the damages a
test's own process cannot make: as root, a folder made read-only stays writable to it; the tests start this
script with the capabilities that ignore permissions dropped).

    python tests/faultrun.py PHASE DAMAGE TEMP -- ARGS...

PHASE: "pass one" (the spill's third write), "compaction" (the same, and a compaction at every write after it,
which makes new files), "between" (the solve) or "pass two" (the outputs' writing); on Dask "dask pass one"
(the second unit done), "dask cutoffs" or "dask pass two", TEMP the output's folder, FAULTRUN_DASK_UNIT
the units' points;
DAMAGE: "read-only" (the run's work folder and its files made read-only); TEMP: the --temp-dir the run uses.
"""

from __future__ import annotations

import os
import stat
import sys


def read_only(temp: str) -> None:
    """Every folder under ``temp`` and its files made read-only (deepest first)."""
    for root, dirs, files in os.walk(temp, topdown=False):
        for f in files:
            os.chmod(os.path.join(root, f), stat.S_IRUSR | stat.S_IRGRP)
        if root != temp:
            os.chmod(root, stat.S_IRUSR | stat.S_IXUSR)


def main() -> None:
    phase, damage, temp = sys.argv[1:4]
    args = sys.argv[sys.argv.index("--") + 1:]
    from prism_stream.engines import pipeline
    from prism_stream.run import spill as spill_mod
    from prism_stream_cli.main import run

    damages = {"read-only": read_only}

    def later(real, at=1):
        calls = [0]

        def wrapped(*a, **kw):
            calls[0] += 1
            if calls[0] == at:
                damages[damage](temp)
            return real(*a, **kw)
        return wrapped

    if phase.startswith("dask "):  # a Dask run's staging folder (TEMP: the output's folder), from the driver
        from prism_stream.engines.dask import driver

        unit, sample = int(os.environ.get("FAULTRUN_DASK_UNIT", "0")), driver.sample
        if unit:  # units of this many points (the command line has no option for it)
            driver.sample = lambda *a, **kw: sample(*a, **{**kw, "unit_size": unit})
        name = {"dask pass one": "_unit_done", "dask cutoffs": "select", "dask pass two": "write"}[phase]
        setattr(driver.OnCluster, name, later(getattr(driver.OnCluster, name), at=2 if "one" in phase else 1))
    elif phase in ("pass one", "compaction"):
        spill_mod.Spill.add = later(spill_mod.Spill.add, at=3)
        if phase == "compaction":  # a compaction after the damage: it writes new files in the folder
            spill_mod.Spill._due = lambda self, more: True
    elif phase == "between":
        pipeline.solve = later(pipeline.solve)
    else:
        pipeline.write_outputs = later(pipeline.write_outputs)
    run(args)


if __name__ == "__main__":
    main()
