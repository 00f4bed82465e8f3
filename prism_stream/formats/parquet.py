"""Parquet in (a file; directories and globs expand to one source per file) and out.

Pass one reads only the three color columns; work units are row groups.
"""

from __future__ import annotations

import json
import os
from typing import Iterator

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..errors import CorruptInput, NoColorError, OutputError, UnsupportedFormat, UsageError
from ..run import remote
from .arrow import from_numpy, list_values, rows_of, to_numpy
from .base import AtomicFile, ColorChunk, PointChunk, Sink, Source, Unit, WriteOptions
from .geo import GEO_KEY, GEOMETRY, file_geo, geo_crs, geo_metadata, point_column, wkb_points
from .columns import (LISTS_FIRST, by_lower, column_notes, common_schema, conform, kept_coordinates,
                      not_coordinates, select_columns, wkb_typed)
from .guard import reading

PROVENANCE_KEY = b"prism_stream"
DEFAULT_RGB = ("red", "green", "blue")


class ArrowPointChunk(PointChunk):
    def __init__(self, start: int, batch: pa.RecordBatch, rgb_names, path, packed: str | None = None,
                 unpack: bool = True):
        """``packed``: the colors are this column's packed words, written as red, green, blue (and alpha) when
        ``unpack``, else as the word they are."""
        self.start = start
        self.batch = batch
        self.packed = packed if unpack else None
        if packed is None:
            self.rgb = tuple(color_array(batch.column(batch.schema.get_field_index(n)), n, path) for n in rgb_names)
        else:
            from .pcd import unpack

            self.words = packed_words(batch.column(batch.schema.get_field_index(packed)), packed, path)
            self.rgb = unpack(self.words)

    def to_arrow(self, mask: np.ndarray | None = None) -> pa.RecordBatch:
        batch = self.batch if mask is None else rows_of(self.batch, mask)
        if self.packed is None:
            return batch
        rows = slice(None) if mask is None else mask  # the chunk's words and channels, unpacked once
        return unpacked_batch(batch, self.packed, self.words[rows], tuple(c[rows] for c in self.rgb))


def _list_names(batch: pa.RecordBatch, schema: pa.Schema) -> pa.RecordBatch:
    """A batch back from the spill with its fixed-size lists' value fields as the file has them: pyarrow's
    pickle names every list's values ``item`` (GeoArrow points: ``element: double not null``), which a writer
    would then cast, loading ``pyarrow.compute``."""
    fields, columns, changed = [], [], False
    for field, column in zip(batch.schema, batch.columns):
        want = schema.field(field.name).type if schema.get_field_index(field.name) >= 0 else field.type
        if column.type != want and pa.types.is_fixed_size_list(want) and pa.types.is_fixed_size_list(column.type) \
                and column.type.list_size == want.list_size and column.type.value_type == want.value_type \
                and not column.null_count:
            column = pa.FixedSizeListArray.from_arrays(list_values(column), type=want)
            field, changed = field.with_type(want), True
        fields.append(field)
        columns.append(column)
    if not changed:
        return batch
    return pa.RecordBatch.from_arrays(columns, schema=pa.schema(fields, metadata=batch.schema.metadata))


def color_array(col: pa.Array, name: str, path: str) -> np.ndarray:
    """A color column as numpy: numeric, and no point without a color."""
    if col.null_count:
        raise CorruptInput(f"column {name!r} has {col.null_count} points with no color (null)", path)
    if not (pa.types.is_integer(col.type) or pa.types.is_floating(col.type)):
        raise CorruptInput(f"color column {name!r} has type {col.type}, not a number", path)
    return to_numpy(col)


PACKED = ("rgb", "rgba")  # PCL's packed color word: a float32 (its bits) or a uint32 0xAARRGGBB


def packed_color_column(schema: pa.Schema) -> str | None:
    """The packed color column of a Parquet without red, green, blue (PCL's ``rgb``/``rgba``, as converters
    from PCD write it), or None: a 32-bit float or integer column of that name (any case)."""
    lower = by_lower(schema.names)
    for want in PACKED:
        name = lower.get(want)
        if name is None:
            continue
        t = schema.field(name).type
        if not (pa.types.is_floating(t) or pa.types.is_integer(t)) or t.bit_width < 32:  # (a word is 32 bits)
            continue
        if any(c in lower for c in DEFAULT_RGB):
            return None
        return name
    return None


