"""prism-stream's outputs read by the readers that need more than pip (issue 31).

The test suite checks every writer with pip readers (laspy, laszip, copclib,
geopandas, plyfile). This script covers the readers a user meets outside
Python's wheels:

* the npm ``copc`` package (copc.js, what COPC web viewers load) under node:
  ``bench/interop/read_copc.mjs`` prints what it reads of one file (header,
  VLRs and EVLRs, WKT, extra-bytes descriptors, every hierarchy node and its
  points); it reads COPC through ``Copc.create`` and the hierarchy, and plain
  LAS/LAZ through the same package's ``Las.*`` helpers (laz-perf for LAZ);
  ``cd bench/interop && npm install --no-package-lock`` puts it in
  ``bench/interop/node_modules`` (package.json pins copc 0.0.8, which pins laz-perf 0.0.7);
* Open3D (pip ``open3d``, the ``bench`` extra, whose wheel needs the system's
  libusb-1.0): ``read_point_cloud`` on PLY;
* PDAL, where it installs (Debian's ``pdal`` and PyPI's ``pdal`` bindings,
  which build against an installed libpdal): ``readers.las``/``readers.copc``/
  ``readers.ply``/``readers.arrow`` through the Python bindings;
* copclib (pip, already a test reader) as a COPC cross-check beside them.

For every writer (LAS, LAZ, COPC, Parquet, Parquet ``--geometry``, PLY) it
samples every real cloud of ``tests/data/real`` with prism-stream (an output
prism-stream refuses is listed as refused, with its one-line error), reads
each output with the pip reference (laspy, pyarrow, plyfile: the file's own
consistency against the run's ``--json`` summary and its input) and with each
reader that supports it, and compares: point count, bounds (within a scale
step), every point's RGB (in order, or as a multiset across COPC nodes), CRS
(WKT present and ``pyproj.CRS.equals``), extra-bytes names and, where a
descriptor flags them valid, their min/max against the data; for COPC the
hierarchy (node counts summed, and every node's points as a multiset equal
to laspy's). A reader runs in its own process, so a crash or an exception is
that cell's FAIL with its message.

    .venv/bin/python bench/interop.py                      # a temporary folder, removed after
    .venv/bin/python bench/interop.py --out bench/out/interop --json bench/out/interop.json

Exit 0 when every reader that loaded read every output right (a reader that
could not load is said, with why, and is no failure); 1 when a cell failed.
Never asserted in tests.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
NODE_DIR = HERE / "interop"
REAL = ROOT / "tests" / "data" / "real"

WRITERS = [  # (name, file suffix, extra arguments)
    ("las", ".las", []),
    ("laz", ".laz", []),
    ("copc", ".copc.laz", []),
    ("parquet", ".parquet", []),
    ("parquet-geo", ".geo.parquet", ["--geometry"]),
    ("ply", ".ply", []),
]
LAS_FAMILY = {"las", "laz", "copc"}

READERS = ["reference", "copc-npm", "open3d", "pdal", "copclib"]
READER_TITLES = {
    "reference": "pip reference (laspy/pyarrow/plyfile)",
    "copc-npm": "copc (npm)",
    "open3d": "Open3D",
    "pdal": "PDAL",
    "copclib": "copclib (pip)",
}
SUPPORTS = {
    "reference": {"las", "laz", "copc", "parquet", "parquet-geo", "ply"},
    "copc-npm": {"las", "laz", "copc"},
    "open3d": {"ply"},
    "pdal": {"las", "laz", "copc", "ply", "parquet", "parquet-geo"},
    "copclib": {"copc"},
}
EB_TYPES = {1: "u1", 2: "i1", 3: "u2", 4: "i2", 5: "u4", 6: "i4", 7: "u8", 8: "i8", 9: "f4", 10: "f8"}


class Mismatch(Exception):
    pass


# ----------------------------------------------------------------- the readers


def _run(cmd, timeout=600, cwd=None):
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=cwd)


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in (text or "").strip().splitlines() if ln.strip()]
    return lines[-1] if lines else ""


def probe_readers() -> dict:
    """Which readers load here, their versions, and why the others do not."""
    found = {"reference": {"loaded": True, "version": _pip_versions(), "why": ""}}
    # npm copc under node
    node = shutil.which("node")
    pkg = NODE_DIR / "node_modules" / "copc" / "package.json"
    if not node:
        found["copc-npm"] = {"loaded": False, "why": "no `node` on PATH"}
    elif not pkg.exists():
        found["copc-npm"] = {"loaded": False,
                             "why": f"{pkg.relative_to(ROOT)} missing: run `cd bench/interop && npm install --no-package-lock`"}
    else:
        r = _run([node, "--input-type=module", "-e",
                  "import c from 'copc'; if (!c.Copc || !c.Las) throw new Error('copc has no Copc/Las export');"
                  " console.log(process.version)"], cwd=NODE_DIR)
        if r.returncode:
            found["copc-npm"] = {"loaded": False, "why": _last_line(r.stderr) or f"node exited {r.returncode}"}
        else:
            ver = json.loads(pkg.read_text())["version"]
            found["copc-npm"] = {"loaded": True, "version": f"copc {ver} (node {r.stdout.strip()})", "why": ""}
    # Open3D, in its own process (its wheel needs libusb-1.0)
    r = _run([sys.executable, "-c", "import open3d; print(open3d.__version__)"])
    found["open3d"] = ({"loaded": True, "version": f"open3d {r.stdout.strip()}", "why": ""} if r.returncode == 0
                       else {"loaded": False, "why": _last_line(r.stderr)})
    # PDAL: the Python bindings (pip `pdal`, built against libpdal); the CLI is said when present
    r = _run([sys.executable, "-c", "import pdal; print(pdal.__version__, getattr(pdal, 'info', {}).get('version', '') "
              "if isinstance(getattr(pdal, 'info', None), dict) else '')"])
    cli = shutil.which("pdal")
    if r.returncode == 0:
        found["pdal"] = {"loaded": True, "version": f"pdal (Python) {r.stdout.strip()}", "why": ""}
    else:
        why = f"Python bindings: {_last_line(r.stderr)}"
        why += f"; the CLI is at {cli}, but this bench reads through the bindings" if cli else "; no `pdal` CLI on PATH"
        found["pdal"] = {"loaded": False, "why": why}
    r = _run([sys.executable, "-c", "import copclib, importlib.metadata as m; print(m.version('copclib'))"])
    found["copclib"] = ({"loaded": True, "version": f"copclib {r.stdout.strip()}", "why": ""} if r.returncode == 0
                        else {"loaded": False, "why": _last_line(r.stderr)})
    return found


def _pip_versions() -> str:
    import importlib.metadata as m
    out = []
    for name in ("laspy", "lazrs", "pyarrow", "plyfile", "pyproj"):
        try:
            out.append(f"{name} {m.version(name)}")
        except m.PackageNotFoundError:
            out.append(f"{name} missing")
    return ", ".join(out)


# Worker modes: each non-reference reader runs in a child process
# (`interop.py --worker NAME FILE`), which prints one JSON object.


def worker_open3d(path: str) -> dict:
    import open3d as o3d
    pc = o3d.io.read_point_cloud(path, format="ply")
    pts = np.asarray(pc.points)
    cols = np.asarray(pc.colors)
    return {"count": int(len(pts)), "xyz": pts.tolist(),
            "rgb01": cols.tolist() if pc.has_colors() else None}


def worker_copclib(path: str) -> dict:
    import copclib
    r = copclib.FileReader(path)
    cfg = r.copc_config
    h = cfg.las_header
    v3 = lambda v: [float(v.x), float(v.y), float(v.z)]  # noqa: E731
    scale, offset = v3(h.scale), v3(h.offset)
    nodes, xyz, rgb = {}, [], []
    for node in r.GetAllNodes():
        key = str(node.key)
        nodes[key] = int(node.point_count)
        if node.point_count <= 0:
            continue
        p = r.GetPoints(node)
        xs, ys, zs = np.asarray(p.x), np.asarray(p.y), np.asarray(p.z)
        xyz.append(np.stack([np.rint((xs - offset[0]) / scale[0]), np.rint((ys - offset[1]) / scale[1]),
                             np.rint((zs - offset[2]) / scale[2])], axis=1).astype(np.int64))
        rgb.append(np.stack([np.asarray(p.red), np.asarray(p.green), np.asarray(p.blue)], axis=1).astype(np.int64))
    xyz = np.concatenate(xyz) if xyz else np.zeros((0, 3), np.int64)
    rgb = np.concatenate(rgb) if rgb else np.zeros((0, 3), np.int64)
    return {"count": int(h.point_count), "min": v3(h.min), "max": v3(h.max), "scale": scale,
            "wkt": cfg.wkt or None, "nodes": nodes, "grid": xyz.tolist(), "rgb": rgb.tolist()}


def worker_pdal(path: str) -> dict:
    import pdal
    kind = "readers.copc" if path.endswith(".copc.laz") else None
    stage = {"type": kind, "filename": path} if kind else path
    if path.endswith(".parquet"):
        stage = {"type": "readers.arrow", "filename": path}
    p = pdal.Pipeline(json.dumps([stage]))
    p.execute()
    arr = p.arrays[0]
    md = p.metadata
    md = md if isinstance(md, dict) else json.loads(md)
    wkt = None
    for v in (md.get("metadata") or {}).values():
        if isinstance(v, dict) and v.get("comp_spatialreference"):
            wkt = v["comp_spatialreference"]
        elif isinstance(v, dict) and v.get("spatialreference"):
            wkt = wkt or v["spatialreference"]
    names = arr.dtype.names
    pick = lambda *cands: next((c for c in cands if c in names), None)  # noqa: E731
    r, g, b = pick("Red", "red"), pick("Green", "green"), pick("Blue", "blue")
    return {"count": int(len(arr)),
            "xyz": np.stack([arr["X"], arr["Y"], arr["Z"]], axis=1).tolist(),
            "rgb": np.stack([arr[r], arr[g], arr[b]], axis=1).astype(np.int64).tolist() if r else None,
            "wkt": wkt or None, "dims": list(names)}


WORKERS = {"open3d": worker_open3d, "copclib": worker_copclib, "pdal": worker_pdal}


def run_worker(name: str, path: Path) -> dict:
    r = _run([sys.executable, str(Path(__file__).resolve()), "--worker", name, str(path)])
    try:
        out = json.loads(r.stdout.strip().splitlines()[-1]) if r.stdout.strip() else None
    except json.JSONDecodeError:
        out = None
    if out is None or "error" in (out or {}):
        msg = (out or {}).get("error") or _last_line(r.stderr) or _last_line(r.stdout) \
            or f"exit {r.returncode}{' (signal %d)' % -r.returncode if r.returncode < 0 else ''}"
        raise Mismatch(f"{name} raised: {msg}")
    return out


def run_npm(path: Path, writer: str) -> dict:
    cmd = ["node", str(NODE_DIR / "read_copc.mjs"), str(path)] + ([] if writer == "copc" else ["--las"])
    r = _run(cmd, cwd=NODE_DIR)
    out = None
    if r.stdout.strip():
        try:
            out = json.loads(r.stdout.strip().splitlines()[-1])
        except json.JSONDecodeError:
            out = None
    if out is None:
        raise Mismatch(f"node exited {r.returncode}: {_last_line(r.stderr)[:200]}")
    if "error" in out:
        raise Mismatch(f"copc threw: {out['error']}")
    return out


# ------------------------------------------------------- the pip reference read


def parse_las_records(path: Path) -> dict:
    """VLRs and EVLRs of a LAS/LAZ file from its bytes (where each one is)."""
    raw = path.read_bytes()
    hs = int.from_bytes(raw[94:96], "little")
    nv = int.from_bytes(raw[100:104], "little")
    minor = raw[25]
    recs, pos = [], hs
    for _ in range(nv):
        uid = raw[pos + 2:pos + 18].split(b"\0")[0].decode("ascii", "replace")
        rid = int.from_bytes(raw[pos + 18:pos + 20], "little")
        ln = int.from_bytes(raw[pos + 20:pos + 22], "little")
        recs.append({"user_id": uid, "record_id": rid, "evlr": False, "data": raw[pos + 54:pos + 54 + ln]})
        pos += 54 + ln
    if minor >= 4:
        start = int.from_bytes(raw[235:243], "little")
        ne = int.from_bytes(raw[243:247], "little")
        pos = start
        for _ in range(ne if start else 0):
            uid = raw[pos + 2:pos + 18].split(b"\0")[0].decode("ascii", "replace")
            rid = int.from_bytes(raw[pos + 18:pos + 20], "little")
            ln = int.from_bytes(raw[pos + 20:pos + 28], "little")
            recs.append({"user_id": uid, "record_id": rid, "evlr": True, "data": raw[pos + 60:pos + 60 + ln]})
            pos += 60 + ln
    return {"records": recs, "minor": minor, "pdrf": raw[104] & 0x3F}


def parse_extra_bytes(data: bytes) -> list[dict]:
    out = []
    for o in range(0, len(data) - len(data) % 192, 192):
        e = data[o:o + 192]
        t, opt = e[2], e[3]
        name = e[4:36].split(b"\0")[0].decode("ascii", "replace")
        d = {"name": name, "type": t, "options": opt}
        if 1 <= t <= 10:
            any_t = "<u8" if EB_TYPES[t][0] == "u" else "<i8" if EB_TYPES[t][0] == "i" else "<f8"
            val = lambda off: np.frombuffer(e[off:off + 8], any_t)[0].item()  # noqa: E731
            if opt & 2:
                d["min"] = val(64)
            if opt & 4:
                d["max"] = val(88)
            d["scale"] = np.frombuffer(e[112:120], "<f8")[0].item() if opt & 8 else None
            d["offset"] = np.frombuffer(e[136:144], "<f8")[0].item() if opt & 16 else None
        out.append(d)
    return out


def read_reference(path: Path, writer: str) -> dict:
    """What laspy / pyarrow / plyfile read of one output."""
    if writer in LAS_FAMILY:
        import laspy
        las = laspy.read(str(path))
        h = las.header
        recs = parse_las_records(path)
        wkt_recs = [r for r in recs["records"] if r["user_id"] == "LASF_Projection" and r["record_id"] == 2112]
        ebs = []
        for r in recs["records"]:
            if r["user_id"] == "LASF_Spec" and r["record_id"] == 4:
                ebs = parse_extra_bytes(r["data"])
        eb_data = {}
        for name in h.point_format.extra_dimension_names:
            rawv = np.asarray(las.points.array[name]) if name in (las.points.array.dtype.names or ()) else None
            scaled = np.asarray(las[name])
            if rawv is not None and rawv.ndim > 1:
                continue  # an array dimension: no single min/max
            eb_data[name] = {"raw": (rawv.min().item(), rawv.max().item()) if rawv is not None and len(rawv) else None,
                             "scaled": (scaled.min().item(), scaled.max().item()) if len(scaled) else None}
        grid = np.stack([las.X, las.Y, las.Z], axis=1).astype(np.int64)
        rgb = (np.stack([las.red, las.green, las.blue], axis=1).astype(np.int64)
               if "red" in h.point_format.dimension_names else None)
        crs = None
        try:
            crs = h.parse_crs()
        except Exception as e:  # a CRS laspy cannot parse is a finding of its own
            crs = f"unparsable: {e}"
        return {"count": len(las.points), "header_count": int(h.point_count),
                "min": list(map(float, h.mins)), "max": list(map(float, h.maxs)),
                "scale": list(map(float, h.scales)), "offset": list(map(float, h.offsets)),
                "grid": grid, "xyz": np.stack([las.x, las.y, las.z], axis=1), "rgb": rgb,
                "crs": crs, "wkt_records": [("EVLR" if r["evlr"] else "VLR", r["data"].split(b"\0")[0].decode("utf8", "replace"))
                                            for r in wkt_recs],
                "eb_names": list(h.point_format.extra_dimension_names), "eb_desc": ebs, "eb_data": eb_data,
                "pdrf": recs["pdrf"], "minor": recs["minor"]}
    if writer in ("parquet", "parquet-geo"):
        import pyarrow.parquet as pq
        t = pq.read_table(str(path))
        cols = {c.lower(): c for c in t.column_names}
        xyz = np.stack([t[cols[c]].to_numpy() for c in ("x", "y", "z")], axis=1).astype(np.float64)
        rgb = (np.stack([t[cols[c]].to_numpy() for c in ("red", "green", "blue")], axis=1).astype(np.int64)
               if all(c in cols for c in ("red", "green", "blue")) else None)
        md = t.schema.metadata or {}
        geo = json.loads(md[b"geo"]) if b"geo" in md else None
        geom = None
        if "geometry" in t.column_names:
            geom = t["geometry"].to_pylist()
        return {"count": t.num_rows, "xyz": xyz, "rgb": rgb, "geo": geo, "geometry": geom,
                "min": xyz.min(axis=0).tolist() if len(xyz) else None,
                "max": xyz.max(axis=0).tolist() if len(xyz) else None, "columns": t.column_names}
    if writer == "ply":
        from plyfile import PlyData
        ply = PlyData.read(str(path))
        v = ply["vertex"].data
        names = v.dtype.names
        xyz = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
        pick = [next((n for n in (c, "diffuse_" + c) if n in names), None) for c in ("red", "green", "blue")]
        rgb = np.stack([v[n] for n in pick], axis=1).astype(np.int64) if all(pick) else None
        raw = path.read_bytes()[:1 << 20]
        end = raw.find(b"end_header")
        header_lines = raw[:end + len(b"end_header")].decode("ascii", "replace").split("\n")
        return {"count": len(v), "xyz": xyz, "rgb": rgb, "header_lines": header_lines,
                "color_types": [v.dtype[n].str for n in pick if n],
                "min": xyz.min(axis=0).tolist() if len(xyz) else None,
                "max": xyz.max(axis=0).tolist() if len(xyz) else None}
    raise ValueError(writer)


def input_crs(path: Path):
    if path.suffix.lower() not in (".las", ".laz"):
        return None
    import laspy
    with laspy.open(str(path)) as f:
        try:
            return f.header.parse_crs()
        except Exception:
            return None


# ----------------------------------------------------------------- comparisons


def _crs_equal(wkt_or_crs, ref) -> bool:
    from pyproj import CRS
    try:
        a = wkt_or_crs if isinstance(wkt_or_crs, CRS) else CRS.from_user_input(wkt_or_crs)
    except Exception as e:  # noqa: BLE001
        text = str(wkt_or_crs)
        raise Mismatch(f"its WKT does not parse ({type(e).__name__}; it starts {text[:30]!r}, {len(text)} chars)") from None
    b = ref if isinstance(ref, CRS) else CRS.from_user_input(ref)
    return a.equals(b) or a.equals(b, ignore_axis_order=True)


def _multiset(*arrays) -> np.ndarray:
    a = np.concatenate([np.asarray(x, dtype=np.float64).reshape(len(arrays[0]), -1) for x in arrays], axis=1)
    return a[np.lexsort(a.T[::-1])] if len(a) else a


def _bounds_close(got_min, got_max, want_min, want_max, tol, what):
    gmin, gmax = np.asarray(got_min, float), np.asarray(got_max, float)
    wmin, wmax = np.asarray(want_min, float), np.asarray(want_max, float)
    tol = np.asarray(tol, float) * 1.0001 + 1e-9 * np.maximum(np.abs(wmin), np.abs(wmax))
    if np.any(np.abs(gmin - wmin) > tol) or np.any(np.abs(gmax - wmax) > tol):
        raise Mismatch(f"{what} {np.round(gmin, 6).tolist()}..{np.round(gmax, 6).tolist()} "
                       f"!= {np.round(wmin, 6).tolist()}..{np.round(wmax, 6).tolist()}")


def _eb_minmax_problems(desc: list[dict], eb_data: dict, who: str) -> list[str]:
    """Descriptors that flag min/max valid must hold the data's extremes (raw or scaled)."""
    out = []
    for d in desc:
        data = eb_data.get(d["name"])
        if data is None or ("min" not in d and "max" not in d):
            continue
        bad = False
        for i, key in ((0, "min"), (1, "max")):
            if key not in d:
                continue
            v = float(d[key])
            cands = [float(x[i]) for x in (data.get("raw"), data.get("scaled")) if x is not None]
            bad |= not any(abs(v - c) <= 1e-6 * max(1.0, abs(c)) for c in cands)
        if bad:
            data_rng = data.get("raw") or data.get("scaled")
            out.append(f"{who}extra bytes '{d['name']}' flagged min..max {d.get('min', '-')!r}..{d.get('max', '-')!r}, "
                       f"the data {data_rng[0]!r}..{data_rng[1]!r}")
    return out


