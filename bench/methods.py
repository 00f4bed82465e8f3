"""The comparison points of the benchmark, one subprocess each (so peak RSS is per method).

    python bench/methods.py laz-read FILE --layers rgb|all [--threads N]
    python bench/methods.py laz-chunks FILE [--threads N]
    python bench/methods.py laz-decimate FILE OUT.laz --ratio R [--threads N]
    python bench/methods.py parquet-read FILE --how batches|rowgroups|table [--threads N]
    python bench/methods.py in-memory FILE.parquet OUT.parquet --ratio R
    python bench/methods.py open3d FILE.parquet --how voxel|random|uniform --param P

Each prints one JSON line (points read, points out, seconds spent inside).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

CHUNK = 1 << 20


def laz_read(path: str, layers: str, threads: int) -> dict:
    """The floor for LAZ: a bare laspy read, RGB layer only (PF 6-10) or every layer."""
    import laspy

    backend = (laspy.LazBackend.LazrsParallel,) if threads > 1 else (laspy.LazBackend.Lazrs,)
    kw = {"laz_backend": backend}
    with laspy.open(path) as r:
        pf = r.header.point_format.id
    if layers == "rgb" and pf >= 6:
        kw["decompression_selection"] = laspy.DecompressionSelection.base().decompress_rgb()
    n = 0
    with laspy.open(path, **kw) as r:
        for pts in r.chunk_iterator(CHUNK):
            n += len(pts)
    return {"points_in": n, "points_out": None, "selective": "decompression_selection" in kw}


def laz_chunks(path: str, threads: int) -> dict:
    """A lower floor for LAZ: lazrs decoding whole chunks from memory through the chunk table
    (``decompress_points_with_chunk_table``), a chunk a call at one thread, a read's chunks a call (lazrs
    spreads them over its threads) at more; what prism-stream's reader does, without the filter."""
    import os
    import struct

    if threads == 1:
        os.environ["RAYON_NUM_THREADS"] = "1"
    else:
        os.environ["RAYON_NUM_THREADS"] = str(threads)
    import lazrs

    with open(path, "rb") as f:
        head = f.read(375)
        header_size, offset, nvlr = struct.unpack_from("<HII", head, 94)
        width = struct.unpack_from("<H", head, 105)[0]
        pos, vlr = header_size, None
        for _ in range(nvlr):
            f.seek(pos)
            h = f.read(54)
            length = struct.unpack_from("<H", h, 20)[0]
            if h[2:18].rstrip(b"\0") == b"laszip encoded":
                vlr = f.read(length)
                break
            pos += 54 + length
        f.seek(offset)
        table = lazrs.read_chunk_table(f, lazrs.LazVlr(vlr))
        f.seek(offset + 8)
        n, i = 0, 0
        out = bytearray(0)
        while i < len(table):
            j, points = i, 0
            while j < len(table) and points < CHUNK:
                points += table[j][0]
                j += 1
            run = table[i:j]
            data = f.read(sum(b for _, b in run))
            if len(out) < points * width:
                out = bytearray(points * width)
            if threads == 1:
                at = put = 0
                for c in run:
                    lazrs.decompress_points_with_chunk_table(memoryview(data)[at:at + c[1]], vlr,
                                                             memoryview(out)[put:put + c[0] * width], [c])
                    at, put = at + c[1], put + c[0] * width
            else:
                lazrs.decompress_points_with_chunk_table(data, vlr, memoryview(out)[:points * width], run)
            n += points
            i = j
    return {"points_in": n, "points_out": None}