def packed_words(col: pa.Array, name: str, path: str) -> np.ndarray:
    """The uint32 color words of a packed column (a float's bits, an integer's value)."""
    if col.null_count:
        raise CorruptInput(f"column {name!r} has {col.null_count} points with no color (null)", path)
    v = to_numpy(col)
    if v.dtype.kind == "f":
        return v.astype(np.float32).view(np.uint32)
    if v.dtype.itemsize == 4:
        return v.view(np.uint32)  # int32 or uint32: the word's bits
    bad = v[(v < 0) | (v >= 1 << 32)] if v.dtype.kind == "i" else v[v >= 1 << 32]
    if bad.size:
        raise CorruptInput(f"packed color column {name!r} holds {int(bad[0])}, not a 32-bit color word", path)
    return v.astype(np.uint32)


def unpack_colors(col: pa.Array, name: str, path: str) -> tuple:
    """The 8-bit red, green, blue of a packed color column (PCD's own unpacking)."""
    from .pcd import unpack

    return unpack(packed_words(col, name, path))


def _unpacked_fields(schema: pa.Schema, packed: str) -> list:
    """The fields of ``schema`` with the packed color column replaced by uint8 red, green, blue (and alpha)."""
    fields = []
    for f in schema:
        if f.name != packed:
            fields.append(f)
            continue
        fields += [pa.field(c, pa.uint8()) for c in DEFAULT_RGB]
        if packed.lower() == "rgba":
            fields.append(pa.field("alpha", pa.uint8()))
    return fields


def unpacked_batch(batch: pa.RecordBatch, packed: str, words: np.ndarray, rgb: tuple) -> pa.RecordBatch:
    """``batch`` with its packed color column (``words``, unpacked as ``rgb``) as red, green, blue (and alpha
    from an ``rgba`` word's top byte)."""
    i = batch.schema.get_field_index(packed)
    channels = [from_numpy(c) for c in rgb]
    if packed.lower() == "rgba":
        channels.append(from_numpy((words >> 24).astype(np.uint8)))
    arrays = batch.columns[:i] + channels + batch.columns[i + 1:]
    return pa.RecordBatch.from_arrays(arrays, schema=pa.schema(_unpacked_fields(batch.schema, packed),
                                                               metadata=batch.schema.metadata))


def find_color_columns(schema: pa.Schema, wanted, path: str) -> tuple[str, str, str]:
    """The color column names, matched exactly first, then ignoring case (PDAL writes Red/Green/Blue)."""
    names = schema.names
    lower = {n.lower(): n for n in names}
    out = []
    for w in wanted:
        if w in names:
            out.append(w)
        elif w.lower() in lower:
            out.append(lower[w.lower()])
        else:
            raise NoColorError(
                f"no color column {w!r} (columns: {', '.join(names[:12])}{'...' if len(names) > 12 else ''}); "
                "name them with --rgb-columns", path)
    return tuple(out)


