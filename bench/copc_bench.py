"""The cost of COPC output beside a plain LAZ output of the same run and one decode of the input.

    python bench/make_data.py --sizes 20M
    python bench/copc_bench.py --sizes 20M --ratios 0.01 0.1 --repeats 3

For each size and ratio, on the LAZ PF7 tiling, every method runs as its own
process under ``/usr/bin/time -v``, round-robin, ``--repeats`` times; the
table keeps the median wall and CPU time and the largest peak RSS:

- floor: one full decode of the input (laspy, every layer, 1 thread);
- ``prism-stream IN out.laz --ratio R`` (the sample as plain LAZ);
- ``prism-stream IN out.copc.laz --ratio R`` (the same sample as COPC).

Writes bench/out/copc-<date>.json and adds its tables to bench/RESULTS_COPC.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import make_data  # noqa: E402
from run import PRISM, PY, TMP, new_run, round_robin, run_heading, save_run, warm  # noqa: E402


def methods(ratio: float) -> list[dict]:
    out = TMP / "copc"
    common = ["--ratio", str(ratio), "--quiet", "--json", "--overwrite", "--threads", "1"]
    return [
        dict(key="floor", name="floor: one full decode (1 thread)",
             cmd=[PY, str(HERE / "methods.py"), "laz-read", "{path}", "--layers", "all", "--threads", "1"]),
        dict(key="laz", name=f"prism-stream IN out.laz --ratio {ratio}", cmd=[PRISM, "{path}", f"{out}.laz", *common]),
        dict(key="copc", name=f"prism-stream IN out.copc.laz --ratio {ratio}",
             cmd=[PRISM, "{path}", f"{out}.copc.laz", *common]),
    ]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", nargs="+", default=["20M"])
    ap.add_argument("--ratios", nargs="+", type=float, default=[0.01, 0.1])
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args(argv)
    TMP.mkdir(parents=True, exist_ok=True)
    results = new_run(runs={})
    for size in a.sizes:
        path = str(make_data.paths(make_data.parse_size(size))["pf7_laz"])
        warm(Path(path))
        for ratio in a.ratios:
            results["runs"][f"{size} points, ratio {ratio}"] = round_robin(methods(ratio), path, a.repeats,
                                                                           f"{size} {ratio}")
    save_run(results, "copc")
    render(results)
    return 0


def render(results: dict) -> None:
    path = HERE / "RESULTS_COPC.md"
    lines = run_heading(results, path, "COPC output: cost beside plain LAZ output and one decode", "copc_bench.py")
    lines += ["Input: the LAZ 1.4 PF7 tiling. Each method is its own process, "
              "round-robin; median wall and CPU seconds, largest peak RSS; load: the 1-minute load average at "
              "each run's start (above 2 on this 2-core machine, other work shared the cores).", ""]
    for title, rows in results["runs"].items():
        lines += [f"## {title}", "", "| method | median wall s | median CPU s | peak RSS MiB | kept | load |",
                  "| --- | --- | --- | --- | --- | --- |"]
        for r in rows.values():
            cpu = r.get("cpu_median_s")
            lines.append(f"| {r['name']} | {r['median_s']:.2f} | {'-' if cpu is None else f'{cpu:.2f}'} | "
                         f"{r['peak_rss_mib']:.0f} | {r.get('points_out') or '-'} | "
                         f"{', '.join(f'{x:.1f}' for x in r['load1'])} |")
        lines.append("")
    with open(path, "a") as f:
        f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