def laz_decimate(path: str, output: str, ratio: float, threads: int) -> dict:
    """The decimation floor: decode every point with laspy and write every (1/ratio)-th, as many as
    prism-stream keeps, with laspy (LAZ)."""
    import laspy

    backend = (laspy.LazBackend.LazrsParallel,) if threads > 1 else (laspy.LazBackend.Lazrs,)
    step = max(1, round(1 / ratio))
    n = kept = 0
    with laspy.open(path, laz_backend=backend) as r, \
            laspy.open(output, mode="w", header=r.header, laz_backend=backend) as w:
        for pts in r.chunk_iterator(CHUNK):
            first = (-n) % step
            part = pts[np.arange(first, len(pts), step)]  # a copy: laspy writes contiguous records only
            w.write_points(part)
            n += len(pts)
            kept += len(part)
    return {"points_in": n, "points_out": kept}


def parquet_read(path: str, how: str, threads: int) -> dict:
    """The floor for Parquet: every column, streamed in batches or read whole."""
    import pyarrow.parquet as pq

    # pre_buffer=False: with pre-buffering (pyarrow's default), a whole-file iter_batches keeps about
    # the file's size allocated until it ends, so peak RSS grows with the file (1.3 GB at 100M rows)
    if how == "batches":
        n = 0
        for batch in pq.ParquetFile(path, pre_buffer=False).iter_batches(batch_size=CHUNK, use_threads=threads > 1):
            n += batch.num_rows
    elif how == "rowgroups":
        f, n = pq.ParquetFile(path, pre_buffer=False), 0
        for i in range(f.num_row_groups):
            for batch in f.iter_batches(batch_size=CHUNK, row_groups=[i], use_threads=threads > 1):
                n += batch.num_rows
    else:
        n = pq.read_table(path, use_threads=threads > 1).num_rows
    return {"points_in": n, "points_out": None}


def _keys(r, g, b):
    """SPEC 1-2 (rgb, 0 quant bits, auto depth) in numpy."""
    shift = 0 if max(r.max(), g.max(), b.max()) <= 255 else 8
    return ((r.astype(np.uint32) >> shift) << 16) | ((g.astype(np.uint32) >> shift) << 8) | (b.astype(np.uint32) >> shift)


def paper_k(sizes: np.ndarray, target: int) -> int:
    """The paper's integer k*: S(k) = sum(min(n_b, k)) closest to T, ties to the smaller k."""
    ns = np.sort(sizes)
    cums = np.concatenate([[0], np.cumsum(ns)])
    ks = np.arange(1, int(ns[-1]) + 1)
    below = np.searchsorted(ns, ks, side="left")
    s = cums[below] + ks * (len(ns) - below)
    return int(ks[np.argmin(np.abs(s - target))])


def in_memory(path: str, output: str, ratio: float) -> dict:
    """The authors' approach: load everything, sort by bin key, keep up to k* per bin."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    t = time.perf_counter()
    table = pq.read_table(path)
    secs = {"load": time.perf_counter() - t}
    t = time.perf_counter()
    keys = _keys(table["red"].to_numpy(), table["green"].to_numpy(), table["blue"].to_numpy())
    order = np.argsort(keys)
    sk = keys[order]
    starts = np.flatnonzero(np.concatenate([[True], sk[1:] != sk[:-1]]))
    sizes = np.diff(np.append(starts, len(sk)))
    n = len(keys)
    target = int(np.floor(ratio * n + 0.5))
    k = paper_k(sizes, target)
    rank = np.arange(n) - np.repeat(starts, sizes)
    keep = np.sort(order[rank < k])
    secs["sample"] = time.perf_counter() - t
    t = time.perf_counter()
    pq.write_table(table.take(pa.array(keep)), output, compression="zstd")
    secs["write"] = time.perf_counter() - t
    return {"points_in": n, "points_out": int(len(keep)), "k": k, "bins": int(len(sizes)), "target": target,
            "seconds": {a: round(b, 4) for a, b in secs.items()}}


def open3d_down(path: str, how: str, param: float) -> dict:
    """Open3D's downsamplers on the whole cloud in memory (nothing is written)."""
    import open3d as o3d
    import pyarrow.parquet as pq

    t = time.perf_counter()
    table = pq.read_table(path, columns=["x", "y", "z", "red", "green", "blue"])
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.column_stack([table[c].to_numpy() for c in "xyz"]))
    rgb = np.column_stack([table[c].to_numpy() for c in ("red", "green", "blue")]).astype(np.float64) / 65535.0
    pcd.colors = o3d.utility.Vector3dVector(rgb)
    n = len(table)
    del table, rgb
    secs = {"load": time.perf_counter() - t}
    t = time.perf_counter()
    if how == "voxel":
        out = pcd.voxel_down_sample(voxel_size=param)
    elif how == "random":
        out = pcd.random_down_sample(sampling_ratio=param)
    else:
        out = pcd.uniform_down_sample(every_k_points=int(param))
    secs["sample"] = time.perf_counter() - t
    return {"points_in": n, "points_out": len(out.points), "open3d": o3d.__version__,
            "seconds": {a: round(b, 4) for a, b in secs.items()}}


