"""E57 in (ASTM E2807, terrestrial laser scanners), through pye57 (libE57Format).

Every scan of the file is read, in scan order, as one cloud; a point's
record index runs across the scans. Points stream through libE57's
compressed-vector reader a chunk at a time, so a scan is never loaded whole
(a range that starts inside a scan reads that scan from its start and
discards what comes before).

- Coordinates: ``cartesianX/Y/Z`` become ``x, y, z`` (float64) in the
  file's global frame: each scan's pose (rotation, translation) is applied,
  as scans of one file are meant to be combined. Every other point field is
  kept under its E57 name.
- Colors: ``colorRed/Green/Blue`` at the range each scan declares
  (``colorLimits``, else the prototype's integer bounds) are mapped to 8 bits:
  a 256-value range is ``v - min``; the full 16-bit range ``0..65535`` is
  ``v >> 8`` (SPEC 1's 16-bit rule); any other range is SPEC 1's float rule
  on ``(v - min) / (max - min)``. Values outside the declared range are an
  input error. The output keeps the file's own color values.
- A scan without color, or scans whose fields differ, cannot join one
  colored cloud: a one-line refusal.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np
import pyarrow as pa

from ..errors import CorruptInput, NoColorError, UnsupportedFormat, UsageError
from .base import ColorChunk, PointChunk, Source, columns_to_arrow
from .guard import reading

COLORS = ("colorRed", "colorGreen", "colorBlue")
XYZ = ("cartesianX", "cartesianY", "cartesianZ")


def _pye57(path: str | None = None):
    try:
        import pye57
    except ImportError:  # an optional dependency: a missing extra, as for --dask or s3:// (exit 2)
        raise UsageError("reading E57 needs pye57: pip install '.[e57]' in the clone (or pip install pye57)",
                         path) from None
    return pye57


def _field_dtype(node, lib) -> np.dtype | None:
    t = node.type()
    if t == lib.NodeType.E57_SCALED_INTEGER:
        return np.dtype("f8")
    if t == lib.NodeType.E57_FLOAT:
        return np.dtype("f4" if lib.FloatNode(node).precision() == lib.FloatPrecision.E57_SINGLE else "f8") \
            if hasattr(lib, "FloatPrecision") else np.dtype("f8")
    if t == lib.NodeType.E57_INTEGER:
        n = lib.IntegerNode(node)
        lo, hi = n.minimum(), n.maximum()
        for code in ("u1", "u2", "u4") if lo >= 0 else ("i1", "i2", "i4"):
            info = np.iinfo(code)
            if info.min <= lo and hi <= info.max:
                return np.dtype(code)
        return np.dtype("i8")
    return None  # strings and blobs: not point data we can carry


def color_map(values: np.ndarray, lo: float, hi: float, path: str) -> np.ndarray:
    """8-bit channel from E57 color values declared in [lo, hi] (see the module docstring)."""
    v = np.asarray(values)
    if v.size and (v.min() < lo or v.max() > hi):
        bad = v[(v < lo) | (v > hi)][0]
        raise CorruptInput(f"color value {bad} outside the declared range {lo:g}..{hi:g}", path)
    if hi - lo == 255:
        return (v - lo).astype(np.uint8)
    if lo == 0 and hi == 65535:
        return (v.astype(np.uint32) >> 8).astype(np.uint8)
    if hi <= lo:
        return np.zeros(v.shape, np.uint8)
    c = (v.astype(np.float64) - lo) / (hi - lo)
    return np.minimum(np.floor(c * 255.0), 255).astype(np.uint8)


class E57PointChunk(PointChunk):
    def __init__(self, ordinal: int, start: int, columns: dict, rgb):
        self.ordinal = ordinal
        self.start = start
        self.columns = columns
        self.rgb = rgb

    def to_arrow(self, mask: np.ndarray | None = None) -> pa.RecordBatch:
        return columns_to_arrow(self.columns, mask)


class E57Source(Source):
    format = "e57"
    spills = True  # point chunks implement take; the default spill state (the chunk) pickles

    def __init__(self, path: str, ordinal: int, **_):
        self.path = path
        self.ordinal = ordinal
        self.pye57 = _pye57(path)
        lib = self.pye57.libe57
        with reading(path, "not a readable E57 file"):
            e57 = self.pye57.E57(path)
            self.scans = []
            fields = None
            for i in range(e57.scan_count):
                header = e57.get_header(i)
                proto = lib.StructureNode(header.points.prototype())
                found = {}
                for j in range(proto.childCount()):
                    node = proto.get(j)
                    dt = _field_dtype(node, lib)
                    if dt is not None:
                        found[node.elementName()] = (dt, node)
                if not all(c in found for c in COLORS):
                    raise NoColorError(f"scan {i} has no colorRed/Green/Blue, so its points cannot be binned", path)
                if fields is not None and list(found) != list(fields):
                    raise UnsupportedFormat(f"scan {i}'s point fields differ from scan 0's; one cloud needs one "
                                            "layout", path)
                fields = fields or {n: dt for n, (dt, _) in found.items()}
                self.scans.append({"count": int(header.point_count), "limits": self._limits(header, found, lib),
                                   "pose": self._pose(header)})
            e57.close()
        self.fields = fields or {}
        self.color_fields = COLORS
        self.count = sum(s["count"] for s in self.scans)
        if not self.scans:
            raise NoColorError("E57 holds no scans, so no points to bin", path)

    @staticmethod
    def _limits(header, found, lib) -> list:
        node = header.node
        out = []
        for name in COLORS:
            key = name  # colorLimits holds colorRedMinimum, colorRedMaximum...
            if node.isDefined("colorLimits"):
                lim = node["colorLimits"]
                out.append((float(lim[key + "Minimum"].value()), float(lim[key + "Maximum"].value())))
            else:
                dt, proto = found[name]
                n = lib.IntegerNode(proto) if proto.type() == lib.NodeType.E57_INTEGER else None
                out.append((float(n.minimum()), float(n.maximum())) if n else (0.0, 1.0))
        return out

    @staticmethod
    def _pose(header):
        if not header.has_pose():
            return None
        return np.asarray(header.rotation_matrix, dtype=np.float64), np.asarray(header.translation, dtype=np.float64)

    def _scan_chunks(self, e57, index: int, names, chunk_size: int) -> Iterator[dict]:
        lib = self.pye57.libe57
        header = e57.get_header(index)
        arrays = {n: np.empty(chunk_size, self.fields[n]) for n in names}
        buffers = lib.VectorSourceDestBuffer()
        for n in names:
            buffers.append(lib.SourceDestBuffer(e57.image_file, n, arrays[n], chunk_size, True, True))
        reader = header.points.reader(buffers)
        try:
            while True:
                got = reader.read()
                if not got:
                    return
                yield {n: arrays[n][:got].copy() for n in names}
        finally:
            reader.close()

    def _chunks(self, chunk_size: int, start: int, stop: int | None, names) -> Iterator[tuple[int, int, dict]]:
        stop = self.count if stop is None else min(stop, self.count)
        if stop <= start:
            return
        chunk_size = max(1, min(chunk_size, 1 << 20))
        with reading(self.path):
            e57 = self.pye57.E57(self.path)
            try:
                pos = 0
                for i, scan in enumerate(self.scans):
                    end = pos + scan["count"]
                    if end > start and pos < stop:
                        seen = pos
                        for cols in self._scan_chunks(e57, i, names, chunk_size):
                            n = len(next(iter(cols.values())))
                            a, b = max(start - seen, 0), min(stop - seen, n)
                            if b > a:
                                yield i, seen + a, {k: v[a:b] for k, v in cols.items()}
                            seen += n
                            if seen >= min(end, stop):
                                break
                        if seen < min(end, stop):
                            raise CorruptInput(f"scan {i} ends after {seen - pos} of its {scan['count']} points",
                                               self.path)
                    pos = end
            finally:
                e57.close()

    def _rgb(self, scan: int, cols: dict) -> tuple:
        return tuple(color_map(cols[n], lo, hi, self.path) for n, (lo, hi) in zip(COLORS, self.scans[scan]["limits"]))

    def color_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[ColorChunk]:
        for scan, pos, cols in self._chunks(chunk_size, start, stop, COLORS):
            yield ColorChunk(pos, self._rgb(scan, cols))

    def point_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[E57PointChunk]:
        for scan, pos, cols in self._chunks(chunk_size, start, stop, list(self.fields)):
            yield E57PointChunk(self.ordinal, pos, self._columns(scan, cols), self._rgb(scan, cols))

    def _columns(self, scan: int, cols: dict) -> dict:
        out = {}
        if all(n in cols for n in XYZ):
            xyz = np.stack([cols[n] for n in XYZ], axis=1).astype(np.float64)
            pose = self.scans[scan]["pose"]
            if pose is not None:
                xyz = xyz @ pose[0].T + pose[1]
            out.update(x=xyz[:, 0].copy(), y=xyz[:, 1].copy(), z=xyz[:, 2].copy())
        for n, v in cols.items():
            if n not in XYZ or "x" not in out:
                out[n] = v
        return out

    def arrow_schema(self) -> pa.Schema:
        empty = {n: np.zeros(0, dt) for n, dt in self.fields.items()}
        return E57PointChunk(self.ordinal, 0, self._columns(0, empty), ()).to_arrow().schema

    def describe(self) -> dict:
        return {"format": "e57", "scans": len(self.scans), "points_per_scan": [s["count"] for s in self.scans],
                "color_limits": [s["limits"] for s in self.scans], "fields": [str(n) for n in self.fields],
                "streamed": True}
