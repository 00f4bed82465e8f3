"""Build the benchmark inputs by tiling real clouds side by side.

    python bench/make_data.py --sizes 10M 20M 100M

For every size N it writes, under bench/data/ (git-ignored):

- ``pf7_<N>.laz``: LAS 1.4 point format 7, tiles alternating the Potree lion
  (COPC, PF7) and the IGN LiDAR HD excerpt (PF8 converted to PF7: NIR and
  extra bytes dropped). Pass one of prism-stream can decompress only the
  RGB layer of these (LAZ point formats 6 to 10).
- ``pf3_<N>.laz``: LAS 1.2 point format 3, tiles of Autzen. LAZ PF 0-5
  compresses whole records, so pass one decodes everything.
- ``pf7_<N>.parquet``: the same points as ``pf7_<N>.laz`` as Parquet
  (x, y, z float64; red, green, blue, intensity uint16; return_number,
  number_of_returns, classification uint8; gps_time float64), row groups
  of 1,000,000 rows, zstd.

Every tile is an unmodified copy of its source's points, shifted in x/y onto
its own cell of a square grid so that tiles never overlap; the last tile is
cut to reach exactly N points. Writing streams one tile at a time, so memory
stays at a few tiles whatever N is. A file that already exists with the
right point count is kept (the script is idempotent); outputs are written
to a temporary name and renamed when complete.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import laspy
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"
REAL = HERE.parent / "tests" / "data" / "real"  # the committed real clouds (tests/data/README.md)

LION = "potree__lion_takanawa.copc.laz"
IGN = "pdal__las_with_several_extra_byte_bloc.laz"
AUTZEN = "pdal__autzen_trim.las"

SCALE = 0.01           # every source is stored at 0.01 with zero offsets, so raw integers tile exactly
MARGIN = 1000          # 10 m (raw units) between tiles
ROW_GROUP = 1_000_000
PARQUET_COLUMNS = ("red", "green", "blue", "intensity", "return_number", "number_of_returns",
                   "classification", "gps_time")


def parse_size(text: str) -> int:
    """'20M' -> 20_000_000, '500k' -> 500_000, '1234' -> 1234."""
    t = text.strip().lower().replace("_", "")
    mult = {"k": 10**3, "m": 10**6, "g": 10**9}.get(t[-1:], 1)
    return int(float(t[:-1] if mult != 1 else t) * mult)


def size_label(n: int) -> str:
    for unit, v in (("G", 10**9), ("M", 10**6), ("k", 10**3)):
        if n % v == 0:
            return f"{n // v}{unit}"
    return str(n)


def paths(n: int) -> dict:
    label = size_label(n)
    return {"pf7_laz": DATA / f"pf7_{label}.laz", "pf3_laz": DATA / f"pf3_{label}.laz",
            "parquet": DATA / f"pf7_{label}.parquet"}


def _template(path: Path, point_format: int) -> laspy.ScaleAwarePointRecord:
    """The source's points in ``point_format``, standard dimensions only, x/y moved to start at 0."""
    las = laspy.read(path)
    h = las.header
    if not np.allclose(h.scales, SCALE) or not np.allclose(h.offsets, 0):
        raise SystemExit(f"{path}: expected scales {SCALE} and zero offsets, got {h.scales} {h.offsets}")
    fmt = laspy.PointFormat(point_format)
    rec = laspy.ScaleAwarePointRecord.zeros(len(las.points), point_format=fmt,
                                            scales=np.full(3, SCALE), offsets=np.zeros(3))
    for name in fmt.dimension_names:
        rec[name] = las.points[name]
    rec["X"] = rec["X"] - rec["X"].min()
    rec["Y"] = rec["Y"] - rec["Y"].min()
    return rec


def _extent(rec) -> tuple[int, int]:
    return int(rec["X"].max()) + 1, int(rec["Y"].max()) + 1


