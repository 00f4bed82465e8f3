"""Coordinate reference systems across formats, and the GeoParquet 1.1 ``geo`` metadata.

Where a CRS comes from: a LAS/LAZ header (WKT or GeoTIFF keys, parsed by
laspy through pyproj); a Parquet file's ``geo`` metadata (GeoParquet: the
primary column's ``crs``, PROJJSON; PDAL writes one); or the ``crs_wkt`` a
prism-stream Parquet kept from its LAS source. Where it goes: Parquet output
records it in ``prism_stream_source`` (WKT and PROJJSON) always, and in a
GeoParquet ``geo`` key when the output has a geometry column (``--geometry``
adds one: WKB ``Point Z``; a GeoParquet input's own geometry columns are
kept). GeoParquet needs a geometry column to name as ``primary_column``, so
an output without one is not labelled GeoParquet. LAS output gets a WKT VLR.

A CRS that cannot describe the coordinates (a geographic CRS on coordinates
beyond +-360 / +-90, as PDAL writes EPSG:4326 for a LAS file that had no
CRS) is not carried on: the sink says so.
"""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa

GEO_KEY = b"geo"
GEOMETRY = "geometry"
GEOPARQUET_VERSION = "1.1.0"
_WKB_POINT_Z = 1001  # ISO WKB Point Z
_WKB_POINT = 1
_EWKB_Z = 0x80000000


def _pyproj():
    import pyproj

    return pyproj


def file_geo(metadata: dict | None) -> dict | None:
    """The parsed ``geo`` key of a Parquet file's key-value metadata, if any and valid JSON."""
    raw = (metadata or {}).get(GEO_KEY)
    if not raw:
        return None
    try:
        geo = json.loads(raw)
    except ValueError:
        return None
    if not (isinstance(geo, dict) and isinstance(geo.get("columns"), dict)):
        return None
    # what the rest reads of it, of the types the spec gives (a list as the primary column failed as unhashable)
    if not isinstance(geo.get("primary_column", ""), str) or not all(
            isinstance(k, str) and isinstance(v, dict) for k, v in geo["columns"].items()):
        return None
    return geo


def geo_crs(geo: dict | None):
    """The primary column's CRS of a ``geo`` metadata dict (absent: OGC:CRS84, as the spec says; null: None)."""
    if not geo:
        return None
    col = geo["columns"].get(geo.get("primary_column")) or {}
    pyproj = _pyproj()
    if "crs" not in col:
        return pyproj.CRS.from_user_input("OGC:CRS84")
    if col["crs"] is None:
        return None
    try:
        return pyproj.CRS.from_json_dict(col["crs"]) if isinstance(col["crs"], dict) \
            else pyproj.CRS.from_user_input(col["crs"])
    except Exception:  # noqa: BLE001 - an unreadable CRS is reported as none (the sink says so)
        return None


def source_crs(source):
    """A source's CRS as a pyproj CRS, or None (unknown, or a format without one)."""
    crs = getattr(source, "crs", None)
    return crs() if callable(crs) else None


def common_crs(sources):
    """(crs, why_not): the inputs' CRS when they agree, else (None, a sentence saying why none is written)."""
    found = [source_crs(s) for s in sources]
    known = [c for c in found if c is not None]
    if not known:
        return None, None
    first = known[0]
    if len(known) != len(found) or any(c != first for c in known[1:]):
        return None, "the inputs do not share one CRS, so none is written"
    return first, None


def implausible(crs, lo, hi) -> str | None:
    """Why ``crs`` cannot be the CRS of coordinates in [lo, hi] (x, y), or None."""
    if crs is None or not crs.is_geographic:
        return None
    if not (np.all(np.isfinite(lo[:2])) and np.all(np.isfinite(hi[:2]))):
        return None
    if max(abs(lo[0]), abs(hi[0])) > 360 or max(abs(lo[1]), abs(hi[1])) > 90:
        return (f"the input's CRS {crs.name!r} is geographic (degrees) but the coordinates reach "
                f"{max(abs(lo[0]), abs(hi[0])):.0f}, {max(abs(lo[1]), abs(hi[1])):.0f}; that CRS is not written")
    return None


def geo_metadata(columns: dict, primary: str) -> bytes:
    """The ``geo`` key: ``columns`` maps each WKB geometry column's name to its GeoParquet entry."""
    return json.dumps({"version": GEOPARQUET_VERSION, "primary_column": primary, "columns": columns},
                      sort_keys=True).encode()


def point_column(crs) -> dict:
    """The GeoParquet entry of a WKB ``Point Z`` column in ``crs`` (None: unknown, written as null)."""
    return {"encoding": "WKB", "geometry_types": ["Point Z"], "edges": "planar",
            "crs": crs.to_json_dict() if crs is not None else None}


