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
    """x, y, z of a WKB point column: ISO or EWKB (PostGIS's, an SRID or not), 2D (z = 0), Z, M or ZM (M
    read past), little or big endian, each row by its own header, so any run of rows reads alike (a batch
    mixing them failed or not with the chunk size). A row that is no point is refused."""
    from ..errors import CorruptInput

    if column.null_count:
        raise CorruptInput(f"geometry column {name!r} has {column.null_count} points with no geometry (null)", path)
    column = _one_array(column)  # (once, for both readers)
    fast = _one_kind(column)
    if fast is not None:
        return fast
    xyz, valid, _, why = wkb_rows(column)
    if not valid.all():
        raise CorruptInput(f"geometry column {name!r} holds {why[int(np.flatnonzero(~valid)[0])]}", path)
    return [xyz[:, 0], xyz[:, 1], xyz[:, 2]]


def _one_array(column) -> pa.Array:
    """A chunked column as one array (no chunk at all: an empty one)."""
    if isinstance(column, pa.ChunkedArray):
        return column.combine_chunks() if column.num_chunks else pa.array([], pa.binary())
    return column


def _one_kind(column) -> list | None:
    """x, y, z of a column of little-endian ISO Point Z (or 2D Point) rows alone, as most files hold them, in a
    few vectorised steps; None for any other column (:func:`wkb_rows` reads those row by row)."""
    column = _one_array(column)
    if not pa.types.is_binary(column.type) or len(column) == 0:
        return None
    n = len(column)
    offsets = np.frombuffer(column.buffers()[1], dtype=np.int32, count=n + 1, offset=column.offset * 4)
    size = int(offsets[1] - offsets[0])
    if size not in (21, 29) or int(offsets[-1] - offsets[0]) != size * n or not np.all(np.diff(offsets) == size):
        return None
    raw = np.frombuffer(column.buffers()[2], dtype=np.uint8)[offsets[0]:offsets[-1]].reshape(n, size)
    kind = np.ascontiguousarray(raw[:, 1:5]).view("<u4").ravel()
    if not (np.all(raw[:, 0] == 1) and np.all(kind == (_WKB_POINT_Z if size == 29 else _WKB_POINT))):
        return None
    coords = np.ascontiguousarray(raw[:, 5:]).view("<f8")
    return [coords[:, 0].copy(), coords[:, 1].copy(), coords[:, 2].copy() if size == 29 else np.zeros(n)]


_WHY = ("no WKB point: a row shorter than a WKB header", "no WKB point: an invalid byte order",
        "WKB geometry other than points (Point, Point Z, M or ZM)",
        "no WKB point: a row whose length is not its type's")


def wkb_rows(column: pa.Array) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """(xyz (n, 3), points, z, why) of a WKB column's rows: ``points`` marks the rows that are WKB points
    (the rest, nulls and other geometries, hold NaN), ``z`` those with a Z, ``why`` says what each other row
    is (by :data:`_WHY`; None for points and nulls). The one reader of WKB points of the sampler and of
    ``check``."""
    column = _one_array(column).cast(pa.large_binary())
    n = len(column)
    xyz, points, has_z = np.full((n, 3), np.nan), np.zeros(n, bool), np.zeros(n, bool)
    why: list = [None] * n
    if n == 0:
        return xyz, points, has_z, why
    offsets = np.frombuffer(column.buffers()[1], dtype=np.int64, count=n + 1, offset=column.offset * 8)
    data = np.frombuffer(column.buffers()[2], dtype=np.uint8) if column.buffers()[2] is not None \
        else np.zeros(0, np.uint8)
    if not len(data):  # no bytes at all (nulls, empty rows): one to gather from, never a point's
        data = np.zeros(1, np.uint8)
    nulls = column.is_null().to_numpy(zero_copy_only=False)
    block = 1 << 16  # rows a gather (its index array: 12 MiB)
    for a in range(0, n, block):
        b = min(n, a + block)
        _wkb_block(data, offsets[a:b + 1], nulls[a:b], (xyz[a:b], points[a:b], has_z[a:b], why, a))
    return xyz, points, has_z, why


def _wkb_block(data: np.ndarray, offsets: np.ndarray, nulls: np.ndarray, out: tuple) -> None:
    """:func:`wkb_rows` of the rows whose bytes start at ``offsets[:-1]``, into ``out`` = (xyz, points, z, why,
    the first row's index in ``why``)."""
    xyz, points, has_z, why, first = out
    start, sizes = offsets[:-1], np.diff(offsets)
    size = int(sizes[0])
    whole = data[start[0]:start[0] + size * len(sizes)].reshape(-1, size) if size and np.all(sizes == size) \
        else None  # (rows of no bytes, nulls or empty: no slices of them)

    def rows_of(at: np.ndarray, width: int) -> np.ndarray:  # each row's ``width`` bytes from ``at`` (padded)
        a = int(at[0] - start[0])
        if whole is not None and width <= size - a and np.all(at - start == a):  # one layout: slices
            return np.ascontiguousarray(whole[:, a:a + width])
        return np.ascontiguousarray(data[np.clip(at[:, None] + np.arange(width), 0, len(data) - 1)])

    short = sizes < 5
    order = data[np.clip(start, 0, len(data) - 1)]
    little = order == 1
    head = rows_of(start + 1, 4) if whole is None or size >= 5 else np.zeros((len(start), 4), np.uint8)
    kind = np.where(little, head.view("<u4").ravel(), head.view(">u4").ravel()).astype(np.int64)
    iso = np.isin(kind, (_WKB_POINT_Z, 2001, 3001))
    ewkb = (kind & 0x1FFFFFFF) == _WKB_POINT  # ISO's 2D Point too
    z = ((kind == _WKB_POINT_Z) | (kind == 3001)) | (ewkb & ((kind & _EWKB_Z) != 0))
    m = ((kind == 2001) | (kind == 3001)) | (ewkb & ((kind & 0x40000000) != 0))
    srid = ewkb & ((kind & 0x20000000) != 0)
    want = 5 + 4 * srid + 8 * (2 + z + m)
    code = np.select([short, order > 1, ~(iso | ewkb), sizes != want], [0, 1, 2, 3], -1)
    code[nulls] = -1
    ok = (code == -1) & ~nulls
    for i in np.flatnonzero(code >= 0):
        why[first + int(i)] = _WHY[int(code[i])]
    if not ok.any():
        return
    width = 24 if z.any() else 16
    raw = rows_of(start + 5 + 4 * srid, width)
    coords = np.where(little[:, None], raw.view("<f8"), raw.view(">f8")).astype(np.float64)
    xyz[ok, 0], xyz[ok, 1] = coords[ok, 0], coords[ok, 1]
    xyz[ok, 2] = np.where(z[ok], coords[ok, 2], 0.0) if width == 24 else 0.0
    points[ok] = True
    has_z[ok] = z[ok]
