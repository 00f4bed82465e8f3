"""LAS/LAZ out from points that were not LAS (Parquet, PLY, PCD, E57...).

A LAS header fixes the coordinate scale and offset before the first point,
but a good scale depends on the extent of what is written. The sink
therefore spools the kept points (Arrow IPC, in the output's folder), then
writes the LAS at commit, when the extent is known.

Choices, documented because they decide what is lost:

- Point format 7 (LAS 1.4: GPS time, 16-bit RGB), or the point format a
  prism-stream Parquet recorded from its LAS source, if that one has RGB.
- Colors: 16-bit integer Parquet columns (LAS's own fields through Parquet,
  PDAL's Red/Green/Blue) are LAS values and stored unchanged, whatever their range;
  otherwise an 8-bit decision is stored as ``v * 256`` (the LAS spec's
  16-bit scaling, which SPEC 1's ``auto`` rule reads back as the same 8-bit
  value), a 16-bit decision unchanged, floats as ``floor(255 c) * 256``.
- Scale: per axis, a power of ten as fine as the input's precision: a
  millionth (2^-20) of the extent, and for float32 coordinates no coarser
  than the float32 spacing at the extent's largest magnitude (the coarsest
  step the input itself has). That is the decimal grid PDAL's and LAStools'
  users read (0.01 for a 100 km tile, 1e-07 for a 2 m float32 model), and
  its 32-bit integers reach far past the extent around the offset (200
  times it from a float64 input, at least 6 times from a float32 one), the extent's middle rounded to a power of ten below the extent.
  Every coordinate is kept within half a step, and the run says so
  (``--scale``/``--offset`` choose another grid). A Parquet written by prism-stream from a
  LAS file carries that file's scales and offsets, which are reused, so
  LAS -> Parquet -> LAS gives back the same integers; so are those of the
  LAS file PDAL read (its ``readers.las`` metadata in a PDAL Parquet).
- PDAL's dimension names (``Intensity``, ``ReturnNumber``, ``GpsTime``,
  ``ScanAngleRank``...) and any spelling of a LAS dimension that differs only
  in case and underscores fill that dimension; a GeoParquet geometry column
  is not a dimension (the points' X, Y, Z come from it when there are no
  x, y, z columns).
- CRS: the inputs' (GeoParquet ``geo``, or the one a prism-stream Parquet
  kept from its LAS source) as a WKT VLR, unless it cannot describe the
  coordinates (a geographic CRS on projected values), which is said.
- Other numeric columns whose name is a dimension of the point format
  (``intensity``, ``classification``...) fill it when their values fit;
  every other numeric column becomes an extra-bytes dimension. Columns LAS
  cannot hold (lists, text, WKB geometry) are dropped and named in the
  provenance.
"""

from __future__ import annotations

import json
import math
import os

import laspy
import numpy as np
import pyarrow as pa

from ..errors import OutputError, PrismError, UnsupportedFormat, UsageError
from ..run import staging
from . import extrabytes
from .arrow import from_numpy, indices, to_numpy
from .base import AtomicFile, PointChunk, Sink, Source
from .columns import schema_difference, select_columns
from .conversion import SourceCursor, as_unsigned, color_fields, colors_16bit, depth_decisions
from .geo import common_crs, implausible
from .guard import describe
from .lasheader import provenance_vlr, stamp
from .parquet import point_xyz, xyz_arrays, xyz_float32, xyz_names

DEFAULT_POINT_FORMAT = 7
RGB_FORMATS = (2, 3, 5, 7, 8, 10)
SPOOL_BATCH = 1 << 20


def coordinate_scale(lo: float, hi: float, float32: bool = False) -> tuple[float, float]:
    """(scale, offset) of one axis: a decimal grid as fine as the input's precision, with room around it.

    The input's precision is a millionth of the extent (2^-20 of it), and for float32 coordinates no coarser
    than the float32 spacing at the extent's largest magnitude (the coarsest step the input itself has).
    The scale is the largest power of ten not above it, so 32-bit integers reach past the extent around
    the offset (200 times it, and at least 6 times for float32 coordinates near zero); the offset is the extent's middle, rounded to a power of ten below the extent.
    """
    span = hi - lo
    if not (span > 0 and math.isfinite(span)):
        return 0.001, float(lo) if math.isfinite(lo) else 0.0
    q = span / 2.0 ** 20 or span  # a subnormal span: its millionth underflows to 0
    if float32:
        top = max(abs(lo), abs(hi))
        q = min(q, 2.0 ** (math.floor(math.log2(top)) - 23))
    scale = _power_of_ten_below(q)
    step = max(_power_of_ten_below(span), scale)
    mid = lo + span / 2
    return scale, float(round(mid / step)) * step


