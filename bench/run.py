"""Speed and memory of prism-stream beside its floors and the alternatives.

    python bench/run.py                              # 10M, 20M, 100M points, 3 runs each
    python bench/run.py --sizes 1M --repeats 1       # a quick check
    python bench/run.py --render bench/out/results-....json   # re-render RESULTS.md only

For every size it builds the inputs (bench/make_data.py, idempotent), then
runs every method as its own subprocess under ``/usr/bin/time -v`` (peak RSS
per run; without it, a wrapper process reads getrusage(RUSAGE_CHILDREN)),
round-robin over the methods ``--repeats`` times, and keeps the median wall
time. Inputs are read once before timing, so runs see a warm page cache.
Results go to bench/out/results-<date>.json and bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import threading
import time
from importlib import metadata
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import make_data  # noqa: E402

OUT = HERE / "out"
ROOT = HERE.parent


def compile_bytecode() -> None:
    """The checkout's bytecode written first, as a pip install writes a wheel's: with PYTHONDONTWRITEBYTECODE set
    (some images set it) an editable checkout is compiled again by each run, 0.1 s of a 10M-point Parquet run
    (bench/PROFILE.md) that the floors, whose libraries are installed with their bytecode, do not pay."""
    import compileall

    for part in ("prism_stream", "cli"):
        compileall.compile_dir(str(ROOT / part), quiet=1)
TMP = OUT / "tmp"
PY = sys.executable
PRISM = str(Path(PY).parent / "prism-stream")
RATIO = 0.01
GNU_TIME = "/usr/bin/time"

INPUTS = {
    "pf7_laz": "LAZ, LAS 1.4 point format 7 (lion + IGN tiles; selective RGB decompression applies)",
    "pf3_laz": "LAZ, LAS 1.2 point format 3 (Autzen tiles; pass one decodes whole records)",
    "parquet": "Parquet, the pf7 points (11 columns, 1M-row groups, zstd)",
}


def methods(size: int, heavy_max: int, have_open3d: bool, voxel: float | None) -> list[dict]:
    """Every (input, method) of one size: name, the command, what it is compared with."""
    out = []
    m = lambda *a: [PY, str(HERE / "methods.py"), *a]  # noqa: E731
    for inp in ("pf7_laz", "pf3_laz"):
        for t in (1, 2):
            sfx = "" if t == 1 else f" --threads {t}"
            out += [
                dict(input=inp, name=f"floor: laspy read, RGB layer only{sfx}", key=f"floor_rgb_t{t}",
                     cmd=lambda p, t=t: m("laz-read", p, "--layers", "rgb", "--threads", str(t))),
                dict(input=inp, name=f"floor: laspy read, all layers{sfx}", key=f"floor_all_t{t}",
                     cmd=lambda p, t=t: m("laz-read", p, "--layers", "all", "--threads", str(t))),
                dict(input=inp, name=f"floor: lazrs whole-chunk decode from the chunk table{sfx}",
                     key=f"floor_chunks_t{t}", cmd=lambda p, t=t: m("laz-chunks", p, "--threads", str(t))),
                dict(input=inp, name=f"floor: decimation, laspy decode + write 1% as LAZ{sfx}",
                     key=f"floor_decimate_t{t}",
                     cmd=lambda p, t=t, inp=inp: m("laz-decimate", p, str(TMP / f"decimate_{inp}_t{t}.laz"),
                                                   "--ratio", str(RATIO), "--threads", str(t))),
                dict(input=inp, name=f"prism-stream LAZ -> Parquet{sfx}", key=f"prism_t{t}", floor=f"floor_all_t{t}",
                     cmd=lambda p, t=t, inp=inp: [PRISM, p, str(TMP / f"prism_{inp}_t{t}.parquet"), "--ratio",
                                                  str(RATIO), "--quiet", "--json", "--overwrite", "--threads", str(t)]),
                dict(input=inp, name=f"prism-stream LAZ -> Parquet, two reads (--reads two){sfx}", key=f"prism2_t{t}",
                     floor=f"floor_sum_t{t}",
                     cmd=lambda p, t=t, inp=inp: [PRISM, p, str(TMP / f"prism2_{inp}_t{t}.parquet"), "--ratio",
                                                  str(RATIO), "--quiet", "--json", "--overwrite", "--threads", str(t),
                                                  "--reads", "two"]),
            ]
    for t in (1, 2):
        sfx = "" if t == 1 else f" --threads {t}"
        out += [
            dict(input="parquet", name=f"floor: pyarrow iter_batches, all columns{sfx}", key=f"floor_batches_t{t}",
                 cmd=lambda p, t=t: m("parquet-read", p, "--how", "batches", "--threads", str(t))),
            dict(input="parquet", name=f"floor: pyarrow iter_batches per row group, all columns{sfx}",
                 key=f"floor_rowgroups_t{t}",
                 cmd=lambda p, t=t: m("parquet-read", p, "--how", "rowgroups", "--threads", str(t))),
            dict(input="parquet", name=f"floor: pyarrow read_table, all columns{sfx}", key=f"floor_table_t{t}",
                 cmd=lambda p, t=t: m("parquet-read", p, "--how", "table", "--threads", str(t))),
            dict(input="parquet", name=f"prism-stream Parquet -> Parquet{sfx}", key=f"prism_t{t}",
                 floor=f"floor_table_t{t}",
                 cmd=lambda p, t=t: [PRISM, p, str(TMP / f"prism_parquet_t{t}.parquet"), "--ratio", str(RATIO),
                                     "--quiet", "--json", "--overwrite", "--threads", str(t)]),
            dict(input="parquet", name=f"prism-stream Parquet -> Parquet, two reads (--reads two){sfx}",
                 key=f"prism2_t{t}", floor=f"floor_table_t{t}",
                 cmd=lambda p, t=t: [PRISM, p, str(TMP / f"prism2_parquet_t{t}.parquet"), "--ratio", str(RATIO),
                                     "--quiet", "--json", "--overwrite", "--threads", str(t), "--reads", "two"]),
        ]
    out.append(dict(input="parquet", name="DuckDB SQL (exact rule, window selection; DuckDB default threads)",
                    key="duckdb", floor="floor_table_t1",
                    cmd=lambda p: [PY, str(HERE / "duckdb_prism.py"), p, str(TMP / "duckdb.parquet"),
                                   "--ratio", str(RATIO)]))
    if size <= heavy_max:
        out.append(dict(input="parquet", name="in-memory numpy (authors' approach: sort by key, k* per bin)",
                        key="in_memory", floor="floor_table_t1",
                        cmd=lambda p: m("in-memory", p, str(TMP / "in_memory.parquet"), "--ratio", str(RATIO))))
        if have_open3d:
            out += [
                dict(input="parquet", name=f"Open3D voxel_down_sample (voxel {voxel:.4g})", key="o3d_voxel",
                     floor="floor_table_t1",
                     cmd=lambda p: m("open3d", p, "--how", "voxel", "--param", repr(voxel))),
                dict(input="parquet", name=f"Open3D random_down_sample ({RATIO})", key="o3d_random",
                     floor="floor_table_t1", cmd=lambda p: m("open3d", p, "--how", "random", "--param", str(RATIO))),
                dict(input="parquet", name=f"Open3D uniform_down_sample (every {round(1 / RATIO)})",
                     key="o3d_uniform", floor="floor_table_t1",
                     cmd=lambda p: m("open3d", p, "--how", "uniform", "--param", str(round(1 / RATIO)))),
            ]
    return out


def measure(cmd: list[str]) -> dict:
    """Run one subprocess; wall seconds, peak RSS (MiB) and its JSON stdout."""
    stats = TMP / "time.txt"
    if os.path.exists(GNU_TIME):
        full = [GNU_TIME, "-v", "-o", str(stats), *cmd]
    else:
        wrap = ("import resource,subprocess,sys; p=subprocess.run(sys.argv[1:]); "
                "u=resource.getrusage(resource.RUSAGE_CHILDREN); "
                "open(%r,'w').write('Maximum resident set size (kbytes): %%d\\nUser time (seconds): %%f\\n"
                "System time (seconds): %%f\\n' %% (u.ru_maxrss, u.ru_utime, u.ru_stime)); "
                "sys.exit(p.returncode)" % str(stats))
        full = [PY, "-c", wrap, *cmd]
    load = os.getloadavg()[0]
    t = time.perf_counter()
    proc = subprocess.Popen(full, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak = [0]
    done = threading.Event()
    poller = threading.Thread(target=_poll_tree, args=(proc.pid, peak, done), daemon=True)
    poller.start()
    out, err = proc.communicate()
    wall = time.perf_counter() - t
    done.set()
    poller.join()
    p = subprocess.CompletedProcess(full, proc.returncode, out, err)
    if p.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr.strip()[-2000:]}")
    text = stats.read_text()
    rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", text).group(1))
    cpu = [float(v) for v in re.findall(r"(?:User|System) time \(seconds\): ([\d.]+)", text)]
    try:
        report = json.loads(p.stdout.strip().splitlines()[-1]) if p.stdout.strip() else {}
    except json.JSONDecodeError:
        report = json.loads(p.stdout)
    return {"wall": wall, "cpu": sum(cpu) if len(cpu) == 2 else None, "rss_mib": rss_kb / 1024, "load1": load,
            "tree_pss_mib": peak[0] / 2**20 if peak[0] else None, "report": report}


def _pss(pid: int) -> int:
    """A process's proportional set size in bytes (shared pages split among their users), 0 if gone."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                if line.startswith("Pss:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def _poll_tree(root: int, peak: list, done: threading.Event) -> None:
    """The peak of the summed PSS of ``root`` and all its descendants (a run's decoder processes, shared
    memory counted once), polled every 0.1 s (Linux; nothing elsewhere)."""
    try:
        import psutil
    except ImportError:
        return
    while not done.is_set():
        try:
            procs = [psutil.Process(root)]
            procs += procs[0].children(recursive=True)
        except psutil.Error:
            return
        peak[0] = max(peak[0], sum(_pss(q.pid) for q in procs))
        done.wait(0.1)


