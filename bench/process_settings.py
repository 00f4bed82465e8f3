"""What the command line's process settings save (cli/main.py, cli/options.py): the same run with each setting
as shipped and with the library default forced back, interleaved round by round.

    python bench/process_settings.py bench/data/pf7_10M.parquet --threads 1 --rounds 8
    python bench/process_settings.py bench/data/pf7_10M.parquet --threads 2 --rounds 8
    python bench/process_settings.py bench/data/pf7_10M.laz --threads 1 --rounds 4

The settings: ``MIMALLOC_ALLOW_THP=0`` (Arrow's allocator without transparent huge pages, at any thread count) and
``OPENBLAS_NUM_THREADS=1`` (no BLAS thread pool). A variant sets the variable to the library's own default,
which the command line keeps (it only fills in what is unset). Each run is ``prism-stream IN OUT --ratio 0.01
--quiet --overwrite --threads N`` in its own process under ``/usr/bin/time``: medians of wall, user + system
CPU and peak RSS, the checkout's bytecode written first (as bench/run.py does). CPU time is the steadier
measure on a shared machine.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile

VARIANTS = {
    "as shipped": {},
    "huge pages (MIMALLOC_ALLOW_THP=1)": {"MIMALLOC_ALLOW_THP": "1"},
    "BLAS pool (OPENBLAS_NUM_THREADS=cores)": {"OPENBLAS_NUM_THREADS": str(os.cpu_count() or 1)},
}


def once(src: str, out: str, threads: int, env: dict) -> tuple[float, float, float]:
    exe = shutil.which("prism-stream") or os.path.join(os.path.dirname(sys.executable), "prism-stream")
    run_env = {k: v for k, v in os.environ.items() if k not in ("MIMALLOC_ALLOW_THP", "OPENBLAS_NUM_THREADS")}
    run_env.update(env)
    done = subprocess.run(["/usr/bin/time", "-f", "%e %U %S %M", exe, src, out, "--ratio", "0.01", "--quiet",
                           "--overwrite", "--threads", str(threads)], capture_output=True, text=True, env=run_env)
    if done.returncode != 0:
        raise SystemExit(done.stderr)
    wall, user, system, rss = map(float, done.stderr.strip().splitlines()[-1].split())
    return wall, user + system, rss / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("input")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--only", nargs="*", help="variants to run (default: all)")
    args = ap.parse_args()
    variants = {k: v for k, v in VARIANTS.items() if not args.only or any(o in k for o in args.only)}
    from run import compile_bytecode  # bench/run.py's: the checkout's bytecode, as an installed package has it

    compile_bytecode()
    got: dict[str, list] = {k: [] for k in variants}
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "out.parquet")
        for r in range(args.rounds):
            for name, env in variants.items():
                got[name].append(once(args.input, out, args.threads, env))
    print(f"{args.input}, --threads {args.threads}, {args.rounds} rounds interleaved, {os.cpu_count()} cores")
    print("| variant | median wall s | min / max wall s | median CPU s | median peak RSS MiB |")
    print("| --- | --- | --- | --- | --- |")
    for name, runs in got.items():
        walls = [w for w, _, _ in runs]
        print(f"| {name} | {statistics.median(walls):.3f} | {min(walls):.2f} / {max(walls):.2f} | "
              f"{statistics.median(c for _, c, _ in runs):.3f} | {statistics.median(m for _, _, m in runs):.0f} |")


if __name__ == "__main__":
    main()
