"""Fixed costs: `--version`, `--help`, and the bundled 110,000-point cloud sampled end to end.

    python bench/startup.py                  # 7 runs of each, round-robin, separate processes
    python bench/startup.py --repeats 3

Each command runs as its own process under /usr/bin/time (peak RSS); the
median wall time is kept. The bundled cloud (data/autzen_trim.laz, ratio
0.01, Parquet out) runs three ways: the default (a small input is held in
memory and computed with numpy alone), the streaming one-read path
(``PRISM_STREAM_MEMORY_POINTS=0``), and reading twice. The floor is a
Python process that imports laspy and pyarrow, decodes the same file and
writes the same number of rows to Parquet. Results: bench/RESULTS_STARTUP.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from run import OUT, PRISM, PY, TMP, new_run, round_robin, run_heading, save_run  # noqa: E402

CLOUD = HERE.parent / "data" / "autzen_trim.laz"
FLOOR = ("import sys, laspy, pyarrow as pa, pyarrow.parquet as pq; las = laspy.read(sys.argv[1]); "
         "pq.write_table(pa.table({'x': las.x[:1100], 'red': las.red[:1100]}), sys.argv[2])")


def methods(out: str) -> list[dict]:
    sample = [PRISM, "{path}", out, "--ratio", "0.01", "--overwrite", "--json", "--quiet"]
    return [
        {"key": "version", "name": "`prism-stream --version`", "cmd": ["sh", "-c", f"{PRISM} --version > /dev/null"]},
        {"key": "help", "name": "`prism-stream --help`", "cmd": ["sh", "-c", f"{PRISM} --help > /dev/null"]},
        {"key": "memory", "name": "bundled cloud, default (held in memory, numpy alone)", "cmd": sample},
        {"key": "spill", "name": "bundled cloud, streaming one read (`PRISM_STREAM_MEMORY_POINTS=0`)",
         "cmd": ["env", "PRISM_STREAM_MEMORY_POINTS=0", *sample]},
        {"key": "two", "name": "bundled cloud, streaming two reads (`--reads two`)", "cmd": [*sample, "--reads", "two"]},
        {"key": "floor", "name": "floor: import laspy + pyarrow, decode the file, write 1,100 rows",
         "cmd": [PY, "-c", FLOOR, "{path}", out + ".floor.parquet"]},
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    TMP.mkdir(parents=True, exist_ok=True)
    ms = methods(str(TMP / "startup.parquet"))
    results = new_run(repeats=args.repeats, input=str(CLOUD.relative_to(HERE.parent)),
                      methods=round_robin(ms, str(CLOUD), args.repeats, "startup"))
    save_run(results, "startup")
    path = HERE / "RESULTS_STARTUP.md"
    lines = run_heading(results, path, "Fixed costs: start-up and the bundled cloud", "startup.py")
    lines += ["", f"Median of {args.repeats} runs each, round-robin, each its own process.", "",
              "| command | median s | min-max s | peak RSS MiB | inside the run (s) |", "| --- | --- | --- | --- | --- |"]
    for m in ms:
        r = results["methods"][m["key"]]
        inner = r.get("inner_median_s", {}).get("total")
        lines.append(f"| {r['name']} | {r['median_s']:.2f} | {r['min_s']:.2f}-{r['max_s']:.2f} | "
                     f"{r['peak_rss_mib']:.0f} | {'' if inner is None else f'{inner:.2f}'} |")
    text = "\n".join(lines) + "\n\n"
    with open(path, "a") as f:
        f.write(text)
    print(text)


if __name__ == "__main__":
    main()
