"""Issue 26's table: the 52M-point cloud of B equal random colors, random and sorted, through the command line.

    python bench/scale_table.py --json bench/out/scale_table.json          # every B, both orders, 3 options
    python bench/scale_table.py --bins 10000 --orders sorted --json /tmp/t.json

For each order and B it writes the cloud once (``bench/equal_bins.py``: x/y/z float64, uint8 colors, 1M-row
groups; ``--sorted``: each color's points together, one color after another), takes the input's histogram with
DuckDB, then runs ``prism-stream IN OUT --json`` with ``--ratio 0.01``, ``--ratio 0.05`` and ``--k 260``, each a
child process measured from outside (``billion.measure``: wall time, peak RSS of the process tree, peak bytes
under the temporary folder and beside the output), and checks each output with DuckDB (``billion.check``: rows =
T, every bin's count within [min(n_b, K), min(n_b, K + 1)], exactly E bins at K + 1). The spill columns come
from the run's own summary: the filter's candidates, the most the spill held at once, what pass two read.
A file is deleted once its runs are done (``--keep`` keeps them).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import billion  # noqa: E402

HERE = billion.HERE
OPTIONS = {"ratio 0.01": ["--ratio", "0.01"], "ratio 0.05": ["--ratio", "0.05"], "k 260": ["--k", "260"]}


def bound(n: int, t: int) -> float:
    return min(n, 2 * t * (1 + math.log(n / t))) if t else 0.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=52_000_000)
    ap.add_argument("--bins", type=int, nargs="+", default=[3_000, 8_000, 10_000, 50_000, 200_000])
    ap.add_argument("--orders", nargs="+", default=["random", "sorted"], choices=["random", "sorted"])
    ap.add_argument("--options", nargs="+", default=list(OPTIONS), choices=list(OPTIONS))
    ap.add_argument("--work", default=os.path.join(HERE, "data", "scale_work"))
    ap.add_argument("--keep", action="store_true", help="keep the generated clouds")
    ap.add_argument("--json", required=True)
    a = ap.parse_args()
    os.makedirs(a.work, exist_ok=True)
    tmp = os.path.join(a.work, "tmp")
    rows = []

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    for order in a.orders:
        for bins in a.bins:
            cloud = os.path.join(HERE, "data", f"eq_{a.points // 1_000_000}M_{bins}_{order}.parquet")
            if not os.path.exists(cloud):
                cmd = [sys.executable, os.path.join(HERE, "equal_bins.py"), cloud, "--points", str(a.points),
                       "--bins", str(bins)] + (["--sorted"] if order == "sorted" else [])
                subprocess.run(cmd, check=True)
            truth = billion.truth_histogram([cloud], "8", cloud + ".hist.json")
            for name in a.options:
                out = os.path.join(a.work, "out.parquet")
                shutil.rmtree(tmp, ignore_errors=True)
                os.makedirs(tmp)
                cmd = billion.CLI + [cloud, out, *OPTIONS[name], "--json", "--overwrite", "--temp-dir", tmp]
                r = billion.measure(cmd, [tmp, out], log)
                s = json.loads(r["stdout"][r["stdout"].index("{"):])
                p = s["plan"]
                t = s["kept"]
                row = {"order": order, "bins": bins, "option": name, "n": s["points"], "k": s["k"], "target": t,
                       "extra": s["extra"], "reads": p["reads"],
                       "candidates": p.get("spill_candidates", p.get("spill_points_written")),
                       "written": p.get("spill_points_written"),
                       "peak": p.get("spill_points_peak"), "left": p.get("spill_points"),
                       "compactions": p.get("spill_compactions"), "spill_bytes": p.get("spill_bytes"),
                       "bound": bound(s["points"], t), "wall_s": r["wall_s"], "peak_rss_mib": r["peak_rss_mib"],
                       "temp_peak_bytes": r["temp_peak_bytes"], "check": billion.check(out, s, truth)}
                rows.append(row)
                log(json.dumps({k: v for k, v in row.items()}))
                os.unlink(out)
            if not a.keep:
                os.unlink(cloud)
    with open(a.json, "w") as f:
        json.dump({"rows": rows}, f, indent=1)
    print(table(rows))
    return 0


def table(rows) -> str:
    lines = ["| order | B | option | K | T | candidates | held at most | / bound | left (pass two) | compactions | "
             "temp peak GiB | wall s | peak RSS MiB | check |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        c = r["check"]
        lines.append(f"| {r['order']} | {r['bins']:,} | `--{r['option']}` | {r['k']} | {r['target']:,} | "
                     f"{r['candidates']:,} | {r['peak']:,} | {r['peak'] / r['bound']:.2f} | {r['left']:,} | "
                     f"{r['compactions']} | {r['temp_peak_bytes'] / 2**30:.2f} | {r['wall_s']} | "
                     f"{r['peak_rss_mib']} | {'OK' if c['ok'] else 'FAILED'} ({c['bins_at_k1']} bins at K+1) |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