def voxel_size_for(n: int, target: int) -> float:
    """A voxel size whose voxel_down_sample gives about ``target`` points on the tiled pf7 input of n points.

    Estimated from the source tiles (each tile's occupancy, times the number
    of tiles), so it costs a second, not a pass over the big file.
    """
    from make_data import IGN, LION, REAL, _template

    templates = [_template(REAL / LION, 7), _template(REAL / IGN, 7)]
    per_cycle = sum(len(t) for t in templates)
    xyz = [np.column_stack([np.asarray(t.x), np.asarray(t.y), np.asarray(t.z)]) for t in templates]

    def occupied(p: np.ndarray, v: float) -> int:
        cell = np.floor((p - p.min(axis=0)) / v).astype(np.int64)
        span = cell.max(axis=0) + 1
        return len(np.unique((cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]))

    def count(v: float) -> float:
        return (n / per_cycle) * sum(occupied(p, v) for p in xyz)

    lo, hi = 1e-3, 100.0
    for _ in range(30):
        mid = (lo * hi) ** 0.5
        if count(mid) > target:
            lo = mid
        else:
            hi = mid
    return float((lo * hi) ** 0.5)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("laz-read")
    p.add_argument("path")
    p.add_argument("--layers", choices=["rgb", "all"], required=True)
    p.add_argument("--threads", type=int, default=1)
    p = sub.add_parser("laz-chunks")
    p.add_argument("path")
    p.add_argument("--threads", type=int, default=1)
    p = sub.add_parser("laz-decimate")
    p.add_argument("path")
    p.add_argument("output")
    p.add_argument("--ratio", type=float, required=True)
    p.add_argument("--threads", type=int, default=1)
    p = sub.add_parser("parquet-read")
    p.add_argument("path")
    p.add_argument("--how", choices=["batches", "rowgroups", "table"], required=True)
    p.add_argument("--threads", type=int, default=1)
    p = sub.add_parser("in-memory")
    p.add_argument("path")
    p.add_argument("output")
    p.add_argument("--ratio", type=float, required=True)
    p = sub.add_parser("open3d")
    p.add_argument("path")
    p.add_argument("--how", choices=["voxel", "random", "uniform"], required=True)
    p.add_argument("--param", type=float, required=True)
    a = ap.parse_args(argv)
    t = time.perf_counter()
    if a.cmd == "laz-read":
        out = laz_read(a.path, a.layers, a.threads)
    elif a.cmd == "laz-chunks":
        out = laz_chunks(a.path, a.threads)
    elif a.cmd == "laz-decimate":
        out = laz_decimate(a.path, a.output, a.ratio, a.threads)
    elif a.cmd == "parquet-read":
        out = parquet_read(a.path, a.how, a.threads)
    elif a.cmd == "in-memory":
        out = in_memory(a.path, a.output, a.ratio)
    else:
        out = open3d_down(a.path, a.how, a.param)
    out["inner_seconds"] = round(time.perf_counter() - t, 4)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