def _power_of_ten_below(v: float) -> float:
    """The largest power of ten not above ``v`` (> 0), exact as a decimal (1e-7, not 1.0000000000000001e-07)."""
    e = math.floor(math.log10(v))
    if 10.0 ** (e + 1) <= v:  # log10 rounds down a hair below an exact power
        e += 1
    return float(f"1e{e}")


_PDAL_KEYS = (b"PDAL:dimension:metadata", b"PDAL:pipeline:metadata")


def _pdal_las_facts(schema: pa.Schema) -> dict | None:
    """Scales, offsets and point format of the LAS file PDAL read, from the metadata its Parquet writer keeps."""
    for f in schema:
        for key in _PDAL_KEYS:
            raw = (f.metadata or {}).get(key)
            if not raw or b"readers.las" not in raw:
                continue
            try:
                las = json.loads(raw)["root"]["readers.las"]
                las = las[0] if isinstance(las, list) else las
                return {"scales": [float(las[f"scale_{a}"]) for a in "xyz"],
                        "offsets": [float(las[f"offset_{a}"]) for a in "xyz"],
                        "point_format": int(las["dataformat_id"])}
            except (ValueError, KeyError, TypeError, IndexError):
                continue
    return None


def _source_las_facts(sources) -> dict:
    """Scales, offsets and point format of the LAS file a Parquet was made from, when it says (prism-stream's
    ``prism_stream_source`` metadata, or PDAL's ``readers.las`` metadata), and all inputs agree."""
    facts = []
    for s in sources:
        schema = s.arrow_schema() if s.format == "parquet" else pa.schema([])
        raw = (schema.metadata or {}).get(b"prism_stream_source")
        try:
            d = json.loads(raw) if raw else _pdal_las_facts(schema)
        except ValueError:
            return {}
        if not d or not {"scales", "offsets", "point_format"} <= set(d):
            return {}
        facts.append((tuple(d["scales"]), tuple(d["offsets"]), int(d["point_format"])))
    if facts and all(f == facts[0] for f in facts):
        return {"scales": facts[0][0], "offsets": facts[0][1], "point_format": facts[0][2]}
    return {}


_ALIASES = {"infrared": "nir", "scanchannel": "scanner_channel"}


def _norm(name: str) -> str:
    """A dimension name without case or underscores: PDAL's ReturnNumber is LAS's return_number, and E57's
    LAS extension ``las:pointSourceId`` its point_source_id."""
    name = name.lower()
    return (name[4:] if name.startswith("las:") else name).replace("_", "")


def _why_not_las(f: pa.Field, dt) -> str | None:
    """Why column ``f`` cannot be a LAS extra-bytes dimension, or None when it can."""
    if dt is None:
        if pa.types.is_string(f.type) or pa.types.is_large_string(f.type) or pa.types.is_binary(f.type) \
                or pa.types.is_large_binary(f.type) or pa.types.is_dictionary(f.type):
            return "LAS dimensions hold numbers, not text or bytes"
        if pa.types.is_temporal(f.type):
            return "LAS has no date or time dimension (only gps_time, a number)"
        if pa.types.is_nested(f.type):
            return "a LAS dimension is one number per point (vectors of numbers are split; this is not one)"
        return "LAS has no such number type"
    if not 0 < len(f.name.encode()) <= 32:
        return "a LAS extra-bytes name holds 1 to 32 bytes"
    if f.name.lower() in {"x", "y", "z"}:
        return "its name clashes with the LAS coordinates"
    if ":" in f.name:
        return "a LAS extra-bytes name here holds no ':' (an E57 extension's prefix)"
    return None


def _extra_type(t: pa.DataType):
    if pa.types.is_boolean(t):
        return np.dtype("u1")
    if pa.types.is_integer(t) or pa.types.is_floating(t):
        dt = np.dtype(t.to_pandas_dtype())
        return np.dtype("f4") if dt.itemsize == 2 and dt.kind == "f" else dt
    return None


