"""The cost of PRISM ranks (`prism-stream rank`) beside one sampling run and one decode of the same file.

    python bench/make_data.py --sizes 20M 100M
    python bench/rank_bench.py --sizes 20M 100M --repeats 3

For each size and input (the LAZ PF7 tiling and its Parquet copy), every
method runs as its own process under ``/usr/bin/time -v``, round-robin,
``--repeats`` times; the table keeps the median wall and CPU time and the
largest peak RSS. Methods:

- floor: one full decode of the file (laspy, every layer; pyarrow ``iter_batches``);
- ``prism-stream IN OUT --ratio 0.1`` (one sampling run);
- ``prism-stream rank IN OUT --max-ratio 0.1`` (the same points, ranked: every
  ratio up to 0.1 in one file), and with ``--order rank`` (a progressive file);
- ``prism-stream rank IN OUT`` (every point ranked: DuckDB's sort above 16M points).

Writes bench/out/rank-<date>.json and adds its tables to bench/RESULTS_RANK.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import make_data  # noqa: E402
from run import INPUTS, PRISM, PY, TMP, new_run, round_robin, run_heading, save_run, warm  # noqa: E402

RATIO = 0.1


def methods(inp: str) -> list[dict]:
    out = TMP / f"rank_{inp}"
    floor = ([PY, str(HERE / "methods.py"), "laz-read", "{path}", "--layers", "all", "--threads", "1"]
             if inp == "pf7_laz" else
             [PY, str(HERE / "methods.py"), "parquet-read", "{path}", "--how", "batches", "--threads", "1"])
    common = ["--quiet", "--json", "--overwrite", "--threads", "1"]
    return [
        dict(key="floor", name="floor: one full decode (1 thread)", cmd=floor),
        dict(key="sample", name=f"prism-stream --ratio {RATIO}",
             cmd=[PRISM, "{path}", f"{out}_sample.parquet", "--ratio", str(RATIO), *common]),
        dict(key="rank_max", name=f"prism-stream rank --max-ratio {RATIO}",
             cmd=[PRISM, "rank", "{path}", f"{out}_max.parquet", "--max-ratio", str(RATIO), *common]),
        dict(key="rank_max_order", name=f"prism-stream rank --max-ratio {RATIO} --order rank",
             cmd=[PRISM, "rank", "{path}", f"{out}_max_order.parquet", "--max-ratio", str(RATIO), "--order", "rank",
                  *common]),
        dict(key="rank_all", name="prism-stream rank (every point)",
             cmd=[PRISM, "rank", "{path}", f"{out}_all.parquet", *common]),
    ]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", nargs="+", default=["20M", "100M"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--inputs", nargs="+", default=["pf7_laz", "parquet"])
    ap.add_argument("--skip", nargs="*", default=[], help="method keys to leave out, e.g. rank_all")
    a = ap.parse_args(argv)
    TMP.mkdir(parents=True, exist_ok=True)
    results = new_run(sizes={})
    for size in a.sizes:
        n = make_data.parse_size(size)
        paths = make_data.paths(n)
        results["sizes"][size] = {}
        for inp in a.inputs:
            path = str(paths[inp])
            warm(Path(path))
            ms = [m for m in methods(inp) if m["key"] not in a.skip]
            results["sizes"][size][inp] = round_robin(ms, path, a.repeats, f"{size} {inp}")
    save_run(results, "rank")
    render(results)
    return 0


def render(results: dict) -> None:
    path = HERE / "RESULTS_RANK.md"
    lines = run_heading(results, path, "PRISM ranks: cost beside one sampling run and one decode", "rank_bench.py")
    lines += ["Each method is its own process (`/usr/bin/time -v`), round-robin; median wall and CPU (user + system) "
             "seconds, largest peak RSS. The load column is the 1-minute load average at each run's start: on this "
             "2-core machine anything above 2 means other work shared the cores, and wall times are inflated; CPU "
             "times much less so.", ""]
    for size, inputs in results["sizes"].items():
        for inp, rows in inputs.items():
            floor = rows.get("floor", {})
            lines += [f"## {size} points, {INPUTS.get(inp, inp)}", "",
                      "| method | median wall s | median CPU s | CPU / floor | peak RSS MiB | kept | load |",
                      "| --- | --- | --- | --- | --- | --- | --- |"]
            for key, r in rows.items():
                cpu = r.get("cpu_median_s")
                ratio = f"{cpu / floor['cpu_median_s']:.2f}x" if cpu and floor.get("cpu_median_s") else "-"
                lines.append(f"| {r['name']} | {r['median_s']:.2f} | {cpu if cpu is None else f'{cpu:.2f}'} | "
                             f"{ratio} | {r['peak_rss_mib']:.0f} | {r.get('points_out') or '-'} | "
                             f"{', '.join(f'{x:.1f}' for x in r['load1'])} |")
            lines.append("")
    with open(path, "a") as f:  # each run adds its sections (bench/rankers.py too)
        f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
