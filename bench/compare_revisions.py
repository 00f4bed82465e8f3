"""Two revisions of prism-stream on the same inputs, interleaved: did a change move the time or the memory?

    python bench/compare_revisions.py --base e8add11 --inputs bench/data/pf7_10M.laz bench/data/pf3_10M.laz \
        --repeats 3 --threads 1 2 --out bench/RESULTS_PIPELINE.md

``--extra '--space 0.8'`` passes more options to both revisions' runs.

The base revision is checked out in a temporary git worktree and run from it (its own ``prism_stream`` and
command line, through PYTHONPATH); the head is this checkout. Each (input, threads) runs one warm-up of
each revision (numba compiles the base's kernels into the worktree's cache there), then ``--repeats``
rounds of base and head in turn, so load that comes and goes falls on both. Reported: median wall
seconds, min / max, peak RSS (``/usr/bin/time``), and that both outputs hold the same bytes.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def run_once(pythonpath: str | None, args: list[str], cwd: str) -> tuple[float, int]:
    """(wall seconds, peak RSS KiB) of one run of the command line with ``args``, in ``cwd`` (not the
    checkout: ``python -c`` puts the working folder first on the path, which would import the head's
    ``prism_stream`` for the base)."""
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    env.setdefault("SOURCE_DATE_EPOCH", "1767225600")  # the same provenance time: comparable bytes
    cmd = ["/usr/bin/time", "-f", "%M", sys.executable, "-c", "from prism_stream_cli.main import run; run()", *args]
    t = time.perf_counter()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=cwd)
    wall = time.perf_counter() - t
    if done.returncode != 0:
        raise SystemExit(f"failed ({done.returncode}): {' '.join(args)}\n{done.stderr}")
    return wall, int(done.stderr.strip().splitlines()[-1])


def digest(path: str) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, help="the revision to compare against (a commit, a tag)")
    ap.add_argument("--inputs", nargs="+", required=True)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", nargs="+", type=int, default=[1])
    ap.add_argument("--ratio", default="0.01")
    ap.add_argument("--out", default=None, help="write the Markdown table here too")
    ap.add_argument("--extra", default="", help="more options for both runs, one string (e.g. '--space 0.8')")
    ap.add_argument("--aot", action="store_true", help="build the base's kernels ahead of time in its worktree first "
                    "(as `make aot` built the head's): without it a base that has the build loads numba instead")
    a = ap.parse_args()
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    if subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                      text=True).stdout.strip():
        head += " + uncommitted changes"  # the head is the working tree
    work = Path(tempfile.mkdtemp(prefix="prism-compare-"))
    tree, shim, outs, head_shim = work / "tree", work / "shim", work / "out", work / "shim_head"
    try:
        subprocess.run(["git", "worktree", "add", "--detach", str(tree), a.base], cwd=ROOT, check=True,
                       capture_output=True)
        shim.mkdir()
        outs.mkdir()
        (shim / "prism_stream").symlink_to(tree / "prism_stream")
        (shim / "prism_stream_cli").symlink_to(tree / "cli")
        # the head through the same kind of path as the base (not the editable install's finder). An A/A run
        # (--base HEAD, 7 rounds, the bundled cloud and a 110k-point Parquet) still measured the base's worktree
        # 0.07-0.09 s slower a run, either way: a difference of that size needs an A/A run beside it
        head_shim.mkdir()
        (head_shim / "prism_stream").symlink_to(ROOT / "prism_stream")
        (head_shim / "prism_stream_cli").symlink_to(ROOT / "cli")
        rows = []
        if a.aot:
            subprocess.run([sys.executable, "-m", "prism_stream.engines.warm", "--aot", "--if-stale"], check=True,
                           env={**os.environ, "PYTHONPATH": str(shim)}, cwd=str(work))
        for name, pp in (("base", str(shim)), ("head", str(head_shim))):  # each revision runs its own code
            where = subprocess.run([sys.executable, "-c", "import prism_stream; print(prism_stream.__file__)"],
                                   env={**os.environ, "PYTHONPATH": pp or ""}, cwd=str(work), capture_output=True,
                                   text=True).stdout.strip()
            want = tree if name == "base" else ROOT
            if not Path(where).resolve().is_relative_to(want.resolve()):
                raise SystemExit(f"the {name} run would import {where}, not the {name} revision's code")
        for path in a.inputs:
            for threads in a.threads:
                results = {}
                for name, pp in (("base", str(shim)), ("head", str(head_shim))):
                    out = str(outs / "out.parquet")  # one name: the command line is in the provenance
                    args = [str(Path(path).resolve()), out, "--ratio", a.ratio, "--quiet", "--overwrite", "--threads",
                            str(threads), *a.extra.split()]
                    run_once(pp, args, str(work))  # warm-up: the kernels load (or compile) for this revision
                    results[name] = {"args": args, "wall": [], "rss": [], "digest": digest(out)}
                for _ in range(a.repeats):
                    for name, pp in (("base", str(shim)), ("head", str(head_shim))):
                        wall, rss = run_once(pp, results[name]["args"], str(work))
                        results[name]["wall"].append(wall)
                        results[name]["rss"].append(rss)
                same = results["base"]["digest"] == results["head"]["digest"]
                for name in ("base", "head"):
                    r = results[name]
                    rows.append((Path(path).name, threads, f"{name} ({a.base if name == 'base' else head})",
                                 statistics.median(r["wall"]), min(r["wall"]), max(r["wall"]),
                                 max(r["rss"]) / 1024, same))
                print(f"{Path(path).name} threads {threads}: base {statistics.median(results['base']['wall']):.2f} s, "
                      f"head {statistics.median(results['head']['wall']):.2f} s, same bytes: {same}", file=sys.stderr)
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=ROOT, capture_output=True)
        shutil.rmtree(work, ignore_errors=True)
    lines = [f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
             f"load average at the end: {', '.join(f'{v:.2f}' for v in os.getloadavg())}.",
             f"Command: `python bench/compare_revisions.py --base {a.base} --inputs {' '.join(a.inputs)} "
             f"--repeats {a.repeats} --threads {' '.join(map(str, a.threads))} --ratio {a.ratio}"
             f"{' --aot' if a.aot else ''}{f' --extra {chr(39)}{a.extra}{chr(39)}' if a.extra else ''}`",
             "",
             "| input | threads | revision | median wall s | min / max s | peak RSS MiB | same output bytes |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {i} | {t} | {rev} | {med:.2f} | {lo:.2f} / {hi:.2f} | {rss:.0f} | {'yes' if same else 'NO'} |"
              for i, t, rev, med, lo, hi, rss, same in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        Path(a.out).write_text(text)


if __name__ == "__main__":
    main()