class ConvertedLasSink(Sink):
    """LAS/LAZ out from non-LAS inputs; see the module docstring for what it chooses."""

    def __init__(self, path: str, sources: list[Source], provenance: dict, rank: str | None = None,
                 grid: tuple | None = None, selection: tuple | None = None):
        super().__init__(path, sources, provenance)
        self.grid = grid  # (scales, offsets or None): --scale/--offset
        if not sources:
            raise UsageError("LAS output needs at least one input", path)
        self.decisions = depth_decisions(sources, provenance)
        self.cursor = SourceCursor(sources)
        schema = sources[0].arrow_schema()
        for s in sources[1:]:
            if not s.arrow_schema().remove_metadata().equals(schema.remove_metadata()):
                raise UnsupportedFormat(f"its attributes differ from {os.path.basename(sources[0].path)}'s "
                                        f"({schema_difference(schema, s.arrow_schema())}); one LAS output needs "
                                        "one layout", s.path)
        # --keep/--drop: the columns the layout is built from (a LAS dimension no column fills is 0)
        schema = select_columns(schema, sources, selection, sources[0].path)
        geometry = getattr(sources[0], "geo", None) or {}
        self.geometry_columns = set(geometry.get("columns", {})) & set(schema.names)
        # x, y, z; a list column of three numbers; WKB points (PDAL's geometry-only GeoParquet names its own)
        self.xyz = point_xyz(schema, sources[0].path, "LAS output", sources[0])
        # float32 coordinates (PLY, PCD, E57 and Parquet floats) bound the default grid by their own spacing
        self.float32 = xyz_float32(schema, self.xyz)
        colors = set(color_fields(sources[0]))
        # 16-bit integer color columns of a Parquet file (LAS's own fields, PDAL's) hold LAS values: written
        # unchanged (other readers' types, XYZ text's for one, say nothing of the scale)
        self.colors16 = all(s.format == "parquet" for s in sources) and all(n in schema.names and (pa.types.is_uint16(schema.field(n).type)
                                                   or pa.types.is_int16(schema.field(n).type)) for n in colors)
        self.facts = _source_las_facts(sources)
        pf = self.facts.get("point_format", DEFAULT_POINT_FORMAT)
        self.point_format = pf if pf in RGB_FORMATS else DEFAULT_POINT_FORMAT
        fmt = laspy.PointFormat(self.point_format)
        standard = set(fmt.dimension_names) - {"X", "Y", "Z", "red", "green", "blue"}
        # standard: LAS dimensions filled from a column of that name; extra: (dimension, column, dtype,
        # element of a vector column or None); dropped: the column names LAS cannot hold
        self.standard, self.extra, self.dropped = [], [], []
        self.nulls = {}  # dimension -> nulls written as NaN
        skip = set(xyz_names(self.xyz)) | colors
        names = {n.lower() for n in schema.names}
        # PDAL's names (Intensity, ReturnNumber, GpsTime, ...) and other spellings of a LAS dimension
        by_norm = {_norm(d): d for d in standard}
        by_norm.update({k: v for k, v in _ALIASES.items() if v in standard})
        taken = {f.name for f in schema if f.name in standard}
        for f in schema:
            if f.name in skip:
                continue
            if f.name in self.geometry_columns:
                self.dropped.append(f.name)
                self.note(f"column {f.name!r} (WKB geometry) not written as a dimension: it holds the points' "
                          "coordinates, which LAS keeps as X, Y, Z")
                continue
            dt = _extra_type(f.type)
            dim = by_norm.get(_norm(f.name)) if f.name not in standard else None
            if dim is not None and dim not in taken and dt is not None:
                taken.add(dim)
                self.standard.append((dim, f.name))
                las_dt = fmt.dimension_by_name(dim).dtype
                if dt.kind == "f" and las_dt is not None and las_dt.kind != "f":
                    self.note(f"column {f.name!r} ({f.type}) stored in LAS dimension {dim} ({las_dt}); the run "
                              "stops if a value is not a whole number that fits")
                continue
            if f.name in standard and dt is not None and dt.kind == "f" \
                    and (fmt.dimension_by_name(f.name).dtype or np.dtype("u1")).kind != "f":
                # a float (E57's intensity in [0, 1]) in an integer dimension would be refused or rounded:
                # kept beside it instead, under a name that says so
                alias = f"{f.name}_float"
                if alias.lower() not in names and len(alias.encode()) <= 32:
                    self.extra.append((alias, f.name, dt, None))
                    self.note(f"column {f.name!r} ({f.type}) stored as LAS extra-bytes dimension {alias!r}: LAS "
                              f"{f.name} is an integer; {f.name} is left 0")
                    continue
            if f.name in standard and dt is not None:
                self.standard.append((f.name, f.name))
                las_dt = fmt.dimension_by_name(f.name).dtype  # None: a bit field, an integer of a few bits
                if las_dt is None and dt.kind in "ub" or las_dt is not None and las_dt == dt:
                    continue
                self.note(f"column {f.name!r} ({f.type}) stored in LAS dimension {f.name} "
                          f"({las_dt or 'a bit field'}); the run stops if a value does not fit")
                continue
            if pa.types.is_fixed_size_list(f.type) and _extra_type(f.type.value_type) is not None:
                dt = _extra_type(f.type.value_type)
                parts = [f"{f.name}_{j}" for j in range(f.type.list_size)]
                if all(0 < len(p.encode()) <= 32 and p.lower() not in names | set(standard) for p in parts):
                    self.extra += [(p, f.name, dt, j) for j, p in enumerate(parts)]
                    self.note(f"column {f.name!r} ({f.type}) stored as LAS extra-bytes dimensions "
                              f"{', '.join(parts)}: one dimension per element")
                    continue
                # not split, and not one number per point either
                self.dropped.append(f.name)
                self.note(f"column {f.name!r} ({f.type}) dropped: one dimension per element would need the names "
                          f"{', '.join(parts)}, and a column or dimension has one of them (or one is over 32 bytes)")
                continue
            why = _why_not_las(f, dt)
            if why:
                self.dropped.append(f.name)
                self.note(f"column {f.name!r} ({f.type}) dropped: {why}")
                continue
            self.extra.append((f.name, f.name, dt, None))
            if dt != np.dtype(f.type.to_pandas_dtype()) or pa.types.is_boolean(f.type):
                self.note(f"column {f.name!r} ({f.type}) stored as LAS extra-bytes {dt}: LAS has no {f.type}")
        if selection is not None:  # a dimension of the point format whose column --keep/--drop left out: 0
            filled = {d for d, _ in self.standard}
            zeroed = sorted({d for f in sources[0].arrow_schema() if f.name not in schema.names
                             for d in ([f.name] if f.name in standard else [by_norm.get(_norm(f.name))])
                             if d is not None and d not in filled})
            if zeroed:
                self.note(f"--{selection[0]}: {', '.join(zeroed)} written as 0 in every record (LAS point format "
                          f"{self.point_format} has them)")
        self.rank = rank
        if rank is not None:  # int64 extra bytes, filled from write()'s ranks
            self.check_rank_name(rank, [n for n, *_ in self.extra] + [d for d, _ in self.standard] + list(standard), 32)
            self.extra.append((rank, None, np.dtype(np.int64), None))
        self._note_colors(schema, tuple(color_fields(sources[0])))
        self.note_skipped_elements()
        self.lo = np.full(3, np.inf)
        self.hi = np.full(3, -np.inf)
        self.file = AtomicFile(path)
        self.spool_path = staging.new_file(path)
        self.spool_schema = None
        self.spool = None

    def _note_colors(self, schema: pa.Schema, colors) -> None:
        """Say how the input's colors become LAS 16-bit RGB, unless they are 16-bit values kept as they are."""
        decisions = set(self.decisions)
        if decisions == {"16"} or self.colors16:
            return
        rules = {"8": "8-bit values * 256, the LAS spec's scaling", "float": "floor(255 c) * 256"}
        how = "; ".join(rules.get(d, f"{d}-bit values as they are") for d in sorted(decisions))
        types = sorted({str(schema.field(n).type) for n in colors if n in schema.names})
        what = f"color field {next(iter(colors))!r} (a packed word; alpha, if any, is dropped)" if len(colors) == 1 \
            else f"color columns {', '.join(colors)} ({', '.join(types)})"
        self.note(f"{what} stored as LAS 16-bit red, green, blue ({how})")

    # -- pass two: spool the kept points --------------------------------

    def write(self, chunk: PointChunk, mask: np.ndarray, ranks: np.ndarray | None = None) -> None:
        i = self.cursor.source_index(chunk)
        if not mask.any():
            return
        src = self.sources[i]
        batch = chunk.to_arrow(mask)
        xyz = xyz_arrays(batch, self.xyz, src.path)
        for axis, v in enumerate(xyz):
            if not np.isfinite(v).all():  # the output's format cannot hold the input's points: a usage error
                raise UsageError(f"a selected point has {'xyz'[axis]} = {v[~np.isfinite(v)][0]}, which LAS, LAZ "
                                 "and COPC cannot store; write Parquet or PLY instead", src.path)
            self.lo[axis] = min(self.lo[axis], float(v.min()))
            self.hi[axis] = max(self.hi[axis], float(v.max()))
        if self.colors16:
            rgb = tuple(as_unsigned(np.asarray(c)[mask]).astype(np.uint16) for c in chunk.rgb)
        else:
            rgb = colors_16bit(tuple(np.asarray(c)[mask] for c in chunk.rgb), self.decisions[i], src.path)
        arrays = [from_numpy(v) for v in xyz] + [from_numpy(c) for c in rgb]
        names = ["x", "y", "z", "red", "green", "blue"]
        for dim, col, dt, part in [(d, c, None, None) for d, c in self.standard] + self.extra:
            if col is None:  # the rank
                arrays.append(from_numpy(np.asarray(ranks, dtype=np.int64)))
            else:
                arrays.append(self._column(batch.column(batch.schema.get_field_index(col)), dim, col, part, src))
            names.append("c_" + dim)
        out = pa.RecordBatch.from_arrays(arrays, names=names)
        try:
            if self.spool is None:
                self.spool_schema = out.schema
                self.spool = pa.ipc.new_stream(self.spool_path, out.schema)
            self.spool.write_batch(out)
        except (OSError, pa.ArrowException) as exc:
            raise OutputError(f"cannot write the output: {exc}", self.path) from None
        self.written += out.num_rows

    def _column(self, column: pa.Array, dim: str, col: str, part, src: Source) -> pa.Array:
        """A column (or one element of a vector column) for dimension ``dim``: a null is NaN in a float
        dimension (counted and said), and refuses the output in any other (no integer means "no value")."""
        if part is not None:
            if column.null_count:
                self._refuse_nulls(col, column.null_count, src)
            size = column.type.list_size
            flat = column.flatten()
            column = flat.take(indices(np.arange(part, len(flat), size)))
        if column.null_count:
            if not pa.types.is_floating(column.type):
                self._refuse_nulls(col, column.null_count, src)
            self.nulls[dim] = self.nulls.get(dim, 0) + column.null_count
            column = pa.array(to_numpy(column), type=column.type, from_pandas=False)
        return column

    def _refuse_nulls(self, col: str, n: int, src: Source) -> None:
        raise UnsupportedFormat(f"column {col!r} has {n} points with no value (null) among those written; a LAS "
                                "dimension cannot hold a missing value, so no LAS output is written (fill the "
                                "nulls, or write Parquet)", src.path)

    # -- commit: the LAS itself -----------------------------------------

    def _header(self) -> laspy.LasHeader:
        header = laspy.LasHeader(point_format=self.point_format, version="1.4")
        if self.grid is not None:
            scales, offsets = self.grid
            header.scales = np.array(scales, dtype=np.float64)
            if offsets is None:  # the middle of the extent, on the grid
                offsets = [round((lo + (hi - lo) / 2) / s) * s if math.isfinite(lo) and math.isfinite(hi) else 0.0
                           for lo, hi, s in zip(self.lo, self.hi, scales)]
            header.offsets = np.array(offsets, dtype=np.float64)
        elif self.facts:
            header.scales = np.array(self.facts["scales"], dtype=np.float64)
            header.offsets = np.array(self.facts["offsets"], dtype=np.float64)
        else:
            pairs = [coordinate_scale(lo, hi, self.float32) for lo, hi in zip(self.lo, self.hi)]
            header.scales = np.array([p[0] for p in pairs])
            header.offsets = np.array([p[1] for p in pairs])
        for name, _, dt, _ in self.extra:
            header.add_extra_dim(laspy.ExtraBytesParams(name=name, type=dt))
        crs, why = common_crs(self.sources)
        why = why or implausible(crs, self.lo, self.hi)
        if why:
            self.note(why)
        elif crs is not None:
            header.add_crs(crs, keep_compatibility=False)  # a WKT VLR (LAS 1.4)
        prov = dict(self.provenance)
        prov["las_conversion"] = {"point_format": self.point_format, "scales": list(map(float, header.scales)),
                                  "offsets": list(map(float, header.offsets)), "dropped_columns": self.dropped,
                                  "scales_from_source": bool(self.facts) and self.grid is None,
                                  "scales_from_options": self.grid is not None, "notes": list(self.notes),
                                  "source": self.sources[0].describe()}
        header.vlrs.append(provenance_vlr(prov))
        stamp(header)
        return header

    def _records(self, batch: pa.RecordBatch, header) -> laspy.ScaleAwarePointRecord:
        n = batch.num_rows
        rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
        for axis, name in enumerate("XYZ"):
            v = to_numpy(batch.column(axis))
            ints = np.round((v - header.offsets[axis]) / header.scales[axis])
            if ints.size and (ints.min() < -(2 ** 31) or ints.max() > 2 ** 31 - 1):
                if self.grid is not None:
                    raise UsageError(f"coordinate {name.lower()} does not fit a LAS 32-bit integer at --scale "
                                     f"{header.scales[axis]:g} and offset {header.offsets[axis]:g} (the points "
                                     f"span {self.lo[axis]:g} to {self.hi[axis]:g}); choose a coarser --scale "
                                     "or another --offset", self.path)
                raise UnsupportedFormat(f"coordinate {name.lower()} does not fit the source's LAS scale and offset",
                                        self.path)
            rec[name] = ints.astype(np.int32)
        for name in ("red", "green", "blue"):
            rec[name] = to_numpy(batch.column(batch.schema.get_field_index(name)))
        for name in [d for d, _ in self.standard] + [n for n, _, _, _ in self.extra]:
            values = to_numpy(batch.column(batch.schema.get_field_index("c_" + name)))
            try:
                with np.errstate(all="ignore"):  # a failed cast is caught below and said in one line
                    rec[name] = values
            except (OverflowError, ValueError, TypeError) as exc:
                raise UnsupportedFormat(f"column {name!r} does not fit LAS dimension {name}: {exc}",
                                        self.path) from None
            got = np.asarray(rec[name])
            same = np.equal(got, values) | (np.isnan(values) & np.isnan(got) if values.dtype.kind == "f" and
                                            got.dtype.kind == "f" else False)
            if not np.all(same):
                i = int(np.flatnonzero(~same)[0])
                raise UnsupportedFormat(f"column {name!r} holds the value {values[i].item()!r}, which LAS dimension {name} "
                                        f"({got.dtype}) cannot hold, so no LAS output is written (write Parquet)",
                                        self.path)
        return rec

    def _commit(self) -> None:
        try:
            if self.spool is not None:
                self.spool.close()
            header = self._header()
            compress = self.path.lower().endswith(".laz")
            with extrabytes.Writer(self.file.tmp, header, compress) as writer:
                if self.spool is not None:
                    with pa.ipc.open_stream(self.spool_path) as reader:
                        for batch in reader:
                            writer.write_points(self._records(batch, header))
        except (PrismError, KeyboardInterrupt, SystemExit):
            self.abort()
            raise
        except BaseException as exc:  # noqa: BLE001 - disk full, a laspy refusal: one line, nothing left
            self.abort()
            raise OutputError(f"cannot write the output: {describe(exc)}", self.path) from None
        self._remove_spool()
        for dim, n in self.nulls.items():
            self.note(f"dimension {dim!r}: {n} points with no value (null) stored as NaN (LAS has no null)")
        if not self.facts and self.grid is None and self.written:
            self.note(f"coordinates stored as LAS 32-bit integers on a grid of {', '.join(f'{v:g}' for v in header.scales)} "
                      f"(x, y, z) at offset {', '.join(f'{v:.12g}' for v in header.offsets)}, each within half a "
                      "step of its value (--scale and --offset choose another)")
        self.file.commit()

    def _remove_spool(self) -> None:
        staging.remove(self.spool_path)

    def abort(self) -> None:
        try:
            if self.spool is not None:
                self.spool.close()
        except BaseException:  # noqa: BLE001 - the spool is deleted next
            pass
        self._remove_spool()
        self.file.discard()
