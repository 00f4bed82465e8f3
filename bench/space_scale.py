"""`sample --space`: wall time and peak RSS against the same run without it, at growing N.

    python bench/space_scale.py --runs 3 --json bench/out/space_scale.json \
        --case 10M:/tmp/x/e10m.parquet --case 100M:bench/data/b2p24/e01.parquet,bench/data/b2p24/e02.parquet

Each configuration runs ``--runs`` times in its own process (``/usr/bin/time -f '%e %M'``), round-robin; the
table gives medians. The configurations: ``--reads two`` without a share (the floor: the same reads less the
spatial one), and ``--space 0.8`` at each ``--ratio``.

``--dask local:2`` runs every configuration on that cluster instead, through ``bench/peak_by_process.py``:
the peak is then the driver's and the largest worker's, each its own process (``time``'s %M folds them).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

BIN = Path(sys.executable).with_name("prism-stream")
PEAKS = Path(__file__).with_name("peak_by_process.py")


def run_once(inputs: list[str], args: list[str], out: Path, dask: str | None = None) -> dict:
    run = [str(BIN), *inputs, str(out), "--overwrite", "--quiet", "--summary", str(out) + ".json", *args]
    if dask:
        cmd = [sys.executable, str(PEAKS), "--", *run, "--dask", dask]
    else:
        cmd = ["/usr/bin/time", "-f", "%e %M", *run]
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed: {p.stderr.strip()[-400:]}")
    summary = json.loads(Path(str(out) + ".json").read_text())
    got = {"space_s": summary["seconds"].get("space"), "kept": summary["kept"], "points": summary["points"]}
    if dask:
        peaks = json.loads(p.stdout)
        workers = [q["peak_mib"] for q in peaks["processes"] if q["role"] == "worker process"]
        driver = [q["peak_mib"] for q in peaks["processes"] if q["role"] == "driver"]
        return {**got, "wall_s": peaks["wall_s"], "peak_rss_mib": max(driver), "worker_peak_mib": max(workers)}
    wall, kb = p.stderr.strip().splitlines()[-1].split()
    return {**got, "wall_s": float(wall), "peak_rss_mib": int(kb) / 1024}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--case", action="append", required=True, metavar="LABEL:FILE[,FILE...]")
    ap.add_argument("--ratios", default="0.0025,0.005")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--json")
    ap.add_argument("--dask", metavar="ADDRESS", help="run every configuration with --dask ADDRESS (local:2)")
    a = ap.parse_args()
    ratios = [r.strip() for r in a.ratios.split(",") if r.strip()]
    rows = []
    with tempfile.TemporaryDirectory(prefix="space-scale-") as tmp:
        for case in a.case:
            label, files = case.split(":", 1)
            inputs = files.split(",")
            configs = [(f"--reads two, ratio {r}", ["--ratio", r, "--reads", "two"]) for r in ratios]
            configs += [(f"--space 0.8, ratio {r}", ["--ratio", r, "--space", "0.8"]) for r in ratios]
            got: dict = {name: [] for name, _ in configs}
            for i in range(a.runs):
                for name, args in configs:
                    got[name].append(run_once(inputs, args, Path(tmp) / "out.parquet", a.dask))
                    print(f"{label} {name} run {i + 1}: {got[name][-1]}", flush=True)
            for name, runs in got.items():
                rows.append({"case": label, "config": name, "runs": runs,
                             "wall_s": statistics.median(r["wall_s"] for r in runs),
                             "peak_rss_mib": statistics.median(r["peak_rss_mib"] for r in runs),
                             "space_s": statistics.median(r["space_s"] or 0 for r in runs),
                             **({"worker_peak_mib": statistics.median(r["worker_peak_mib"] for r in runs),
                                 "dask": a.dask} if a.dask else {}),
                             "points": runs[0]["points"], "kept": runs[0]["kept"]})
    worker = " worker MiB" if a.dask else ""
    print(f"\n{'case':<6} {'configuration':<26} {'N':>13} {'T':>9} {'wall s':>8} {'space s':>8} {'peak MiB':>9}"
          f"{worker}")
    for r in rows:
        print(f"{r['case']:<6} {r['config']:<26} {r['points']:>13,} {r['kept']:>9,} {r['wall_s']:>8.1f} "
              f"{r['space_s']:>8.1f} {r['peak_rss_mib']:>9.0f}"
              + (f" {r['worker_peak_mib']:>10.0f}" if a.dask else ""))
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