def _slim(report: dict) -> dict:
    """What to keep of a method's own JSON (prism-stream's summary is long)."""
    keep = ("points", "points_in", "points_out", "kept", "bins", "k", "extra", "target", "seconds",
            "peak_rss_bytes", "selective", "color_shift", "inner_seconds", "rule")
    out = {k: report[k] for k in keep if k in report}
    if isinstance(report.get("plan"), dict):  # how prism-stream read its input (issue 14)
        out["reads"] = {k: report["plan"][k] for k in ("reads", "why", "spill_points", "spill_bytes")
                        if k in report["plan"]}
    return out


def warm(path: Path) -> None:
    with open(path, "rb") as f:
        while f.read(1 << 24):
            pass


def check_same(a: Path, b: Path) -> dict:
    """Do two Parquet outputs hold the same rows in the same order (column values; nullability aside)?"""
    import numpy as np
    import pyarrow.parquet as pq

    ta, tb = pq.read_table(a), pq.read_table(b)
    same = ta.num_rows == tb.num_rows and set(ta.schema.names) == set(tb.schema.names) and all(
        np.array_equal(ta[c].to_numpy(), tb[c].to_numpy()) for c in ta.schema.names)
    return {"rows_a": ta.num_rows, "rows_b": tb.num_rows, "identical_rows": bool(same)}