class ParquetSource(Source):
    format = "parquet"

    reads_remote = True

    def __init__(self, path: str, ordinal: int, rgb_columns=DEFAULT_RGB, threads: int = 1,
                 storage_options: dict | None = None, **_):
        self.path = path
        self.ordinal = ordinal
        self.threads = threads
        self.handle = None  # a remote file's pyarrow file, closed with the source
        with reading(path, "not a readable Parquet file"):
            if remote.is_remote(path):
                self.handle = remote.arrow_input(path, storage_options)
            else:
                with open(path, "rb") as f:
                    head = f.read(4)
                if head not in (b"PAR1", b"PARE"):  # another kind of file (exit 4, as a .las that is no LAS); a
                    # Parquet file cut short is corrupt (6), and an encrypted one (PARE) says so through pyarrow
                    raise UnsupportedFormat("not a Parquet file (it does not begin with PAR1)", path)
            # pre_buffer would read ahead without bound (RSS grows with the file)
            self.file = pq.ParquetFile(self.handle or path, pre_buffer=False)
            self.schema = self.file.schema_arrow
        # a packed color word (PCL's rgb/rgba) stands in for red, green, blue when no color columns are named
        self.packed = packed_color_column(self.schema) if tuple(rgb_columns or DEFAULT_RGB) == DEFAULT_RGB else None
        try:
            self.rgb_names = find_color_columns(self.schema, rgb_columns or DEFAULT_RGB, path)
            self.packed = None
        except NoColorError:
            if self.packed is None:
                raise
            self.rgb_names = DEFAULT_RGB  # the columns the points are written with (unpacked)
        # an rgba word beside an alpha column: the colors are read from it, and it is written as it is (its
        # alpha would write over that column), as a PCD file's word is
        self.unpack = not (self.packed and self.packed.lower() == "rgba" and "alpha" in by_lower(self.schema.names))
        if not self.unpack:
            self.color_fields = (self.packed,)
        # an unpacked rgba word's alpha: part of the color, so --keep keeps it (:func:`.columns.select_columns`)
        self.word_alpha = ("alpha",) if self.packed and self.unpack and self.packed.lower() == "rgba" else ()
        self.read_columns = None  # the columns decoded (None: every one; see :meth:`read_only`)
        meta = self.file.metadata
        self.count = int(meta.num_rows)
        self.row_groups = [meta.row_group(i).num_rows for i in range(meta.num_row_groups)]
        # GeoParquet: the file's key-value metadata (pyarrow leaves it out of the schema when the file
        # carries its own ARROW:schema without it, as PDAL's do)
        self.geo = file_geo(meta.metadata) or file_geo(self.schema.metadata)

    def crs(self):
        """The CRS of the points: GeoParquet's primary column, else the LAS CRS a prism-stream Parquet kept."""
        if self.geo is not None:
            return geo_crs(self.geo)
        raw = (self.schema.metadata or {}).get(b"prism_stream_source")
        try:
            wkt = json.loads(raw).get("crs_wkt") if raw else None
        except (ValueError, AttributeError):
            wkt = None
        if not wkt:
            return None
        import pyproj

        try:
            return pyproj.CRS.from_wkt(wkt)
        except pyproj.exceptions.CRSError:
            return None

    def geometry_columns(self) -> set:
        """Names of the GeoParquet geometry columns (WKB) of this file."""
        return set(self.geo["columns"]) if self.geo else set()

    def units(self, unit_size: int) -> list[Unit]:
        """Whole row groups (the natural block of a Parquet file), consecutive ones together up to
        ``unit_size`` points (a group larger than that is a unit of its own): a file written in small groups
        (100,000 rows is common) would otherwise be thousands of units, each paying a unit's fixed cost."""
        units, start, pos = [], 0, 0
        for n in self.row_groups:
            if pos > start and pos + n - start > unit_size:
                units.append(Unit(self, start, pos))
                start = pos
            pos += n
        if pos > start:
            units.append(Unit(self, start, pos))
        return units or [Unit(self, 0, 0)]

    def _batches(self, chunk_size: int, start: int, stop: int | None, columns) -> Iterator[tuple[int, pa.RecordBatch]]:
        stop = self.count if stop is None else stop
        groups, first, pos = [], None, 0
        for i, n in enumerate(self.row_groups):
            if pos + n > start and pos < stop:
                groups.append(i)
                first = pos if first is None else first
            pos += n
        if not groups:
            return
        pos = first
        # one reader per row group: a single reader over many groups holds on to what it decoded
        # (apache/arrow#39808) and was slower on 100M rows
        with reading(self.path):
            for group in groups:
                for batch in self.file.iter_batches(batch_size=chunk_size, row_groups=[group], columns=columns,
                                                    use_threads=self.threads > 1):
                    a, b = max(pos, start), min(pos + batch.num_rows, stop)
                    if b > a:
                        yield a, batch.slice(a - pos, b - a)
                    pos += batch.num_rows

    def color_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[ColorChunk]:
        if self.packed is not None:
            for pos, batch in self._batches(chunk_size, start, stop, [self.packed]):
                yield ColorChunk(pos, unpack_colors(batch.column(0), self.packed, self.path))
            return
        for pos, batch in self._batches(chunk_size, start, stop, list(self.rgb_names)):
            yield ColorChunk(pos, tuple(color_array(batch.column(i), n, self.path) for i, n in enumerate(self.rgb_names)))

    def read_only(self, names) -> None:
        """Decode only these of the file's columns from here on (a run whose output leaves the rest out:
        --keep/--drop); its colors (or packed color word) are always read. A columnar file decodes a column at
        a time, so what is left out costs nothing: 10M points, x, y, z and colors of 11 columns, decoded in
        0.28 s against 0.50 (bench/PROFILE.md)."""
        wanted = set(names) | set(self.rgb_names) | ({self.packed} if self.packed else set())
        columns = [n for n in self.schema.names if n in wanted]
        self.read_columns = None if len(columns) == len(self.schema.names) else columns

    def spilled_schema(self) -> pa.Schema:
        """The columns a spilled point holds (:meth:`spill_state`): the file's, as decoded (:meth:`read_only`)."""
        if self.read_columns is None:
            return self.schema
        return pa.schema([f for f in self.schema if f.name in self.read_columns])

    def column_bytes(self) -> dict:
        """Each top-level column's bytes a row in the file, uncompressed (its row groups' metadata): what a
        column of no fixed width (a list, WKB) holds, for the temporary-disk forecast."""
        meta, total = self.file.metadata, {}
        for i in range(meta.num_row_groups):
            group = meta.row_group(i)
            for j in range(group.num_columns):
                column = group.column(j)
                name = column.path_in_schema.split(".")[0]
                total[name] = total.get(name, 0) + column.total_uncompressed_size
        rows = max(1, self.count)
        return {name: size / rows for name, size in total.items()}

    def point_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[ArrowPointChunk]:
        for pos, batch in self._batches(chunk_size, start, stop, self.read_columns):
            yield ArrowPointChunk(pos, batch, self.rgb_names, self.path, self.packed, self.unpack)

    def arrow_schema(self) -> pa.Schema:
        """The columns the points are written with: the file's, a packed color word as red, green, blue."""
        if self.packed is None or not self.unpack:
            return self.schema
        return pa.schema(_unpacked_fields(self.schema, self.packed), metadata=self.schema.metadata)

    spills = True

    def spill_state(self, chunk: ArrowPointChunk, at: np.ndarray):
        return rows_of(chunk.batch, at)

    def restore(self, state) -> ArrowPointChunk:
        chunk = ArrowPointChunk(0, _list_names(state, self.schema), self.rgb_names, self.path, self.packed,
                                self.unpack)
        chunk.ordinal = self.ordinal
        return chunk

    def close(self) -> None:
        if self.handle is not None:
            self.handle.close()

    def describe(self) -> dict:
        d = {"format": "parquet", "rows": self.count, "row_groups": len(self.row_groups),
             "color_columns": [self.packed] if self.packed else list(self.rgb_names)}
        if self.packed:
            d["packed_color"] = self.packed
        return d