def wkb_points(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> pa.Array:
    """ISO WKB ``Point Z`` of each point (little-endian, 29 bytes each) as an Arrow binary array."""
    n = len(x)
    rec = np.zeros(n, dtype=[("order", "u1"), ("type", "<u4"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    rec["order"], rec["type"] = 1, _WKB_POINT_Z
    rec["x"], rec["y"], rec["z"] = x, y, z
    data = pa.py_buffer(rec.tobytes())
    offsets = pa.py_buffer(np.arange(0, 29 * n + 1, 29, dtype=np.int32).tobytes())
    return pa.Array.from_buffers(pa.binary(), n, [None, offsets, data])


def wkb_xyz(column: pa.Array, name: str, path: str) -> list[np.ndarray]:
    """x, y, z of a WKB point column: ISO (Point, Point Z) or EWKB (a Z flag, an SRID or not: PostGIS's), 2D
    (z = 0) or with Z, little or big endian, each row read by its own byte order and type, so any run of rows
    reads alike (a batch mixing them failed or not with the chunk size)."""
    from ..errors import CorruptInput

    if column.null_count:
        raise CorruptInput(f"geometry column {name!r} has {column.null_count} points with no geometry (null)", path)
    if isinstance(column, pa.ChunkedArray):
        column = column.combine_chunks()
    column = column.cast(pa.large_binary())
    n = len(column)
    if n == 0:
        return [np.zeros(0), np.zeros(0), np.zeros(0)]
    offsets = np.frombuffer(column.buffers()[1], dtype=np.int64, count=n + 1, offset=column.offset * 8)
    data = np.frombuffer(column.buffers()[2], dtype=np.uint8)
    block = 1 << 16  # rows a gather (its index array: 12 MiB)
    parts = [_wkb_rows(data, offsets[a:a + block + 1], a, name, path) for a in range(0, n, block)]
    return [np.concatenate([p[i] for p in parts]) for i in range(3)]


def _wkb_rows(data: np.ndarray, offsets: np.ndarray, first: int, name: str, path: str) -> list[np.ndarray]:
    """:func:`wkb_xyz` of the rows whose bytes start at ``offsets[:-1]`` (the first is row ``first``)."""
    from ..errors import CorruptInput

    start, sizes = offsets[:-1], np.diff(offsets)
    if np.any(sizes < 5):
        raise CorruptInput(f"geometry column {name!r} holds something other than WKB points (a row of "
                           f"{int(sizes[sizes < 5][0])} bytes)", path)

    size = int(sizes[0])
    whole = data[start[0]:start[0] + size * len(sizes)].reshape(-1, size) if np.all(sizes == size) else None

    def rows_of(at: np.ndarray, width: int) -> np.ndarray:  # each row's ``width`` bytes from ``at`` (padded)
        if whole is not None and width <= size - int(at[0] - start[0]):  # rows of one size: slices of them
            a = int(at[0] - start[0])
            return np.ascontiguousarray(whole[:, a:a + width])
        return np.ascontiguousarray(data[np.minimum(at[:, None] + np.arange(width), len(data) - 1)])

    order = data[start]
    if not np.all(order <= 1):
        raise CorruptInput(f"geometry column {name!r}: invalid WKB byte order {int(order[order > 1][0])}", path)
    little = order == 1
    head = rows_of(start + 1, 4)
    kind = np.where(little, head.view("<u4").ravel(), head.view(">u4").ravel()).astype(np.int64)
    iso_z = kind == _WKB_POINT_Z
    ewkb = ((kind & 0x1FFFFFFF) == _WKB_POINT) & ((kind & 0x40000000) == 0)  # ISO Point too; EWKB without M
    if not np.all(iso_z | ewkb):
        bad = kind[~(iso_z | ewkb)][0]
        raise CorruptInput(f"geometry column {name!r} holds WKB geometry type {int(bad)}, not a point (Point or "
                           "Point Z)", path)
    has_z = iso_z | ((kind & _EWKB_Z) != 0)
    srid = ewkb & ((kind & 0x20000000) != 0)
    want = 5 + 4 * srid + np.where(has_z, 24, 16)
    if not np.all(sizes == want):
        bad = int(np.flatnonzero(sizes != want)[0])
        raise CorruptInput(f"geometry column {name!r} holds something other than WKB points (row {first + bad}: "
                           f"{int(sizes[bad])} bytes for a point of {int(want[bad])})", path)
    raw = rows_of(start + 5 + 4 * srid, 24 if has_z.any() else 16)
    coords = np.where(little[:, None], raw.view("<f8"), raw.view(">f8")).astype(np.float64)
    z = np.where(has_z, coords[:, 2], 0.0) if coords.shape[1] == 3 else np.zeros(len(coords))
    return [coords[:, 0].copy(), coords[:, 1].copy(), z]