def summarize(runs: list[dict]) -> dict:
    walls = [r["wall"] for r in runs]
    rss = [r["rss_mib"] for r in runs]
    last = runs[-1]["report"]
    trees = [r.get("tree_pss_mib") for r in runs]
    out = {"runs": len(runs), "median_s": statistics.median(walls), "min_s": min(walls), "max_s": max(walls),
           "walls": [round(w, 3) for w in walls], "peak_rss_mib": max(rss),
           **({"tree_pss_mib": max(trees)} if all(v is not None for v in trees) else {}),
           "load1": [round(r["load1"], 2) for r in runs], "report": _slim(last)}
    cpus = [r.get("cpu") for r in runs]
    if all(c is not None for c in cpus):
        out["cpu_median_s"] = statistics.median(cpus)
        out["cpus"] = [round(c, 3) for c in cpus]
    out["points_out"] = last.get("kept", last.get("points_out"))
    if "seconds" in last:
        keys = last["seconds"].keys()
        out["inner_median_s"] = {k: round(statistics.median(r["report"]["seconds"].get(k, 0) for r in runs), 3)
                                 for k in keys}
    return out


def round_robin(ms: list[dict], path: str, repeats: int, label: str) -> dict:
    """Each method's command on ``path``, round-robin, ``repeats`` times: its summary, by method key."""
    runs = {m["key"]: [] for m in ms}
    for _ in range(repeats):
        for m in ms:
            r = measure([c.replace("{path}", path) for c in m["cmd"]])
            runs[m["key"]].append(r)
            print(f"{label} {m['key']}: {r['wall']:.2f} s, {r['rss_mib']:.0f} MiB, load {r['load1']:.1f}", flush=True)
    return {m["key"]: dict(name=m["name"], **summarize(runs[m["key"]])) for m in ms}


def new_run(**fields) -> dict:
    """A run's results: the machine, the date, the command line and ``fields``."""
    return {"machine": machine(), "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
            "argv": sys.argv, **fields}


def save_run(results: dict, prefix: str) -> None:
    """Keep one run's results as bench/out/<prefix>-<date>.json."""
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"{prefix}-{stamp}.json").write_text(json.dumps(results, indent=1))


def run_heading(results: dict, path: Path, title: str, script: str) -> list[str]:
    """The lines that open one run's section of a RESULTS file (its title first, when the file is new)."""
    m = results["machine"]
    lines = [] if path.exists() else [f"# {title}", ""]
    return lines + [f"### Run of {results['date']}", "",
                    f"Machine: {m.get('cpu')}, {m.get('cores')} cores, {m.get('ram_gib')} GiB; {m.get('os')}; engine "
                    f"{m.get('git')}. Command: `python bench/{script} {' '.join(results['argv'][1:])}` (after "
                    "`python bench/make_data.py`)."]