def output_schema(sources, provenance: dict, geometry: bool = False, columns: str = "same",
                  selection: tuple | None = None) -> pa.Schema:
    """The inputs' common schema and metadata, with the provenance added (every engine's Parquet output).

    ``geometry``: add a WKB ``Point Z`` column named ``geometry``. The GeoParquet ``geo`` key is written
    whenever the output has a geometry column (this one, or a GeoParquet input's own). ``columns``: how
    inputs with different columns share one output (:func:`common_schema`)."""
    schema, _ = common_schema(sources, columns) if sources else (pa.schema([]), [])
    schema = select_columns(schema, sources, selection, sources[0].path if sources else "")
    meta = dict(schema.metadata or {})
    meta.pop(GEO_KEY, None)
    meta[PROVENANCE_KEY] = json.dumps(provenance, sort_keys=True).encode()
    extra = _source_metadata(sources)
    if extra:
        meta[b"prism_stream_source"] = json.dumps(extra, sort_keys=True).encode()
    from .geo import common_crs

    crs, _ = common_crs(sources) if sources else (None, None)
    columns, primary = {}, None
    first_geo = getattr(sources[0], "geo", None) if sources else None
    if first_geo and all(getattr(s, "geo", None) == first_geo for s in sources):
        columns = {n: c for n, c in first_geo["columns"].items() if n in schema.names}
        primary = first_geo.get("primary_column") if first_geo.get("primary_column") in columns else None
    if geometry:
        if GEOMETRY in schema.names:
            raise UsageError(f"--geometry: the input already has a column named {GEOMETRY!r}", sources[0].path)
        point_xyz(schema, sources[0].path if sources else "")
        schema = schema.append(pa.field(GEOMETRY, pa.binary(), nullable=False))
        columns[GEOMETRY] = point_column(crs)
        primary = GEOMETRY
    if columns and primary:
        meta[GEO_KEY] = geo_metadata(columns, primary)
    return schema.with_metadata(meta)


