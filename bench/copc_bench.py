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
import datetime as dt
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import make_data  # noqa: E402
from run import OUT, PRISM, PY, TMP, machine, measure, summarize, warm  # noqa: E402


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
    results = {"machine": machine(), "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
               "argv": sys.argv, "runs": {}}
    for size in a.sizes:
        path = str(make_data.paths(make_data.parse_size(size))["pf7_laz"])
        warm(Path(path))
        for ratio in a.ratios:
            ms = methods(ratio)
            runs = {m["key"]: [] for m in ms}
            for _ in range(a.repeats):
                for m in ms:
                    r = measure([c.replace("{path}", path) for c in m["cmd"]])
                    runs[m["key"]].append(r)
                    print(f"{size} {ratio} {m['key']}: {r['wall']:.2f} s, {r['rss_mib']:.0f} MiB, "
                          f"load {r['load1']:.1f}", flush=True)
            results["runs"][f"{size} points, ratio {ratio}"] = {
                m["key"]: dict(name=m["name"], **summarize(runs[m["key"]])) for m in ms}
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"copc-{stamp}.json").write_text(json.dumps(results, indent=1))
    render(results)
    return 0


def render(results: dict) -> None:
    m = results["machine"]
    path = HERE / "RESULTS_COPC.md"
    lines = [] if path.exists() else ["# COPC output: cost beside plain LAZ output and one decode", ""]
    lines += [f"### Run of {results['date']}", "",
              f"Machine: {m.get('cpu')}, {m.get('cores')} cores, {m.get('ram_gib')} GiB; {m.get('os')}; engine "
              f"{m.get('git')}. Command: `python bench/copc_bench.py {' '.join(results['argv'][1:])}` (after "
              "`python bench/make_data.py`). Input: the LAZ 1.4 PF7 tiling. Each method is its own process, "
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