def machine() -> dict:
    cpu = "?"
    try:
        cpu = next(l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name"))
    except (OSError, StopIteration):
        pass
    mem = 0
    try:
        mem = int(next(l.split()[1] for l in open("/proc/meminfo") if l.startswith("MemTotal"))) * 1024
    except (OSError, StopIteration):
        pass
    osname = platform.platform()
    try:
        osname = next(l.split("=", 1)[1].strip().strip('"') for l in open("/etc/os-release")
                      if l.startswith("PRETTY_NAME")) + f" (kernel {platform.release()})"
    except (OSError, StopIteration):
        pass
    versions = {}
    for pkg in ("prism-stream", "numpy", "numba", "laspy", "lazrs", "pyarrow", "duckdb", "open3d"):
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            versions[pkg] = None
    git = subprocess.run(["git", "-C", str(HERE), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return {"cpu": cpu, "cores": os.cpu_count(), "ram_gib": round(mem / 2**30, 1), "os": osname,
            "python": platform.python_version(), "packages": versions, "git": git.stdout.strip(),
            "peak_rss_tool": "/usr/bin/time -v" if os.path.exists(GNU_TIME) else "getrusage(RUSAGE_CHILDREN) wrapper"}


def open3d_status() -> tuple[bool, str]:
    p = subprocess.run([PY, "-c", "import open3d; print(open3d.__version__)"], capture_output=True, text=True)
    if p.returncode == 0:
        return True, f"open3d {p.stdout.strip()}"
    return False, "open3d not importable: " + (p.stderr.strip().splitlines() or ["?"])[-1]


def _picked(m: dict, only, skip) -> bool:
    tag = f"{m['input']}:{m['key']}"
    return (not only or any(o in tag for o in only)) and not any(s in tag for s in skip or ())


def run_size(size: int, repeats: int, heavy_max: int, have_open3d: bool, only, skip, log, inputs=None) -> dict:
    files = make_data.build(size, log=log, inputs=inputs)
    shutil.rmtree(TMP, ignore_errors=True)  # no output of an earlier size may stand in for this one's
    TMP.mkdir(parents=True)
    voxel = None
    if have_open3d and size <= heavy_max:
        import methods as mth

        voxel = mth.voxel_size_for(size, int(RATIO * size + 0.5))
    todo = methods(size, heavy_max, have_open3d, voxel)
    todo = [m for m in todo if _picked(m, only, skip) and m["input"] in files]
    for f in files.values():
        warm(f)
    runs = {(m["input"], m["key"]): [] for m in todo}
    for r in range(repeats):
        for m in todo:
            res = measure(m["cmd"](str(files[m["input"]])))
            runs[(m["input"], m["key"])].append(res)
            log(f"  {make_data.size_label(size)} run {r + 1}/{repeats} {m['input']:8s} {m['name']}: "
                f"{res['wall']:.2f} s, {res['rss_mib']:.0f} MiB")
    rows = []
    for m in todo:
        s = summarize(runs[(m["input"], m["key"])])
        s.update({"input": m["input"], "key": m["key"], "name": m["name"], "floor_key": m.get("floor"),
                  "command": " ".join(m["cmd"](str(files[m["input"]]))).replace(str(HERE.parent) + "/", "")})
        rows.append(s)
    add_floor_sums(rows)
    checks = {}
    duck, pq1 = TMP / "duckdb.parquet", TMP / "prism_parquet_t1.parquet"
    if duck.exists() and pq1.exists() and any(r["key"] == "duckdb" for r in rows):
        checks["duckdb_vs_prism_parquet"] = check_same(duck, pq1)
    return {"size": size, "label": make_data.size_label(size), "voxel_size": voxel, "rows": rows,
            "files": {k: {"path": str(v.relative_to(HERE.parent)), "bytes": v.stat().st_size} for k, v in files.items()},
            "checks": checks}


def add_floor_sums(rows: list[dict]) -> None:
    """The LAZ floor of a two-pass run: RGB-only read + full read (medians, mins and maxes added)."""
    for inp in ("pf7_laz", "pf3_laz"):
        for t in (1, 2):
            a = next((r for r in rows if r["input"] == inp and r["key"] == f"floor_rgb_t{t}"), None)
            b = next((r for r in rows if r["input"] == inp and r["key"] == f"floor_all_t{t}"), None)
            name = "floor: RGB-only + all layers (sum)"
            if b and not a and inp == "pf3_laz":
                a, name = b, "floor: 2 x all layers (PF3 has no RGB-only read)"
            if not (a and b):
                continue
            i = rows.index(b) + 1
            rows.insert(i, {"input": inp, "key": f"floor_sum_t{t}", "runs": min(a["runs"], b["runs"]),
                            "name": name + ("" if t == 1 else f" --threads {t}"),
                            "median_s": a["median_s"] + b["median_s"], "min_s": a["min_s"] + b["min_s"],
                            "max_s": a["max_s"] + b["max_s"], "peak_rss_mib": max(a["peak_rss_mib"], b["peak_rss_mib"]),
                            **({"cpu_median_s": a["cpu_median_s"] + b["cpu_median_s"]}
                               if "cpu_median_s" in a and "cpu_median_s" in b else {}),
                            "points_out": None, "derived": True, "command": "(sum of the two rows above)"})


# ---------------------------------------------------------------- report


def _row(rows, inp, key):
    return next((r for r in rows if r["input"] == inp and r["key"] == key), None)


def _best(p: dict, f: dict) -> str:
    """The ratio of the fastest runs: on a shared machine, the least disturbed estimate."""
    out = f"; best runs {p['min_s'] / f['min_s']:.2f}x" if p["runs"] > 1 else ""
    if p.get("cpu_median_s") and f.get("cpu_median_s"):
        out += f"; CPU time {p['cpu_median_s'] / f['cpu_median_s']:.2f}x"
    return out


def _cpu_ratio(p: dict, f: dict, threads: int, limit: float):
    """The same target judged on CPU time, for single-thread runs (where CPU time tracks the work)."""
    if threads != 1 or not p.get("cpu_median_s") or not f.get("cpu_median_s"):
        return None
    return p["cpu_median_s"] / f["cpu_median_s"] <= limit


def _floor_target(target: str, p: dict, f: dict, threads: int, limit: float) -> dict:
    """A 'within ``limit`` x of the floor' target from prism-stream's row ``p`` and the floor's row ``f``."""
    x = p["median_s"] / f["median_s"]
    return {"target": target, "value": f"{x:.2f}x ({p['median_s']:.1f} s vs {f['median_s']:.1f} s)" + _best(p, f),
            "pass": x <= limit, "cpu_pass": _cpu_ratio(p, f, threads, limit)}


def targets(results: dict) -> list[dict]:
    """Issue 30's targets (14's, tightened), PASS/FAIL from the medians."""
    out = []
    sizes = results["sizes"]
    for s in sizes:
        rows = s["rows"]
        for inp in ("pf7_laz", "pf3_laz"):
            for t in (1, 2):
                p, f = _row(rows, inp, f"prism_t{t}"), _row(rows, inp, f"floor_all_t{t}")
                if p and f:
                    out.append(_floor_target(f"LAZ -> Parquet within 1.1x of ONE full laspy decode, {inp}, "
                                             f"{s['label']}, threads {t}", p, f, t, 1.1))
                f = _row(rows, inp, f"floor_decimate_t{t}")
                if p and f:
                    out.append(_floor_target(f"LAZ -> Parquet within 1.1x of the decimation floor, {inp}, "
                                             f"{s['label']}, threads {t}", p, f, t, 1.1))
                f = _row(rows, inp, f"floor_chunks_t{t}")
                if p and f:
                    out.append(dict(_floor_target(f"(no target) LAZ -> Parquet against lazrs's whole-chunk decode, "
                                                  f"{inp}, {s['label']}, threads {t}", p, f, t, 1.1), informative=True))
            p1, p2 = _row(rows, inp, "prism_t1"), _row(rows, inp, "prism_t2")
            if p1 and p2:
                x = p1["median_s"] / p2["median_s"]
                f1, f2 = _row(rows, inp, "floor_all_t1"), _row(rows, inp, "floor_all_t2")
                ceiling = (f"; a bare decode gains {f1['median_s'] / f2['median_s']:.2f}x from its second thread"
                           if f1 and f2 else "")
                out.append({"target": f"LAZ --threads 2 >= 1.6x faster than --threads 1, {inp}, {s['label']}",
                            "value": f"{x:.2f}x ({p1['median_s']:.1f} s vs {p2['median_s']:.1f} s){ceiling}",
                            "pass": x >= 1.6})
        for t in (1, 2):
            p, f = _row(rows, "parquet", f"prism_t{t}"), _row(rows, "parquet", f"floor_table_t{t}")
            if p and f:
                out.append(_floor_target(f"Parquet -> Parquet within 1.2x of one pyarrow read_table, {s['label']}, "
                                         f"threads {t}", p, f, t, 1.2))
            d = _row(rows, "parquet", "duckdb")
            if p and d:
                x = d["median_s"] / p["median_s"]
                out.append({"target": f"Parquet -> Parquet >= 3x faster than the DuckDB SQL, {s['label']}, threads {t}",
                            "value": f"{x:.2f}x ({p['median_s']:.1f} s vs DuckDB {d['median_s']:.1f} s)"
                                     + (f"; best runs {d['min_s'] / p['min_s']:.2f}x" if p["runs"] > 1 else ""),
                            "pass": x >= 3.0})
    by = {s["size"]: s for s in sizes}
    big = max(by) if by else None
    for s in sizes:
        if s["size"] < 100_000_000:
            continue
        for r in s["rows"]:
            if not r["key"].startswith("prism"):
                continue
            out.append({"target": f"peak RSS under 1 GiB at {s['label']}: {r['input']} {r['name']}",
                        "value": f"{r['peak_rss_mib']:.0f} MiB", "pass": r["peak_rss_mib"] < 1024})
            if r.get("tree_pss_mib"):
                out.append({"target": f"all processes' memory (summed PSS) under 1 GiB at {s['label']}: {r['input']} "
                                      f"{r['name']}", "value": f"{r['tree_pss_mib']:.0f} MiB",
                            "pass": r["tree_pss_mib"] < 1024})
            small = by.get(10_000_000)
            if small:
                q = _row(small["rows"], r["input"], r["key"])
                if q:
                    x = r["peak_rss_mib"] / q["peak_rss_mib"]
                    out.append({"target": f"peak RSS flat from 10M to {s['label']} (within 15%): {r['input']} "
                                          f"{r['name']}",
                                "value": f"{r['peak_rss_mib']:.0f} vs {q['peak_rss_mib']:.0f} MiB ({x:.2f}x)",
                                "pass": x <= 1.15})
    if big is not None and big < 100_000_000:
        out.append({"target": "peak RSS at 100M points", "value": "not measured (no 100M run)", "pass": None})
    return out


def render(results: dict) -> str:
    m = results["machine"]
    L = ["# prism-stream benchmark", ""]
    if results.get("note"):
        L += [f"> **{results['note']}**", ""]
    L += [f"Run {results['started']} to {results['finished']} (git {m['git']}), ratio {RATIO}, seed 0, exact rule, "
          f"sizes {', '.join(s['label'] for s in results['sizes'])}; "
          + (f"median of {results['repeats']} run(s) per method"
             + (f" ({results['large_repeats']} at 100M points and above)"
                if results.get("large_repeats") != results["repeats"] else "")
             if results.get("repeats") else "median of the runs given in each table's runs column")
          + ", each a separate process, methods interleaved round-robin, warm page cache.", ""]
    L += ["## Machine", "",
          f"- CPU: {m['cpu']}, {m['cores']} cores; RAM {m['ram_gib']} GiB; {m['os']}",
          f"- Python {m['python']}; " + ", ".join(f"{k} {v}" for k, v in m["packages"].items()),
          f"- Peak RSS from {m['peak_rss_tool']} (the largest single process); all processes: the peak of the "
          "summed PSS of the run's process tree, polled every 0.1 s (decoder processes and their shared memory "
          "counted once); wall time from the parent (process start to exit, imports included).",
          f"- {results['open3d']}", ""]
    L += ["## Targets", "", "PASS/FAIL compares median wall times; 'best runs' is the ratio of the fastest runs "
          "(less disturbed by other jobs on a shared machine); for single-thread runs the same target is also judged "
          "on CPU time (user + system), which other jobs disturb much less than wall time. A wall ratio below 1 "
          "(prism-stream faster than the bare reads it contains) is contention, not speed.", "",
          "| target | measured | result |", "| --- | --- | --- |"]
    for t in targets(results):
        res = "n/a" if t["pass"] is None else ("PASS" if t["pass"] else "FAIL")
        if t.get("informative"):
            res = "(information)"
        if t.get("cpu_pass") is not None:
            res += f" (CPU time: {'PASS' if t['cpu_pass'] else 'FAIL'})"
        L.append(f"| {t['target']} | {t['value']} | {res} |")
    L.append("")
    for s in results["sizes"]:
        loads = [v for r in s["rows"] for v in r.get("load1", [])]
        L += [f"## {s['label']} points", ""]
        if loads:
            L += [f"1-minute load average at the start of each run: {min(loads):.1f} to {max(loads):.1f} "
                  f"(on {m['cores']} cores).", ""]
        for inp, what in INPUTS.items():
            rows = [r for r in s["rows"] if r["input"] == inp]
            if not rows:
                continue
            f = s["files"][inp]
            L += [f"### {what}", "", f"`{f['path']}`, {f['bytes'] / 2**20:,.0f} MiB", "",
                  "| method | runs | median wall s | min / max s | median CPU s | peak RSS MiB | all processes MiB "
                  "| points out | x of floor | own timings (median s) |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
            for r in rows:
                fl = _row(s["rows"], inp, r.get("floor_key")) if r.get("floor_key") else None
                x = f"{r['median_s'] / fl['median_s']:.2f}" if fl else ""
                own = ", ".join(f"{k} {v}" for k, v in (r.get("inner_median_s") or {}).items())
                pts = f"{r['points_out']:,}" if r.get("points_out") is not None else ""
                cpu = f"{r['cpu_median_s']:.2f}" if "cpu_median_s" in r else ""
                tree = f"{r['tree_pss_mib']:.0f}" if r.get("tree_pss_mib") else ""
                L.append(f"| {r['name']} | {r['runs']} | {r['median_s']:.2f} | {r['min_s']:.2f} / {r['max_s']:.2f} | "
                         f"{cpu} | {r['peak_rss_mib']:.0f} | {tree} | {pts} | {x} | {own} |")
            L.append("")
        for name, c in s.get("checks", {}).items():
            L.append(f"- check {name}: {c['rows_a']:,} vs {c['rows_b']:,} rows, identical rows and order: "
                     f"{'yes' if c['identical_rows'] else 'NO'}")
        if s.get("voxel_size"):
            L.append(f"- Open3D voxel size {s['voxel_size']:.4g} was estimated from the source tiles to give about "
                     f"{RATIO:.0%} of the points.")
        L.append("")
    argv = re.sub(r" --(note|results-md) .*?(?= --|`|$)", "", results["argv"])
    L += ["## Commands", "", "Inputs: `python bench/make_data.py --sizes " +
          " ".join(s["label"] for s in results["sizes"]) + "`; the run(s): `" + argv + "`.", "",
          "Per method (first size shown; `{IN}` is the input of the row):", ""]
    if results["sizes"]:
        s0 = results["sizes"][0]
        seen = set()
        for r in s0["rows"]:
            if r.get("derived"):
                continue
            cmd = r["command"].replace(s0["files"][r["input"]]["path"], "{IN}")
            cmd = cmd.replace(PY, "python").replace(PRISM, "prism-stream")
            cmd = re.sub(r"\S*\.venv/bin/", "", cmd)
            if (r["input"], cmd) not in seen:
                seen.add((r["input"], cmd))
                L.append(f"- {r['input']}, {r['name']}: `{cmd}`")
    L += ["", "## Notes", ""] + [f"- {n}" for n in results.get("notes", [])]
    L += ["", "## The other engines", "",
          "- DuckDB: the `prism_sample` macro and the `sql` command against the streaming engine, 20M and 100M "
          "points: [RESULTS_DUCKDB.md](RESULTS_DUCKDB.md) (`python bench/duckdb_bench.py`).",
          "- Dask: 1 and 2 workers against the local engine, time and peak RSS per worker: "
          "[RESULTS_DASK.md](RESULTS_DASK.md) (`python bench/dask_bench.py`).",
          "- Where the time and memory go, per pass: [PROFILE.md](PROFILE.md).",
          "- One revision against another on the same inputs, interleaved, with the output bytes compared: "
          "[RESULTS_PIPELINE.md](RESULTS_PIPELINE.md) (`python bench/compare_revisions.py`)."]
    return "\n".join(L) + "\n"


NOTES = [
    "x of floor: the one-read LAZ rows against one bare full laspy decode at the same thread count (issue 14's "
    "target); the two-read LAZ rows (--reads two) against an RGB-only read plus a full read, the two decodes that "
    "path cannot avoid; Parquet rows against one pyarrow read_table of all columns at the same thread count (DuckDB, "
    "numpy and Open3D rows against the single-thread read_table).",
    "Two streaming Parquet floors, both with pre_buffer=False (as prism-stream reads since 5d23710): iter_batches "
    "over the whole file (the target's reference) and iter_batches one row group at a time. With pyarrow's default "
    "pre-buffering a whole-file iter_batches keeps about the file's size allocated (1.3 GB peak RSS at 100M rows).",
    "pf3 LAZ (LAS 1.2 PF3) has no layered compression: the 'RGB layer only' read decodes whole records, so its floor "
    "is two full reads.",
    "DuckDB computes the same sample as prism-stream (exact rule, SPEC splitmix64 in UHUGEINT arithmetic masked to "
    "64 bits, window selection); the check line under each size compares the two outputs row by row. DuckDB uses its "
    "default thread count (all cores); prism-stream rows say their thread count.",
    "The in-memory numpy row follows the authors' reference approach: load all points, sort by bin key, keep up to "
    "k* per bin, k* from the paper's integer rule; with many small bins k* = 1 and it keeps far more than 1% "
    "(see points out): that is the paper rule, not a bug of the benchmark. It keeps the first k* points of each bin "
    "in sort order rather than a random k*.",
    "Open3D rows load x, y, z and colors into an Open3D PointCloud and downsample; they write no output and do no "
    "color stratification: they are a reference for in-memory speed and memory, not the same answer.",
    "In-memory numpy and Open3D are run only up to --heavy-max points (they hold the whole cloud in memory).",
    "Open3D 0.20 wheels need the system library libusb-1.0 (Debian: apt-get install libusb-1.0-0); without it "
    "`import open3d` fails and run.py records that and skips the Open3D rows.",
    "CPU s is user + system time of the process (all its threads), from the same tool as the peak RSS: on a "
    "shared machine it is a steadier measure of the work done than wall time (but multi-threaded runs spend more "
    "CPU than wall).",
    "Wall times include process start-up (imports; for prism-stream also loading numba's cached kernels); the "
    "'own timings' column is what prism-stream / DuckDB / the numpy script report for their own stages.",
]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", nargs="+", default=["10M", "20M", "100M"])
    ap.add_argument("--repeats", type=int, default=3, help="runs per method (median reported)")
    ap.add_argument("--large-repeats", type=int, default=None, help="runs per method at 100M points and above "
                    "(default: --repeats)")
    ap.add_argument("--heavy-max", default="20M", help="largest size for the in-memory methods (numpy, Open3D)")
    ap.add_argument("--only", nargs="*", default=None, help="run only methods whose 'input:key' contains one of these "
                    "(e.g. parquet:duckdb, prism_t1)")
    ap.add_argument("--skip", nargs="*", default=None, help="skip methods whose 'input:key' contains one of these")
    ap.add_argument("--inputs", nargs="+", choices=list(INPUTS), default=None,
                    help="run (and build) only these inputs (default: all three)")
    ap.add_argument("--large-only", nargs="*", default=None, help="at 100M points and above, run only these methods")
    ap.add_argument("--note", default="", help="a note printed at the top of RESULTS.md")
    ap.add_argument("--results-md", default=str(HERE / "RESULTS.md"))
    ap.add_argument("--render", nargs="+", default=None, help="re-render RESULTS.md from these results JSON files "
                    "(their sizes merged, first file's machine) and exit")
    a = ap.parse_args(argv)
    if a.render:
        parts = [json.loads(Path(p).read_text()) for p in a.render]
        results = parts[0]
        by_size = {}
        for p in parts:  # a later file's rows replace an earlier one's (same size, input and method)
            for s in p["sizes"]:
                old = by_size.get(s["size"])
                if old is None:
                    by_size[s["size"]] = s
                    continue
                rows = {(r["input"], r["key"]): r for r in old["rows"] if not r.get("derived")}
                rows.update({(r["input"], r["key"]): r for r in s["rows"] if not r.get("derived")})
                old["rows"] = list(rows.values())
                old["files"].update(s["files"])
                old["checks"].update(s.get("checks", {}))
                old["voxel_size"] = s.get("voxel_size") or old.get("voxel_size")
        results["sizes"] = sorted(by_size.values(), key=lambda s: s["size"])
        order = [(m["input"], m["key"]) for m in methods(1, 1, True, 1.0)]
        for s in results["sizes"]:
            s["rows"].sort(key=lambda r: order.index((r["input"], r["key"])) if (r["input"], r["key"]) in order else 999)
        results["started"] = min(p["started"] for p in parts)
        results["finished"] = max(p.get("finished", p["started"]) for p in parts)
        if len(parts) > 1:
            results["argv"] = "`; `".join(p["argv"] for p in parts)
            results["repeats"] = None
        if a.note:
            results["note"] = a.note
        for s in results["sizes"]:
            s["rows"] = [r for r in s["rows"] if not r.get("derived")]
            add_floor_sums(s["rows"])
        Path(a.results_md).write_text(render(results))
        return 0
    OUT.mkdir(exist_ok=True)
    TMP.mkdir(exist_ok=True)
    compile_bytecode()
    have_o3d, o3d_msg = open3d_status()
    started = dt.datetime.now().isoformat(timespec="seconds")
    results = {"started": started, "argv": "python bench/run.py " + " ".join(argv if argv is not None else sys.argv[1:]),
               "repeats": a.repeats, "large_repeats": a.large_repeats or a.repeats, "note": a.note,
               "machine": machine(), "open3d": o3d_msg, "sizes": [], "notes": NOTES}
    stamp = started.replace(":", "-")
    path = OUT / f"results-{stamp}.json"

    def log(msg):
        print(msg, flush=True)

    for label in a.sizes:
        size = make_data.parse_size(label)
        large = size >= 100_000_000
        reps = (a.large_repeats or a.repeats) if large else a.repeats
        only = a.large_only if large and a.large_only else a.only
        results["sizes"].append(run_size(size, reps, make_data.parse_size(a.heavy_max), have_o3d, only, a.skip, log,
                                         a.inputs))
        results["sizes"].sort(key=lambda s: s["size"])
        results["finished"] = dt.datetime.now().isoformat(timespec="seconds")
        path.write_text(json.dumps(results, indent=1))
        Path(a.results_md).write_text(render(results))
    shutil.rmtree(TMP, ignore_errors=True)
    log(f"results: {path} and {a.results_md}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