def point_xyz(schema: pa.Schema, path: str, needs: str = "--geometry", source=None):
    """Where a schema's points hold their coordinates (:func:`.columns.kept_coordinates`): [x, y, z] names (any
    case), the name of a list column of three numbers, or ("wkb", name) for WKB points (else the column
    ``source``'s GeoParquet metadata names); else a one-line refusal of what ``needs`` them."""
    held = kept_coordinates(schema)
    if len(held) == 3:  # x, y, z
        return held
    if held:
        kind = schema.field(held[0]).type
        listed = pa.types.is_fixed_size_list(kind) or pa.types.is_list(kind) or pa.types.is_large_list(kind)
        return held[0] if listed else ("wkb", held[0])
    primary = (getattr(source, "geo", None) or {}).get("primary_column")  # (a file's own key, beside its schema)
    if isinstance(primary, str) and primary in schema.names and wkb_typed(schema.field(primary).type):
        return "wkb", primary
    why = not_coordinates(schema)
    raise UsageError(f"{needs} needs the points' coordinates: x, y and z columns, a list column of three numbers "
                     f"(xyz, position...) or WKB points; " + (f"its {why}" if why else
                                                              f"the input has {', '.join(schema.names[:12])}"), path)


def xyz_names(xyz) -> list[str]:
    """The columns the coordinates ``xyz`` (from :func:`point_xyz`) are read from."""
    if isinstance(xyz, list):
        return list(xyz)
    if isinstance(xyz, str):
        return [xyz]
    return [xyz[1]]


def xyz_float32(schema: pa.Schema, xyz) -> bool:
    """Whether the coordinates ``xyz`` (from :func:`point_xyz`) are float32 values (x, y, z columns, or a list
    column's values): their own spacing bounds a LAS output's grid, and PLY keeps them float."""
    if isinstance(xyz, list):
        return all(pa.types.is_float32(schema.field(n).type) for n in xyz)
    return isinstance(xyz, str) and pa.types.is_float32(schema.field(xyz).type.value_type)


def xyz_arrays(batch: pa.RecordBatch, xyz, path: str = "") -> list[np.ndarray]:
    """x, y, z of a batch as float64 arrays (``xyz`` from :func:`point_xyz`)."""
    if isinstance(xyz, tuple):
        from .geo import wkb_xyz

        return wkb_xyz(batch.column(batch.schema.get_field_index(xyz[1])), xyz[1], path)
    if isinstance(xyz, str):
        column = batch.column(batch.schema.get_field_index(xyz))
        missing = column.null_count or column.flatten().null_count  # a null row, or a null inside one
        if missing:
            raise CorruptInput(f"coordinate column {xyz!r} holds {missing} nulls: points with no coordinates", path)
        if not pa.types.is_fixed_size_list(column.type):
            import pyarrow.compute as pc

            if len(column) and not pc.all(pc.equal(pc.list_value_length(column), 3)).as_py():
                raise CorruptInput(f"coordinate column {xyz!r} holds lists that are not 3 numbers each ({LISTS_FIRST})",
                                   path)
        flat = to_numpy(column.flatten()).reshape(-1, 3).astype(np.float64)
        return [flat[:, 0], flat[:, 1], flat[:, 2]]
    return [to_numpy(batch.column(batch.schema.get_field_index(n))).astype(np.float64)
            for n in xyz]


