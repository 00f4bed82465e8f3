"""prism-stream's `--preset authors` beside the authors' released PRISM.py, on the same clouds.

The authors' script (SUNY-MEC-MEIC-Lab/PRISM, PRISM.py) is unseeded, so rows
cannot be compared; what is compared is what a reader of its output sees:
points kept (ratio), how they spread over the strata (per-bin counts), the
color entropy, outlier removal, time and peak memory. Nothing is fetched:
give the path of a local copy of PRISM.py.

    python bench/authors_compare.py --prism-py /path/to/PRISM.py \
        tests/data/real/* --k 1 --out docs/eval/authors_compare.md

Each cloud is first written to a float-color PLY (Open3D reads only what
its readers know; PRISM.py takes PLY), which both sides then read. PRISM.py
runs in a subprocess (`python PRISM.py -i in.ply -o out.ply -k K -q Q`),
timed with its peak RSS from the kernel (getrusage of the child). Needs
open3d (the `bench` extra).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from prism_stream.core.bins import BinSpec
from prism_stream.evaluate import Cloud
from prism_stream.evaluate.cloud import RGB8
from prism_stream.evaluate.denoise import sor_keep
from prism_stream.evaluate.metrics import entropy_bits


def to_ply(src: str, dest: str) -> int:
    """The cloud as a binary PLY with double xyz and float colors in [0, 1] (v / 255), as Open3D writes."""
    import open3d as o3d

    with Cloud(src) as cloud:
        xyz, keys = [], []
        for c in cloud.chunks():
            xyz.append(c.xyz)
            keys.append(cloud.keys_of(c.ordinal, c.raw.rgb))
    xyz = np.concatenate(xyz)
    rgb = np.column_stack(RGB8.channels(np.concatenate(keys))).astype(np.float64) / 255.0
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    pcd.colors = o3d.utility.Vector3dVector(rgb)
    o3d.io.write_point_cloud(dest, pcd, write_ascii=False)
    return len(xyz)


def read_ply(path: str):
    import open3d as o3d

    pcd = o3d.io.read_point_cloud(path)
    xyz = np.asarray(pcd.points)
    rgb8 = np.round(np.asarray(pcd.colors) * 255.0).astype(np.int64)
    return xyz, rgb8


def authors_bins(rgb8: np.ndarray, chroma: bool, q: float) -> np.ndarray:
    """PRISM.py's own bins, as it computes them (float chromaticity with +1e-6, numpy round half to even)."""
    c = rgb8 / 255.0
    if chroma:
        c = c / (c.sum(axis=1, keepdims=True) + 1e-6)
    lv = (c * 255.0 / q).round().astype(np.int64)
    return (lv[:, 0] << 20) | (lv[:, 1] << 10) | lv[:, 2]


def our_bins(rgb8: np.ndarray, chroma: bool, q: float) -> np.ndarray:
    spec = BinSpec("chroma" if chroma else "rgb", 0, q)
    return spec.keys(rgb8[:, 0], rgb8[:, 1], rgb8[:, 2], 0).astype(np.int64)


def timed(cmd) -> tuple[str, float, float]:
    """Run a command; its stdout, wall seconds and its own peak RSS in MiB (wait4's rusage of that child)."""
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", _SHIM, *cmd], capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    lines = done.stderr.strip().splitlines()
    if done.returncode:
        raise SystemExit(f"{os.path.basename(cmd[1])} failed: {lines[-2:]}")
    return done.stdout, seconds, int(lines[-1]) / 1024


# the shim's only child is the command, so its children's peak RSS is the command's own
_SHIM = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); "
         "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); sys.exit(r.returncode)")


def run_authors(prism_py: str, ply: str, out: str, k: int, q: float, chroma: bool) -> dict:
    cmd = [sys.executable, prism_py, "-i", ply, "-o", out, "-k", str(k), "-q", str(q)]
    if not chroma:
        cmd.append("--no_chromaticity")
    stdout, seconds, peak = timed(cmd)
    return {"seconds": seconds, "peak_rss_mib": peak, "stdout": stdout.strip()}


def run_ours(ply: str, out: str, k: int, q: float, chroma: bool) -> dict:
    stdout, seconds, peak = timed([sys.executable, "-c", _OURS, ply, out, str(k), str(q),
                                   "chroma" if chroma else "rgb"])
    info = json.loads(stdout)
    info.update(seconds=seconds, peak_rss_mib=peak)
    return info


# the authors' pipeline in prism-stream: SOR(100, 2.0) in memory, then PRISM streamed with a fixed k
_OURS = """
import json, sys, numpy as np, prism_stream
from prism_stream.evaluate import Cloud
from prism_stream.evaluate.baselines import write_selection
from prism_stream.evaluate.denoise import sor_keep
ply, out, k, q, space = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4]), sys.argv[5]
with Cloud(ply) as cloud:
    xyz = np.concatenate([c.xyz for c in cloud.chunks()])
    keep = sor_keep(xyz, 100, 2.0)
    clean = out + '.clean.parquet'
    write_selection(cloud, clean, lambda c: keep[c.offset:c.offset + len(c)], {'denoise': 'sor:100,2'}, True)
s = prism_stream.sample(clean, out, k=k, color_space=space, quant_step=q, overwrite=True, threads=1)
print(json.dumps({'after_sor': int(keep.sum()), 'kept': int(s.kept), 'bins': int(s.bins)}))
"""


