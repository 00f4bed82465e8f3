"""Run the command line with temporary data damaged at a phase, in a process of its own (for the damages a
test's own process cannot make: as root, a folder made read-only stays writable to it; the tests start this
script with the capabilities that ignore permissions dropped).

    python tests/faultrun.py PHASE DAMAGE TEMP -- ARGS...

PHASE: "pass one" (the spill's third write), "compaction" (the same, and a compaction at every write after it,
which makes new files), "between" (the solve) or "pass two" (the outputs' writing);
DAMAGE: "read-only" (the run's work folder and its files made read-only); TEMP: the --temp-dir the run uses.
"""

from __future__ import annotations

import os
import stat
import sys


def read_only(temp: str) -> None:
    for name in os.listdir(temp):
        work = os.path.join(temp, name)
        for f in os.listdir(work):
            os.chmod(os.path.join(work, f), stat.S_IRUSR | stat.S_IRGRP)
        os.chmod(work, stat.S_IRUSR | stat.S_IXUSR)


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

    if phase in ("pass one", "compaction"):
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