class ParquetSink(Sink):
    """Parquet out: the inputs' schema and metadata, plus provenance under ``prism_stream``."""

    takes_columns = True
    takes_geometry = True

    @classmethod
    def open(cls, path: str, sources: list[Source], provenance: dict, options: WriteOptions) -> "ParquetSink":
        return cls(path, sources, provenance, options)

    def __init__(self, path: str, sources: list[Source], provenance: dict, options: WriteOptions = WriteOptions(),
                 schema: pa.Schema | None = None, skip_empty: bool = False, compression: str = "zstd"):
        """``options``: ``geometry`` adds a WKB point column (GeoParquet), ``rank`` an int64 column of that
        name (each point's rank), ``flag`` a boolean keep column; ``columns``: inputs with different columns
        (:func:`common_schema`); ``selection``: --keep/--drop (:func:`select_columns`). ``schema``: write this
        one (a part of a dataset whose schema the driver fixed; a ``geometry`` column it has and the input has
        not is computed); ``skip_empty``: commit nothing when no point was written (and remove an earlier file
        at ``path``)."""
        super().__init__(path, sources, provenance)
        flag, geometry, rank, columns = options.flag, options.geometry, options.rank, options.columns
        selection = options.selection
        self.flag = flag
        self.skip_empty = skip_empty
        schema = schema if schema is not None else output_schema(sources, provenance, geometry=geometry,
                                                                 columns=columns, selection=selection)
        for text in column_notes(sources, columns, schema):
            self.note(text)
        self.note_depths(sources, provenance)
        meta = schema.metadata
        own = sources[0].arrow_schema().names if sources else []
        # --geometry: built from the input's own coordinates (the output's schema has the new column already)
        self.xyz = None
        if GEOMETRY in schema.names and GEOMETRY not in own:  # from the input's schema: GeoParquet's names
            first = sources[0] if sources else None
            given = first.arrow_schema() if first else pa.schema([f for f in schema if f.name != GEOMETRY])
            self.xyz = point_xyz(given, first.path if first else path, "--geometry", first)
        self._note_crs(schema)
        if flag is not None:
            if flag in schema.names:
                raise UsageError(f"--flag {flag!r}: the input already has a column of that name", sources[0].path)
            schema = schema.append(pa.field(flag, pa.bool_()))
        self.rank = rank
        if rank is not None:
            self.check_rank_name(rank, [n for n in own if n in schema.names])  # what --drop leaves of the input's
            if rank not in schema.names:  # a dataset part's schema holds it already
                schema = schema.append(pa.field(rank, pa.int64()))
        self.schema = schema.with_metadata(meta)
        # what the inputs' own columns become (their common schema, a dataset's): batches are conformed to it
        added = {flag, rank} | ({GEOMETRY} if self.xyz is not None else set())
        common = pa.schema([f for f in self.schema if f.name not in added])
        self.common = None if all(s.arrow_schema().remove_metadata().equals(common) for s in sources) else common
        self.note_skipped_elements()
        self.file = AtomicFile(path)
        try:
            self.writer = pq.ParquetWriter(self.file.tmp, self.schema, compression=compression)
        except (OSError, pa.ArrowException) as exc:
            self.file.discard()
            raise OutputError(f"cannot write the output: {exc}", path) from None

    def write(self, chunk: PointChunk, mask: np.ndarray, ranks: np.ndarray | None = None) -> None:
        if self.flag is not None:
            batch = chunk.to_arrow(None)
        elif not mask.any():
            return
        else:
            batch = chunk.to_arrow(mask)
        if self.common is not None:
            batch = conform(batch, self.common)
        columns = [*batch.columns]
        if self.xyz is not None:
            columns.append(wkb_points(*xyz_arrays(batch, self.xyz, self.path)))
        if self.flag is not None:
            columns.append(from_numpy(np.asarray(mask, dtype=np.bool_)))
        if self.rank is not None:
            columns.append(from_numpy(np.asarray(ranks, dtype=np.int64)))
        try:
            self.writer.write_batch(pa.RecordBatch.from_arrays(columns, schema=self.schema))
        except (OSError, pa.ArrowException) as exc:
            raise OutputError(f"cannot write the output: {exc}", self.path) from None
        self.written += batch.num_rows

    def _note_crs(self, schema: pa.Schema) -> None:
        """Say where the inputs' CRS went, or why none is written."""
        from .geo import common_crs

        _, why = common_crs(self.sources)
        if why:
            self.note(why)

    def _commit(self) -> None:
        if self.skip_empty and not self.written:
            self.abort()
            if os.path.lexists(self.path):
                os.unlink(self.path)
            return
        try:
            self.writer.close()
        except (OSError, pa.ArrowException) as exc:
            self.file.discard()
            raise OutputError(f"cannot write the output: {exc}", self.path) from None
        self.file.commit()

    def abort(self) -> None:
        self._discard_file(self.writer.close)


def _source_metadata(sources) -> dict:
    """Format facts of the inputs worth keeping beside the points (LAS scales, offsets, CRS)."""
    first = sources[0] if sources else None
    if first is None or first.format == "parquet":
        return {}
    d = first.describe()
    from .geo import common_crs

    crs, _ = common_crs(sources)
    if crs is not None:
        d["crs_wkt"] = crs.to_wkt()
        d["crs_projjson"] = crs.to_json_dict()
    return d


def read_provenance(path: str) -> dict | None:
    meta = pq.ParquetFile(path).schema_arrow.metadata or {}
    raw = meta.get(PROVENANCE_KEY)
    return json.loads(raw) if raw else None