def check_reference(out: dict, ref: dict, expect_crs) -> list[str]:
    """The output as laspy/pyarrow/plyfile read it, against the summary and the input."""
    probs = []
    writer = out["writer"]
    kept = out["summary"]["kept"]
    if ref["count"] != kept:
        probs.append(f"{ref['count']} points, the summary says {kept}")
    if writer in LAS_FAMILY:
        if ref["header_count"] != ref["count"]:
            probs.append(f"header count {ref['header_count']} != {ref['count']} records")
        if ref["count"]:
            dmin = ref["grid"].min(axis=0) * ref["scale"] + ref["offset"]
            dmax = ref["grid"].max(axis=0) * ref["scale"] + ref["offset"]
            try:
                _bounds_close(ref["min"], ref["max"], dmin, dmax, ref["scale"], "header bounds")
            except Mismatch as e:
                probs.append(f"{e} (the points')")
        if expect_crs is not None:
            if ref["crs"] is None:
                probs.append("no CRS (the input has one)")
            elif isinstance(ref["crs"], str):
                probs.append(f"CRS {ref['crs']}")
            elif not _crs_equal(ref["crs"], expect_crs):
                probs.append(f"CRS {ref['crs'].name!r} != the input's {expect_crs.name!r}")
            if ref["pdrf"] >= 6 and not ref["wkt_records"]:
                probs.append(f"point format {ref['pdrf']} without a WKT (LASF_Projection 2112) record")
        from pyproj import CRS
        for kind, text in ref["wkt_records"]:
            try:
                if text:
                    CRS.from_wkt(text)
            except Exception:  # noqa: BLE001
                probs.append(f"its WKT {kind} holds {text[:30]!r}, no CRS"
                             + (" (the input has none)" if expect_crs is None else ""))
        if writer == "copc" and any(w for _, w in ref["wkt_records"]) \
                and not any(k == "EVLR" and w for k, w in ref["wkt_records"]):
            probs.append("COPC: the WKT is in a VLR, none in an EVLR"
                         + (" (copclib misreads it: see its column)" if expect_crs is not None else ""))
        if sorted(d["name"] for d in ref["eb_desc"]) != sorted(ref["eb_names"]):
            probs.append(f"extra-bytes descriptors {[d['name'] for d in ref['eb_desc']]} != dimensions {ref['eb_names']}")
        probs += _eb_minmax_problems(ref["eb_desc"], ref["eb_data"], "")
    elif writer in ("parquet", "parquet-geo"):
        if writer == "parquet-geo":
            if ref["geo"] is None:
                probs.append("no GeoParquet 'geo' metadata")
            elif ref["geometry"] is None:
                probs.append("no geometry column")
            else:
                g = ref["geometry"]
                bad = 0
                for i, wkb in enumerate(g):
                    if wkb is None or len(wkb) < 21:
                        bad += 1
                        continue
                    bo = "<" if wkb[0] == 1 else ">"
                    vals = np.frombuffer(wkb[5:5 + 8 * ((len(wkb) - 5) // 8)], bo + "f8")
                    if not np.allclose(vals[:len(ref["xyz"][i])], ref["xyz"][i][:len(vals)], rtol=0, atol=1e-9):
                        bad += 1
                if bad:
                    probs.append(f"{bad} WKB geometries differ from x,y,z")
                col = (ref["geo"].get("columns") or {}).get(ref["geo"].get("primary_column", "geometry"), {})
                crs = col.get("crs", "absent")
                if expect_crs is not None:
                    if not crs or crs == "absent":
                        probs.append("GeoParquet: no CRS (the input has one)")
                    elif not _crs_equal(json.dumps(crs), expect_crs):
                        probs.append("GeoParquet CRS differs from the input's")
                bbox = col.get("bbox")
                if bbox and ref["count"]:
                    try:
                        _bounds_close(bbox[:2], bbox[-2:] if len(bbox) == 4 else bbox[3:5],
                                      ref["min"][:2], ref["max"][:2], [0, 0], "GeoParquet bbox")
                    except Mismatch as e:
                        probs.append(str(e))
    elif writer == "ply":
        padded = [i + 1 for i, ln in enumerate(ref["header_lines"]) if ln != ln.rstrip(" \t\r")]
        if padded:
            first = ref["header_lines"][padded[0] - 1]
            probs.append(f"PLY header line(s) {padded} end in spaces (e.g. {first[:40]!r}...)")
    return probs


def check_npm(out: dict, ref: dict, npm: dict, expect_crs) -> list[str]:
    probs = []
    h = npm["header"]
    kept = out["summary"]["kept"]
    if h["pointCount"] != kept:
        probs.append(f"header pointCount {h['pointCount']}, the summary says {kept}")
    nodes = npm["nodes"]
    node_sum = sum(int(n["pointCount"]) for n in nodes.values())
    read = sum(int(n.get("count", 0)) for n in nodes.values())
    if out["writer"] == "copc" and node_sum != h["pointCount"]:
        probs.append(f"hierarchy node counts sum to {node_sum}, header {h['pointCount']}")
    if read != ref["count"]:
        probs.append(f"read {read} points, laspy {ref['count']}")
    try:
        _bounds_close(h["min"], h["max"], ref["min"], ref["max"], ref["scale"], "header bounds")
    except Mismatch as e:
        probs.append(f"{e} (laspy's)")
    keys = [k for k in nodes if nodes[k].get("count")]
    grid = np.concatenate([np.stack([nodes[k]["points"][c] for c in "XYZ"], axis=1) for k in keys]) if keys \
        else np.zeros((0, 3))
    has_rgb = keys and len(nodes[keys[0]]["points"]["R"])
    rgb = np.concatenate([np.stack([nodes[k]["points"][c] for c in "RGB"], axis=1) for k in keys]) \
        if has_rgb else None
    if len(grid) == len(ref["grid"]) and len(grid):
        if out["writer"] == "copc":  # nodes: compare as multisets
            if not np.array_equal(_multiset(grid, rgb if rgb is not None else grid[:, :0]),
                                  _multiset(ref["grid"], ref["rgb"] if ref["rgb"] is not None else ref["grid"][:, :0])):
                probs.append("the nodes' points (X, Y, Z, R, G, B) differ from laspy's as a multiset")
        else:
            if not np.array_equal(grid, ref["grid"]):
                probs.append(f"{int((grid != ref['grid']).any(axis=1).sum())} points' X/Y/Z differ from laspy's")
            if (rgb is None) != (ref["rgb"] is None):
                probs.append("colors present in one reader only")
            elif rgb is not None and not np.array_equal(rgb, ref["rgb"]):
                probs.append(f"{int((rgb != ref['rgb']).any(axis=1).sum())} points' RGB differ from laspy's")
    ref_crs = ref["crs"] if ref["crs"] is not None and not isinstance(ref["crs"], str) else expect_crs
    if ref_crs is not None:
        if not npm.get("wkt"):
            how = "GeoTIFF keys only" if not ref["wkt_records"] else "a WKT record it did not find"
            probs.append(f"no WKT read (the file has {how})")
        elif not _crs_equal(npm["wkt"], ref_crs):
            probs.append("its WKT is not CRS.equals laspy's CRS")
    eb_names = [e["name"] for e in npm.get("eb", [])]
    if sorted(eb_names) != sorted(ref["eb_names"]):
        probs.append(f"extra bytes {eb_names}, laspy {ref['eb_names']}")
    probs += _eb_minmax_problems([e for e in npm.get("eb", []) if "length" in e], ref["eb_data"], "its ")
    # its own data's extremes against laspy's
    for name in eb_names:
        got = [n.get("extra", {}).get(name) for n in nodes.values() if n.get("count")]
        got = [g for g in got if g and "min" in g]
        want = ref["eb_data"].get(name)
        if got and want:
            lo, hi = min(g["min"] for g in got), max(g["max"] for g in got)
            if not any(w is not None and abs(lo - w[0]) <= 1e-6 * max(1, abs(w[0])) and abs(hi - w[1]) <= 1e-6 * max(1, abs(w[1]))
                       for w in (want["raw"], want["scaled"])):
                probs.append(f"extra bytes '{name}' read as {lo}..{hi}, laspy {want['scaled']}")
    return probs


def check_open3d(out: dict, ref: dict, o3d: dict) -> list[str]:
    probs = []
    kept = out["summary"]["kept"]
    if o3d["count"] != kept:
        return [f"read {o3d['count']} points, the summary says {kept}"]
    xyz = np.asarray(o3d["xyz"], float)
    if not np.array_equal(xyz, ref["xyz"]):
        d = np.abs(xyz - ref["xyz"]).max()
        probs.append(f"coordinates differ from plyfile's (max {d:g})")
    if ref["rgb"] is not None:
        if o3d["rgb01"] is None:
            probs.append("no colors read")
        else:
            full = 65535 if any(t.endswith("u2") for t in ref["color_types"]) else 255
            rgb = np.rint(np.asarray(o3d["rgb01"], float) * full).astype(np.int64)
            if not np.array_equal(rgb, ref["rgb"]):
                probs.append(f"{int((rgb != ref['rgb']).any(axis=1).sum())} points' RGB differ from plyfile's")
    return probs


def check_copclib(out: dict, ref: dict, c: dict, expect_crs) -> list[str]:
    probs = []
    kept = out["summary"]["kept"]
    if c["count"] != kept:
        probs.append(f"header count {c['count']}, the summary says {kept}")
    if sum(v for v in c["nodes"].values() if v > 0) != c["count"]:
        probs.append(f"node counts sum to {sum(c['nodes'].values())}, header {c['count']}")
    try:
        _bounds_close(c["min"], c["max"], ref["min"], ref["max"], ref["scale"], "header bounds")
    except Mismatch as e:
        probs.append(f"{e} (laspy's)")
    grid, rgb = np.asarray(c["grid"], np.int64).reshape(-1, 3), np.asarray(c["rgb"], np.int64).reshape(-1, 3)
    if len(grid) != ref["count"]:
        probs.append(f"read {len(grid)} points, laspy {ref['count']}")
    elif ref["rgb"] is not None and not np.array_equal(_multiset(grid, rgb), _multiset(ref["grid"], ref["rgb"])):
        probs.append("the nodes' points (X, Y, Z, R, G, B) differ from laspy's as a multiset")
    ref_crs = ref["crs"] if ref["crs"] is not None and not isinstance(ref["crs"], str) else expect_crs
    if ref_crs is not None:
        if not c["wkt"]:
            where = "/".join(k for k, _ in ref["wkt_records"]) or "no"
            probs.append(f"no WKT read (the file has it in a {where} record)")
        elif not _crs_equal(c["wkt"], ref_crs):
            probs.append("its WKT is not CRS.equals laspy's CRS")
    return probs


def check_pdal(out: dict, ref: dict, p: dict, expect_crs) -> list[str]:
    probs = []
    kept = out["summary"]["kept"]
    if p["count"] != kept:
        return [f"read {p['count']} points, the summary says {kept}"]
    xyz = np.asarray(p["xyz"], float)
    tol = np.asarray(ref.get("scale", [1e-9] * 3)) * 0.5001
    if out["writer"] == "copc":
        a, b = _multiset(xyz, p["rgb"] or xyz[:, :0]), _multiset(ref["xyz"], ref["rgb"] if ref["rgb"] is not None else xyz[:, :0])
    else:
        a = np.concatenate([xyz, np.asarray(p["rgb"] or np.zeros((len(xyz), 0)))], axis=1)
        b = np.concatenate([ref["xyz"], ref["rgb"] if ref["rgb"] is not None else np.zeros((len(xyz), 0))], axis=1)
    if a.shape != b.shape or np.any(np.abs(a[:, :3] - b[:, :3]) > tol) or not np.array_equal(a[:, 3:], b[:, 3:]):
        probs.append("points (X, Y, Z, R, G, B) differ from the reference read")
    if expect_crs is not None and out["writer"] != "ply" and out["writer"] != "parquet":
        if not p.get("wkt"):
            probs.append("no CRS read")
        elif not _crs_equal(p["wkt"], expect_crs):
            probs.append("its CRS is not CRS.equals the input's")
    return probs


# ------------------------------------------------------------------ the outputs


def _prism_stream() -> str:
    exe = ROOT / ".venv" / "bin" / "prism-stream"
    return str(exe) if exe.exists() else (shutil.which("prism-stream") or "prism-stream")


def write_outputs(inputs: list[Path], out_dir: Path, ratio: float) -> list[dict]:
    exe = _prism_stream()
    outs = []
    for src in inputs:
        stem = src.name.split(".")[0]
        for writer, suffix, extra in WRITERS:
            dst = out_dir / f"{stem}{suffix}"
            cmd = [exe, str(src), str(dst), "--ratio", str(ratio), "--json", "--overwrite", *extra]
            r = _run(cmd)
            rec = {"name": dst.name, "input": src.name, "writer": writer, "path": str(dst)}
            if r.returncode:
                errs = [ln for ln in r.stderr.splitlines() if ln.strip() and "warning:" not in ln]
                rec["refused"] = (errs[-1] if errs else f"exit {r.returncode}").strip()
            else:
                rec["summary"] = json.loads(r.stdout)
                rec["warnings"] = rec["summary"].get("warnings", [])
            outs.append(rec)
            print(f"  wrote {dst.name}: " + (f"refused: {rec['refused']}" if "refused" in rec
                                               else f"{rec['summary']['kept']} points"), file=sys.stderr)
    return outs


def evaluate(out: dict, readers: dict, crs_by_input: dict) -> dict:
    cells = {}
    if "refused" in out:
        return {r: "refused" for r in READERS}
    path, writer = Path(out["path"]), out["writer"]
    expect_crs = crs_by_input.get(out["input"])
    try:
        ref = read_reference(path, writer)
        probs = check_reference(out, ref, expect_crs)
        cells["reference"] = "ok" if not probs else "FAIL: " + "; ".join(probs)
    except Exception as e:  # noqa: BLE001
        ref = None
        cells["reference"] = f"FAIL: {type(e).__name__}: {e}"
    for name in READERS[1:]:
        if writer not in SUPPORTS[name]:
            cells[name] = "-"
            continue
        if not readers[name]["loaded"]:
            cells[name] = "not loaded"
            continue
        if ref is None:
            cells[name] = "FAIL: the reference could not read it to compare"
            continue
        try:
            if name == "copc-npm":
                probs = check_npm(out, ref, run_npm(path, writer), expect_crs)
            elif name == "open3d":
                try:
                    probs = check_open3d(out, ref, run_worker("open3d", path))
                except Mismatch as e:
                    long = [(i + 1, len(ln)) for i, ln in enumerate(ref["header_lines"]) if len(ln) >= 1024]
                    if long:  # rply, Open3D's PLY parser, reads a header line into a 1024-byte buffer
                        raise Mismatch(f"{e} (header line {long[0][0]} is {long[0][1]} bytes; rply, Open3D's "
                                       "PLY parser, holds 1023)") from None
                    raise
            elif name == "copclib":
                probs = check_copclib(out, ref, run_worker("copclib", path), expect_crs)
            else:
                probs = check_pdal(out, ref, run_worker("pdal", path), expect_crs)
            cells[name] = "ok" if not probs else "FAIL: " + "; ".join(probs)
        except Mismatch as e:
            cells[name] = f"FAIL: {e}"
        except Exception as e:  # noqa: BLE001
            cells[name] = f"FAIL: {type(e).__name__}: {e}"
    # a reader that also fails on the input itself: say so (a limit of the reader, not of the output)
    for name in ("copc-npm",):
        c = cells.get(name, "")
        src = REAL / out["input"]
        if c.startswith("FAIL") and "threw" in c and src.suffix.lower() in (".las", ".laz") and readers[name]["loaded"]:
            try:
                run_npm(src, "copc" if src.name.endswith(".copc.laz") else "las")
            except Mismatch as e:
                cells[name] += f" (it fails on the input {src.name} too: {e})"
    return cells


def render_table(outs: list[dict], readers: dict, width: int = 70) -> str:
    head = ["output", "writer"] + [READER_TITLES[r] for r in READERS]
    rows = []
    notes = []
    for o in outs:
        row = [o["name"], o["writer"]]
        for r in READERS:
            c = o["cells"][r]
            if c.startswith("FAIL"):
                notes.append(f"{o['name']} x {READER_TITLES[r]}: {c}")
                c = f"FAIL [{len(notes)}]: " + (c[6:width] + "..." if len(c) > width else c[6:])
            elif c == "refused":
                c = "refused: " + o["refused"]
            row.append(c)
        rows.append(row)
    esc = lambda s: s.replace("|", "\\|")  # noqa: E731
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(esc(c) for c in row) + " |" for row in rows]
    if notes:
        lines += ["", "Failures in full:", ""]
        lines += [f"{i}. {n}" for i, n in enumerate(notes, 1)]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, help="folder for the outputs (kept); default: a temporary folder, removed")
    ap.add_argument("--ratio", type=float, default=0.05, help="sampling ratio (default 0.05: a few thousand points)")
    ap.add_argument("--inputs", nargs="*", help="inputs (default: every cloud in tests/data/real)")
    ap.add_argument("--json", type=Path, dest="json_path", help="also write the table and the readers as JSON here")
    ap.add_argument("--worker", nargs=2, metavar=("READER", "FILE"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.worker:
        name, path = args.worker
        try:
            res = WORKERS[name](path)
        except BaseException as e:  # noqa: BLE001
            res = {"error": f"{type(e).__name__}: {e}"}
        sys.stdout.flush()
        print(json.dumps(res))
        return 0

    readers = probe_readers()
    exe = _prism_stream()
    r = _run([str(Path(exe).parent / "python") if Path(exe).parent.joinpath("python").exists() else sys.executable,
              "-c", "import prism_stream, prism_stream_cli, importlib.metadata as m; "
              "print(m.version('prism-stream'), prism_stream.__file__.rsplit('/', 2)[0])"], cwd="/")
    rev = _run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"]).stdout.strip()
    dirty = _run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"]).stdout.strip()
    code = _last_line(r.stdout) or _last_line(r.stderr)
    where = (f"the checkout at {rev}{', with uncommitted changes' if dirty else ''}" if code.endswith(str(ROOT))
             else f"not the checkout (PYTHONPATH={os.environ.get('PYTHONPATH', '')!r})")
    print(f"prism-stream: {exe}, version and code: {code}, {where}")
    print("readers:")
    for r in READERS:
        info = readers[r]
        state = f"found: {info['version']}" if info["loaded"] else f"not loaded: {info['why']}"
        print(f"  {READER_TITLES[r]:40s} {state}")

    inputs = [Path(p) for p in (args.inputs or sorted(glob.glob(str(REAL / "*"))))]
    tmp = None
    if args.out:
        out_dir = args.out
        out_dir.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="prism-interop-")
        out_dir = Path(tmp.name)
    try:
        print(f"writing {len(inputs) * len(WRITERS)} outputs into {out_dir} (--ratio {args.ratio})", file=sys.stderr)
        outs = write_outputs(inputs, out_dir, args.ratio)
        crs_by_input = {p.name: input_crs(p) for p in inputs}
        for o in outs:
            print(f"  reading {o['name']}", file=sys.stderr)
            o["cells"] = evaluate(o, readers, crs_by_input)
    finally:
        if tmp is not None:
            tmp.cleanup()

    table = render_table(outs, readers)
    print()
    print(table)
    failed = [(o["name"], r) for o in outs for r in READERS if o["cells"][r].startswith("FAIL")]
    print()
    print(f"{len(outs)} outputs ({sum('refused' in o for o in outs)} refused by prism-stream), "
          f"{len(failed)} failed cells; readers not loaded: "
          + (", ".join(READER_TITLES[r] for r in READERS if not readers[r]["loaded"]) or "none"))
    if args.json_path:
        doc = {"command": " ".join([Path(sys.executable).name, *sys.argv]), "ratio": args.ratio,
               "readers": {r: readers[r] for r in READERS},
               "outputs": [{k: v for k, v in o.items() if k not in ("summary",)} | {"kept": o.get("summary", {}).get("kept")}
                           for o in outs],
               "failed": len(failed)}
        args.json_path.parent.mkdir(parents=True, exist_ok=True)
        args.json_path.write_text(json.dumps(doc, indent=2) + "\n")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