def compare(src: str, prism_py: str, k: int, q: float, chroma: bool, tmp: str) -> dict:
    name = os.path.basename(src)
    ply = os.path.join(tmp, name + ".ply")
    n = to_ply(src, ply)
    theirs_out = os.path.join(tmp, name + ".authors.ply")
    ours_out = os.path.join(tmp, name + ".ours.parquet")
    theirs = run_authors(prism_py, ply, theirs_out, k, q, chroma)
    ours = run_ours(ply, ours_out, k, q, chroma)
    xyz_in, rgb_in = read_ply(ply)
    sor = sor_keep(xyz_in, 100, 2.0)
    _, rgb_t = read_ply(theirs_out)
    import pyarrow.parquet as pq

    t = pq.read_table(ours_out)
    rgb_o = np.column_stack([np.floor(t[c].to_numpy() * 255.0).astype(np.int64) if t[c].type.id in (11, 12)
                             else t[c].to_numpy().astype(np.int64) for c in _color_cols(t)])
    clean = rgb_in[sor]
    row = {"cloud": name, "points": n, "after_sor": int(sor.sum()), "authors_kept": len(rgb_t),
           "ours_kept": ours["kept"], "authors_seconds": theirs["seconds"], "ours_seconds": ours["seconds"],
           "authors_peak_mib": theirs["peak_rss_mib"], "ours_peak_mib": ours["peak_rss_mib"]}
    for label, fn in (("authors_bins", authors_bins), ("our_bins", our_bins)):
        b_in, b_t, b_o = fn(clean, chroma, q), fn(rgb_t, chroma, q), fn(rgb_o, chroma, q)
        keys, n_in = np.unique(b_in, return_counts=True)
        want = np.minimum(n_in, k)  # what any correct PRISM keeps per bin, on these bins
        got_t = _per_bin(keys, b_t)
        got_o = _per_bin(keys, b_o)
        row[label] = {"bins": len(keys), "expected_kept": int(want.sum()),
                      "authors_bins_off": int((got_t != want).sum()), "ours_bins_off": int((got_o != want).sum()),
                      "H_in": entropy_bits(n_in), "H_authors": entropy_bits(got_t), "H_ours": entropy_bits(got_o)}
    return row


def _color_cols(t):
    names = {c.lower(): c for c in t.column_names}
    for want in (("red", "green", "blue"), ("r", "g", "b")):
        if all(w in names for w in want):
            return [names[w] for w in want]
    raise SystemExit("no color columns in our output")


def _per_bin(keys, b):
    k2, c2 = np.unique(b, return_counts=True)
    out = np.zeros(len(keys), np.int64)
    pos = np.searchsorted(keys, k2)
    ok = (pos < len(keys)) & (keys[np.minimum(pos, len(keys) - 1)] == k2)
    out[pos[ok]] = c2[ok]
    return out


def markdown(rows, k, q, chroma) -> str:
    space = "chroma" if chroma else "rgb"
    out = [f"PRISM.py vs `prism-stream` (SOR 100/2.0 in memory, then PRISM {space}, step {q:g}, k = {k}).", "",
           "| Cloud | N | after SOR | kept: PRISM.py | kept: ours | bins (theirs / ours) | bins off: PRISM.py "
           "| bins off: ours | H out: PRISM.py | H out: ours | time s: PRISM.py | time s: ours | peak MiB: PRISM.py "
           "| peak MiB: ours |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        a, o = r["authors_bins"], r["our_bins"]
        out.append(f"| {r['cloud']} | {r['points']:,} | {r['after_sor']:,} | {r['authors_kept']:,} | "
                   f"{r['ours_kept']:,} | {a['bins']:,} / {o['bins']:,} | {a['authors_bins_off']} | "
                   f"{o['ours_bins_off']} | {a['H_authors']:.3f} | {o['H_ours']:.3f} | {r['authors_seconds']:.2f} | "
                   f"{r['ours_seconds']:.2f} | {_mib(r['authors_peak_mib'])} | {_mib(r['ours_peak_mib'])} |")
    out += ["", "*bins off*: bins (each side's own rule) whose kept count is not min(n_b, k) on the SOR-cleaned "
            "input; *H out*: entropy (bits) of the output over that side's own bins."]
    return "\n".join(out) + "\n"


def _mib(v):
    return "-" if v is None else f"{v:.0f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("inputs", nargs="+")
    ap.add_argument("--prism-py", required=True, help="a local copy of the authors' PRISM.py")
    ap.add_argument("--k", type=int, default=1)
    ap.add_argument("--q", type=float, default=1.0)
    ap.add_argument("--no-chromaticity", action="store_true")
    ap.add_argument("--out", help="write the table here (.md); JSON beside it")
    a = ap.parse_args(argv)
    if not os.path.isfile(a.prism_py):
        ap.error(f"{a.prism_py}: no such file")
    rows = []
    with tempfile.TemporaryDirectory(prefix="prism-authors-") as tmp:
        for src in a.inputs:
            rows.append(compare(src, a.prism_py, a.k, a.q, not a.no_chromaticity, tmp))
            print(json.dumps(rows[-1]), file=sys.stderr)
    text = markdown(rows, a.k, a.q, not a.no_chromaticity)
    print(text)
    if a.out:
        with open(a.out, "w") as f:
            f.write(text)
        with open(os.path.splitext(a.out)[0] + ".json", "w") as f:
            json.dump(rows, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
