"""What lazy imports save: the same checkout run as it is, and with every format's module (`--what formats`)
or pyarrow.compute (`--what compute`) imported first, as before the change that spared it, interleaved.

    python bench/import_cost.py data/autzen_trim.laz /tmp/in.parquet bench/data/pf7_10M.parquet --rounds 9
    python bench/import_cost.py --what compute /tmp/in.parquet bench/data/pf7_10M.parquet --rounds 9

Each run is ``python -P -c "...; from prism_stream_cli.main import run; run()" IN OUT --ratio 0.01 --threads 1``
in its own process under ``/usr/bin/time`` (wall, user + system CPU); the variants alternate round by round. One
checkout for both, so nothing but the imports differs (two worktrees differ by 0.07-0.09 s a run on their own:
bench/compare_revisions.py). Medians; CPU time is the steadier measure on a shared machine.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile

VARIANTS = {
    "formats": {
        "lazy (as shipped)": "pass",
        "eager (every format imported first)": "import prism_stream.formats as f; [f.READERS[k] for k in f.READERS]; "
                                               "[f.WRITERS[k] for k in f.WRITERS]",
    },
    # formats.arrow.rows_of: a batch's rows taken through numpy, so a Parquet run never loads pyarrow.compute
    "compute": {
        "as shipped": "pass",
        "pyarrow.compute imported first": "import pyarrow.compute",
    },
}


def once(setup: str, src: str, out: str) -> tuple[float, float]:
    code = f"{setup}; from prism_stream_cli.main import run; run()"
    done = subprocess.run(["/usr/bin/time", "-f", "%e %U %S", sys.executable, "-P", "-c", code, src, out, "--ratio",
                           "0.01", "--overwrite", "--quiet", "--threads", "1"], capture_output=True, text=True,
                          cwd=os.path.dirname(out))
    if done.returncode:
        raise SystemExit(done.stderr)
    wall, user, system = map(float, done.stderr.strip().splitlines()[-1].split())
    return wall, user + system


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("inputs", nargs="+")
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--what", choices=sorted(VARIANTS), default="formats", help="which imports to compare")
    a = ap.parse_args()
    variants = VARIANTS[a.what]
    print("| input | variant | median wall s | min / max s | median CPU s |")
    print("| --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as work:
        out = os.path.join(work, "out.parquet")
        for src in a.inputs:
            src = os.path.abspath(src)
            got: dict = {name: [] for name in variants}
            for name, setup in variants.items():
                once(setup, src, out)  # warm-up: the page cache, the kernels' files
            for _ in range(a.rounds):
                for name, setup in variants.items():
                    got[name].append(once(setup, src, out))
            for name, runs in got.items():
                walls = [w for w, _ in runs]
                print(f"| {os.path.basename(src)} | {name} | {statistics.median(walls):.2f} | "
                      f"{min(walls):.2f} / {max(walls):.2f} | {statistics.median(c for _, c in runs):.2f} |",
                      flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