def tiles(templates: list, n: int):
    """Yield (tile index, shifted record) until exactly n points have been produced."""
    sizes = [len(t) for t in templates]
    per_cycle = sum(sizes)
    count = math.ceil(n / per_cycle) * len(templates)
    cols = math.ceil(math.sqrt(count))
    cell_x = max(_extent(t)[0] for t in templates) + MARGIN
    cell_y = max(_extent(t)[1] for t in templates) + MARGIN
    done, i = 0, 0
    while done < n:
        t = templates[i % len(templates)]
        take = min(len(t), n - done)
        arr = t.array[:take].copy()
        arr["X"] += np.int32((i % cols) * cell_x)
        arr["Y"] += np.int32((i // cols) * cell_y)
        yield i, laspy.ScaleAwarePointRecord(arr, t.point_format, t.scales, t.offsets)
        done += take
        i += 1


def las_count(path: Path) -> int | None:
    try:
        with laspy.open(path) as r:
            return int(r.header.point_count)
    except Exception:  # noqa: BLE001 - unreadable or half-written: rebuild it
        return None


def parquet_count(path: Path) -> int | None:
    try:
        return int(pq.ParquetFile(path).metadata.num_rows)
    except Exception:  # noqa: BLE001
        return None


class LazOut:
    def __init__(self, path: Path, version: str, point_format: int):
        self.path, self.tmp = path, path.with_suffix(".tmp.laz")
        header = laspy.LasHeader(version=version, point_format=point_format)
        header.scales = np.full(3, SCALE)
        header.offsets = np.zeros(3)
        header.generating_software = "prism-stream bench/make_data.py"
        self.writer = laspy.open(self.tmp, mode="w", header=header, do_compress=True,
                                 laz_backend=(laspy.LazBackend.LazrsParallel, laspy.LazBackend.Lazrs))

    def write(self, rec) -> None:
        self.writer.write_points(rec)

    def close(self) -> None:
        self.writer.close()
        os.replace(self.tmp, self.path)


class ParquetOut:
    """Re-chunks the tile stream into row groups of exactly ROW_GROUP rows."""

    def __init__(self, path: Path):
        self.path, self.tmp = path, path.with_suffix(".tmp.parquet")
        fields = [pa.field(c, pa.float64()) for c in "xyz"]
        self.pending: list[dict] = []
        self.held = 0
        self.writer = None
        self.fields = fields

    def write(self, rec) -> None:
        cols = {"x": np.asarray(rec.x), "y": np.asarray(rec.y), "z": np.asarray(rec.z)}
        for c in PARQUET_COLUMNS:
            cols[c] = np.asarray(rec[c])
        self.pending.append(cols)
        self.held += len(rec)
        while self.held >= ROW_GROUP:
            self._flush(ROW_GROUP)

    def _flush(self, rows: int) -> None:
        merged = {k: np.concatenate([p[k] for p in self.pending]) for k in self.pending[0]}
        table = pa.table({k: v[:rows] for k, v in merged.items()})
        if self.writer is None:
            self.writer = pq.ParquetWriter(self.tmp, table.schema, compression="zstd")
        self.writer.write_table(table, row_group_size=rows)
        rest = {k: v[rows:] for k, v in merged.items()}
        self.held -= rows
        self.pending = [rest] if self.held else []

    def close(self) -> None:
        if self.held:
            self._flush(self.held)
        self.writer.close()
        os.replace(self.tmp, self.path)


def synthetic_tile(path, n: int, seed: int, sixteen_bit: bool = False, fmt: int = 3) -> None:
    """A generated LAS tile: a few hundred colors plus noise, like a colorized survey."""
    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(point_format=fmt, version="1.2")
    header.scales = [0.01] * 3
    header.offsets = [0, 0, 0]
    palette = np.random.default_rng(1).integers(20, 236, (300, 3))
    with laspy.open(path, mode="w", header=header) as w:
        for a in range(0, n, 2_000_000):
            m = min(2_000_000, n - a)
            pts = laspy.ScaleAwarePointRecord.zeros(m, header=header)
            pts.x = rng.uniform(0, 1000, m)
            pts.y = rng.uniform(0, 1000, m)
            pts.z = rng.uniform(0, 50, m)
            rgb = np.clip(palette[rng.integers(0, 300, m)] + rng.normal(0, 4, (m, 3)), 0, 255).astype(np.uint16)
            if sixteen_bit:
                rgb = rgb * 257
            pts.red, pts.green, pts.blue = rgb.T
            pts.intensity = rng.integers(0, 65535, m)
            w.write_points(pts)


def build(n: int, log=print, inputs=None) -> dict:
    """Make the inputs of size n (all three, or those named in ``inputs``; skipping those already there); return
    their paths."""
    DATA.mkdir(parents=True, exist_ok=True)
    p = {k: v for k, v in paths(n).items() if inputs is None or k in inputs}
    todo_pf7 = "pf7_laz" in p and las_count(p["pf7_laz"]) != n
    todo_pq = "parquet" in p and parquet_count(p["parquet"]) != n
    if todo_pf7 or todo_pq:
        t0 = time.perf_counter()
        templates = [_template(REAL / LION, 7), _template(REAL / IGN, 7)]
        outs = ([LazOut(p["pf7_laz"], "1.4", 7)] if todo_pf7 else []) + ([ParquetOut(p["parquet"])] if todo_pq else [])
        for _, rec in tiles(templates, n):
            for o in outs:
                o.write(rec)
        for o in outs:
            o.close()
        log(f"wrote {', '.join(str(o.path.name) for o in outs)} ({n:,} points) in {time.perf_counter() - t0:.0f} s")
    if "pf3_laz" in p and las_count(p["pf3_laz"]) != n:
        t0 = time.perf_counter()
        out = LazOut(p["pf3_laz"], "1.2", 3)
        for _, rec in tiles([_template(REAL / AUTZEN, 3)], n):
            out.write(rec)
        out.close()
        log(f"wrote {p['pf3_laz'].name} ({n:,} points) in {time.perf_counter() - t0:.0f} s")
    return p


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", nargs="+", default=["10M", "20M", "100M"], help="point counts, e.g. 1M 20M 100M")
    ap.add_argument("--inputs", nargs="+", choices=["pf7_laz", "pf3_laz", "parquet"], default=None,
                    help="build only these inputs (default: all three)")
    args = ap.parse_args(argv)
    if not REAL.is_dir():
        sys.exit(f"make_data: {REAL}: the real clouds are not there")
    for s in args.sizes:
        build(parse_size(s), inputs=args.inputs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
