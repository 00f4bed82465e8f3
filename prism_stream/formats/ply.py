"""PLY in (ascii, binary little- and big-endian), streamed; PLY out (binary little-endian).

The vertex element is the cloud; every other element (faces, materials,
point lists) is skipped, whether it comes before or after the vertices.
Binary vertices are read through a memory map, so a chunk costs only its
own records; an element before the vertices that has list properties is
walked once, at open, to find where the vertices start. ASCII files hold
one element instance a line and are parsed a chunk of lines at a time.

Colors are ``red/green/blue`` or ``diffuse_red/diffuse_green/diffuse_blue``
(or the names given as ``rgb_columns``), in any integer or float type:

- ``uchar``/``ushort`` (and ``uint``) follow the per-file depth rule of
  SPEC 1, floats the ``floor(255 c)`` rule;
- a channel declared *signed* (``char``, ``short``, ``int``) holds a
  writer's unsigned color in a signed slot: it is read as the unsigned word
  of the same width (two's complement, so ``char`` -56 is 200). ASCII text
  for a ``char`` channel may say 0..255 or -128..127; 128..255 is stored as
  the same byte. Anything outside those ranges is an input error.

List properties on the vertex element are refused (a cloud's vertex is a
fixed record in every writer we know). The output writes binary
little-endian, x/y/z as ``float`` (a PLY input's ``double`` x/y/z stay
``double``, since nothing may be lost), ``uchar red/green/blue`` converted
by the same depth rule that binned them, every other property as declared,
and the provenance as ``comment prism-stream ...`` lines.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np
import pyarrow as pa

from ..errors import CorruptInput, NoColorError, OutputError, UnsupportedFormat, UsageError
from .base import AtomicFile, ColorChunk, PointChunk, Sink, Source, WriteOptions, columns_to_arrow, rows
from .conversion import SourceCursor, as_unsigned, color_fields, colors_8bit, depth_decisions, eight_bit_rules
from .guard import reading
from .columns import not_coordinates, numeric_axes, one_layout, select_columns
from .arrow import to_numpy
from .parquet import point_xyz, xyz_arrays, xyz_float32, xyz_names

TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
TYPE_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
              "f4": "float", "f8": "double"}
COLOR_NAMES = (("red", "green", "blue"), ("diffuse_red", "diffuse_green", "diffuse_blue"))
FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
MAX_HEADER = 1 << 20
PROVENANCE_COMMENT = "prism-stream "  # the comment that carries the provenance JSON: this, then the object
ASCII_LINES = 1 << 16


@dataclass
class Property:
    name: str
    type: str  # numpy code without byte order: "u1", "f4"...
    count_type: str | None = None  # a list property's length type


@dataclass
class Element:
    name: str
    count: int
    properties: list = field(default_factory=list)

    @property
    def has_lists(self) -> bool:
        return any(p.count_type for p in self.properties)


@dataclass
class Header:
    format: str
    elements: list
    comments: list
    obj_info: list
    data_offset: int
    newline: bytes


def read_header(path: str) -> Header:
    """Parse a PLY header, refusing anything malformed in one line."""
    with reading(path, "cannot read the PLY header"):
        with open(path, "rb") as f:
            raw = f.read(MAX_HEADER)
    if not raw.startswith(b"ply"):
        raise UnsupportedFormat("not a PLY file (no 'ply' magic)", path)
    first_break = min((i for i in (raw.find(b"\r"), raw.find(b"\n")) if i >= 0), default=-1)
    if first_break < 0:
        raise CorruptInput("PLY header has no line breaks", path)
    if raw[first_break:first_break + 2] == b"\r\n":
        newline, sep = b"\r\n", b"\n"
    else:
        newline = sep = raw[first_break:first_break + 1]
    pos, lines, end = 0, [], None
    while pos < len(raw):
        nxt = raw.find(sep, pos)
        if nxt < 0:
            break
        line = raw[pos:nxt].strip()
        pos = nxt + len(sep)
        if line == b"end_header":
            end = pos
            break
        lines.append(line)
    if end is None:
        raise CorruptInput(f"no end_header line in the first {MAX_HEADER} bytes", path)
    try:
        text = [ln.decode("ascii") for ln in lines]
    except UnicodeDecodeError:
        raise CorruptInput("PLY header is not ASCII text", path) from None
    if text[0].strip() != "ply":
        raise UnsupportedFormat("not a PLY file (first line is not 'ply')", path)
    fmt, elements, comments, obj_info = None, [], [], []
    for n, line in enumerate(text[1:], start=2):
        words = line.split()
        if not words:
            continue
        key = words[0]
        if key == "format":
            if len(words) != 3 or words[1] not in FORMATS:
                raise CorruptInput(f"header line {n}: unknown format {' '.join(words[1:])!r}", path)
            if words[2] != "1.0":  # the only PLY version; plyfile and RPly refuse any other, as here
                raise CorruptInput(f"header line {n}: PLY version {words[2]!r} (1.0 is the only one)", path)
            fmt = words[1]
        elif key == "comment":
            comments.append(line.split(None, 1)[1] if len(words) > 1 else "")
        elif key == "obj_info":
            obj_info.append(line.split(None, 1)[1] if len(words) > 1 else "")
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise CorruptInput(f"header line {n}: bad element line {line.strip()!r}", path)
            elements.append(Element(words[1], int(words[2])))
        elif key == "property":
            if not elements:
                raise CorruptInput(f"header line {n}: property before any element", path)
            if len(words) == 3 and words[1] in TYPES:
                prop = Property(words[2], TYPES[words[1]])
            elif len(words) == 5 and words[1] == "list" and words[2] in TYPES and words[3] in TYPES:
                if TYPES[words[2]][0] == "f":
                    raise CorruptInput(f"header line {n}: list length type {words[2]} is not an integer", path)
                prop = Property(words[4], TYPES[words[3]], TYPES[words[2]])
            else:
                raise CorruptInput(f"header line {n}: bad property line {line.strip()!r}", path)
            if any(p.name == prop.name for p in elements[-1].properties):
                raise CorruptInput(f"header line {n}: property {prop.name!r} declared twice", path)
            elements[-1].properties.append(prop)
        else:
            raise CorruptInput(f"header line {n}: unknown keyword {key!r}", path)
    if fmt is None:
        raise CorruptInput("PLY header has no format line", path)
    return Header(fmt, elements, comments, obj_info, end, newline)


def find_colors(props, wanted, path: str) -> tuple:
    names = [p.name for p in props]
    candidates = [tuple(wanted)] if wanted else list(COLOR_NAMES)
    for trio in candidates:
        if all(n in names for n in trio):
            return trio
    shown = ", ".join(names[:12]) + ("..." if len(names) > 12 else "")
    raise NoColorError(f"vertex has no red/green/blue or diffuse_red/green/blue properties ({shown})", path)


class PlyPointChunk(PointChunk):
    def __init__(self, ordinal: int, start: int, records: np.ndarray, rgb_names):
        self.ordinal = ordinal
        self.start = start
        self.records = records  # structured, native byte order
        self.rgb = tuple(as_unsigned(records[n]) for n in rgb_names)
        self.rgb_names = tuple(rgb_names)

    def to_arrow(self, mask: np.ndarray | None = None) -> pa.RecordBatch:
        recs = self.records if mask is None else rows(self.records, mask)
        return columns_to_arrow(_colors_unsigned(recs, self.rgb_names))


def _colors_unsigned(recs: np.ndarray, names) -> np.ndarray:
    """The records with a color channel declared signed (``char blue``) as the unsigned type of its width: the
    value the points were binned by (two's complement: ``char`` -56 is 200), which a Parquet output then holds
    too (it held -56, which prism-stream itself refuses as a color)."""
    signed = [n for n in names if recs.dtype.fields[n][0].kind == "i"]
    if not signed:
        return recs
    fields = recs.dtype.fields
    dtype = np.dtype({"names": list(recs.dtype.names),
                      "formats": [fields[n][0] if n not in signed else fields[n][0].str.replace("i", "u")
                                  for n in recs.dtype.names],
                      "offsets": [fields[n][1] for n in recs.dtype.names], "itemsize": recs.dtype.itemsize})
    return recs.view(dtype)


class PlySource(Source):
    format = "ply"
    spills = True  # point chunks implement take; the default spill state (the chunk) pickles

    def __init__(self, path: str, ordinal: int, rgb_columns=None, **_):
        self.path = path
        self.ordinal = ordinal
        self.header = h = read_header(path)
        vertices = [e for e in h.elements if e.name == "vertex"]
        if not vertices:
            raise NoColorError("PLY has no vertex element, so no points to bin", path)
        if len(vertices) > 1:
            raise CorruptInput("PLY declares two vertex elements", path)
        self.element = el = vertices[0]
        lists = [p.name for p in el.properties if p.count_type]
        if lists:
            raise UnsupportedFormat(f"vertex element has list properties ({', '.join(lists)}); "
                                    "only fixed vertex records are read", path)
        self.color_fields = find_colors(el.properties, rgb_columns, path)
        self.count = el.count
        self.endian = FORMATS[h.format]
        self.dtype = np.dtype([(p.name, (self.endian or "<") + p.type) for p in el.properties])
        self.native = self.dtype.newbyteorder("=")
        size = os.path.getsize(path)
        if h.format == "ascii":
            self.vertex_line = sum(e.count for e in h.elements[:h.elements.index(el)])
            self.vertex_offset = None
        else:
            self.vertex_offset = h.data_offset + self._bytes_before(el, size)
            need = self.vertex_offset + self.count * self.dtype.itemsize
            if need > size:
                held = max(0, size - self.vertex_offset) // max(1, self.dtype.itemsize)
                raise CorruptInput(f"header declares {self.count} vertices but the file holds {held}", path)
            # the elements after the vertices (a mesh's faces) must fit what is left: a vertex count that is too
            # high reads the faces' bytes as points, which only the walk of the faces' lists shows
            after = need
            for later in h.elements[h.elements.index(el) + 1:]:
                try:
                    after += element_bytes(path, later, self.endian, after, size)
                except CorruptInput as exc:
                    raise CorruptInput(f"{exc.args[0]}, after the {self.count} vertices the header declares: the "
                                       "vertex count does not match the data, or the file is cut", path) from None

    def _bytes_before(self, vertex: Element, size: int) -> int:
        """Byte length of the binary elements stored before the vertex element."""
        offset = 0
        for el in self.header.elements:
            if el is vertex:
                return offset
            offset += element_bytes(self.path, el, self.endian, self.header.data_offset + offset, size)
        return offset

    # -- reading --------------------------------------------------------

    def _mapped(self, dtype) -> np.ndarray:
        with reading(self.path):
            return np.memmap(self.path, dtype=dtype, mode="r", offset=self.vertex_offset, shape=(self.count,))

    def _ascii_records(self, chunk_size: int, start: int, stop: int) -> Iterator[tuple[int, np.ndarray]]:
        types = [p.type for p in self.element.properties]
        with reading(self.path), open(self.path, "rb") as f:
            f.seek(self.header.data_offset)
            for _ in range(self.vertex_line + start):
                if not f.readline():
                    raise CorruptInput("file ends before the vertex element", self.path)
            pos = start
            while pos < stop:
                n = min(chunk_size, stop - pos, ASCII_LINES)
                lines = [f.readline() for _ in range(n)]
                got = sum(1 for ln in lines if ln)
                if got < n:
                    raise CorruptInput(f"file ends after {pos + got} of the {self.count} vertices its header "
                                       "declares", self.path)
                yield pos, parse_ascii(lines, self.element, types, self.native, pos, self.path)
                pos += n

    def _records(self, chunk_size: int, start: int, stop: int | None) -> Iterator[tuple[int, np.ndarray]]:
        stop = self.count if stop is None else min(stop, self.count)
        if stop <= start:
            return
        if self.vertex_offset is None:
            yield from self._ascii_records(chunk_size, start, stop)
            return
        mm = self._mapped(self.dtype)
        try:
            for a in range(start, stop, chunk_size):
                with reading(self.path):
                    yield a, mm[a:min(stop, a + chunk_size)].astype(self.native)
        finally:
            del mm

    def color_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[ColorChunk]:
        if self.vertex_offset is None:
            for pos, rec in self._records(chunk_size, start, stop):
                yield ColorChunk(pos, tuple(as_unsigned(rec[n]) for n in self.color_fields))
            return
        stop = self.count if stop is None else min(stop, self.count)
        if stop <= start:
            return
        only = np.dtype({"names": list(self.color_fields),
                         "formats": [self.dtype.fields[n][0] for n in self.color_fields],
                         "offsets": [self.dtype.fields[n][1] for n in self.color_fields],
                         "itemsize": self.dtype.itemsize})
        mm = self._mapped(only)
        try:
            for a in range(start, stop, chunk_size):
                with reading(self.path):
                    rec = mm[a:min(stop, a + chunk_size)]
                    yield ColorChunk(a, tuple(as_unsigned(rec[n].astype(rec[n].dtype.newbyteorder("=")))
                                              for n in self.color_fields))
        finally:
            del mm

    def point_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[PlyPointChunk]:
        for pos, rec in self._records(chunk_size, start, stop):
            yield PlyPointChunk(self.ordinal, pos, rec, self.color_fields)

    def arrow_schema(self) -> pa.Schema:
        return PlyPointChunk(self.ordinal, 0, np.zeros(0, self.native), self.color_fields).to_arrow().schema

    def describe(self) -> dict:
        h = self.header
        return {
            "format": "ply",
            "encoding": h.format,
            "vertex_properties": [f"{p.name}:{TYPE_NAMES[p.type]}" for p in self.element.properties],
            "skipped_elements": {e.name: e.count for e in h.elements if e is not self.element},
            "comments": list(h.comments),
        }


def parse_ascii(lines, element: Element, types, native: np.dtype, first: int, path: str) -> np.ndarray:
    """One chunk of ASCII vertex lines into native records, each value checked against its type."""
    width = len(types)
    rows = [ln.split() for ln in lines]
    for i, row in enumerate(rows):
        if len(row) != width:
            raise CorruptInput(f"vertex {first + i} has {len(row)} values, the header declares {width}", path)
    out = np.empty(len(rows), dtype=native)
    if not rows:
        return out
    try:
        values = np.array(rows, dtype=np.float64)
    except ValueError:
        bad = next((v for row in rows for v in row if not _is_number(v)), b"?")
        raise CorruptInput(f"vertex value {bad.decode('ascii', 'replace')!r} is not a number", path) from None
    for j, (prop, code) in enumerate(zip(element.properties, types)):
        col = values[:, j]
        if code[0] == "f":
            out[prop.name] = col.astype(code)
            continue
        info = np.iinfo(code)
        lo, hi = info.min, info.max
        if code == "i1":
            hi = 255  # an unsigned byte in a signed slot: kept as the same byte
        ok = np.isfinite(col) & (col == np.floor(col)) & (col >= lo) & (col <= hi)
        if not ok.all():
            i = int(np.flatnonzero(~ok)[0])
            raise CorruptInput(f"vertex {first + i}: {prop.name} = {rows[i][j].decode('ascii', 'replace')} "
                               f"is not a {TYPE_NAMES[code]}", path)
        if code == "i1":
            out[prop.name] = col.astype(np.int64).astype(np.uint8).view(np.int8)
        else:
            out[prop.name] = col.astype(code)
    return out


def _is_number(v: bytes) -> bool:
    try:
        float(v)
        return True
    except ValueError:
        return False


def element_bytes(path: str, el: Element, endian: str, offset: int, size: int) -> int:
    """Byte length of one binary element, walking its list lengths when it has lists."""
    if not el.has_lists:
        n = el.count * sum(np.dtype(p.type).itemsize for p in el.properties)
        if offset + n > size:
            raise CorruptInput(f"element {el.name!r} ({el.count} records) runs past the end of the file", path)
        return n
    if el.count > size - offset:  # every record holds at least one length byte
        raise CorruptInput(f"element {el.name!r} declares {el.count} records, more than the file can hold", path)
    with reading(path):
        mm = np.memmap(path, dtype=np.uint8, mode="r") if size else np.zeros(0, np.uint8)
    try:
        return _walk_lists(mm, el, endian, offset, path)
    finally:
        del mm


def _walk_lists(mm: np.ndarray, el: Element, endian: str, offset: int, path: str) -> int:
    # Fast path: in a triangle mesh every list has the length of the first one,
    # so the element is a fixed-size record; check that in one vectorized step.
    props = el.properties
    lengths = []
    pos = offset
    for p in props:
        if p.count_type:
            t = np.dtype(endian + p.count_type)
            if pos + t.itemsize > len(mm):
                raise CorruptInput(f"element {el.name!r} runs past the end of the file", path)
            n = int(mm[pos:pos + t.itemsize].view(t)[0])
            if n < 0:
                raise CorruptInput(f"element {el.name!r} has a negative list length", path)
            lengths.append(n)
            pos += t.itemsize + n * np.dtype(p.type).itemsize
        else:
            pos += np.dtype(p.type).itemsize
    record = pos - offset
    total = record * el.count
    if el.count and offset + total <= len(mm):
        fields, at = [], 0
        li = iter(lengths)
        for p in props:
            if p.count_type:
                t = np.dtype(endian + p.count_type)
                fields.append((at, t, next(li)))
                at += t.itemsize + fields[-1][2] * np.dtype(p.type).itemsize
            else:
                at += np.dtype(p.type).itemsize
        block = mm[offset:offset + total].reshape(el.count, record)
        if all((block[:, a:a + t.itemsize].copy().view(t).ravel() == n).all() for a, t, n in fields):
            return total
    # Slow path: records of varying length (a mesh of triangles and quads), walked one by one, with struct on
    # the mapped bytes (numpy's per-record views took 3 us a record; this about a tenth)
    import struct

    pos = offset
    end = len(mm)
    steps = []  # (list length's struct or None, its size, the item or fixed size)
    for p in props:
        size = np.dtype(p.type).itemsize
        if p.count_type:
            t = np.dtype(p.count_type)
            steps.append((struct.Struct((endian or "<") + t.char), t.itemsize, size))
        else:
            steps.append((None, size, 0))
    buf = memoryview(mm) if len(mm) else memoryview(b"")
    try:
        for _ in range(el.count):
            for length, size, item in steps:
                if length is None:
                    pos += size
                    continue
                if pos + size > end:
                    raise CorruptInput(f"element {el.name!r} runs past the end of the file", path)
                n = int(length.unpack_from(buf, pos)[0])
                if n < 0:
                    raise CorruptInput(f"element {el.name!r} has a negative list length", path)
                pos += size + n * item
            if pos > end:
                raise CorruptInput(f"element {el.name!r} runs past the end of the file", path)
    finally:
        buf.release()
    return pos - offset


# -- output ----------------------------------------------------------------

def _arrow_to_ply(t: pa.DataType) -> str | None:
    """The PLY type code a column is written as, or None when PLY cannot hold it."""
    if pa.types.is_boolean(t):
        return "u1"
    if pa.types.is_integer(t):
        code = np.dtype(t.to_pandas_dtype()).str[1:]
        return code if code in TYPE_NAMES else "f8"  # PLY has no 64-bit integers
    if pa.types.is_floating(t):
        code = np.dtype(t.to_pandas_dtype()).str[1:]
        return code if code in TYPE_NAMES else "f4"
    return None


def why_not_ply(t: pa.DataType) -> str:
    """Why a column of type ``t`` has no PLY property type (for the note that says it was dropped)."""
    if pa.types.is_string(t) or pa.types.is_large_string(t) or pa.types.is_binary(t) \
            or pa.types.is_large_binary(t) or pa.types.is_dictionary(t):
        return "PLY properties hold numbers, not text or bytes"
    if pa.types.is_temporal(t):
        return "PLY has no date or time type"
    if pa.types.is_nested(t):
        return "a PLY vertex property is one number per point"
    if pa.types.is_null(t):
        return "the column holds no values"
    return "PLY has no such number type"


def _type_change(t: pa.DataType, code: str) -> str | None:
    """Why a column of type ``t`` written as PLY ``code`` is not written in its own type, if it is not."""
    if pa.types.is_boolean(t):
        return "PLY has no boolean: written as uchar 0/1"
    if pa.types.is_integer(t) and code == "f8":
        return "PLY has no 64-bit integer: written as double, exact up to 2^53"
    if pa.types.is_floating(t) and np.dtype(t.to_pandas_dtype()).str[1:] != code:
        return f"PLY has no {t} type: written as {TYPE_NAMES[code]}"
    return None


def _is_ply_name(name: str) -> bool:
    return bool(name) and name.isascii() and not any(ch.isspace() for ch in name)


COUNT_WIDTH = 20  # digits of the largest vertex count a PLY output may hold (2^64 - 1)


class PlySink(Sink):
    """Binary little-endian PLY out: x/y/z, uchar red/green/blue, every other property.

    What PLY cannot hold is said, never silently lost (``self.notes`` and a
    PrismWarning each): a column without a PLY type (text, time, nested) is
    left out and named; a vector column (a fixed-size list, like a PCD
    ``normal`` with COUNT 3 or a LAS extra-bytes array) becomes one property
    per element, ``name_0``, ``name_1``...; a type PLY lacks (64-bit
    integers, half floats, booleans) is widened and named; a null in a float
    column is written as NaN and counted; a null in an integer column
    refuses the output (no integer means "no value").
    """

    @classmethod
    def open(cls, path: str, sources: list[Source], provenance: dict, options: WriteOptions) -> "PlySink":
        return cls(path, sources, provenance, flag=options.flag, rank=options.rank, selection=options.selection)

    def __init__(self, path: str, sources: list[Source], provenance: dict, flag: str | None = None,
                 rank: str | None = None, selection: tuple | None = None):
        super().__init__(path, sources, provenance)
        self.note_crs_not_written("PLY")
        # flag mode: every vertex is written, with a uchar property `flag` (1 = kept)
        self.flag = flag
        self.decisions = depth_decisions(sources, provenance)
        self.cursor = SourceCursor(sources)
        self.nulls = {}  # column name -> nulls written as NaN
        first = sources[0] if sources else None
        schema = one_layout(sources, "one PLY output needs one vertex layout")
        if first is not None:  # --keep/--drop: the properties written (x, y, z and the colors always)
            schema = select_columns(schema, sources, selection, first.path)
        colors = tuple(color_fields(first)) if first is not None else ()
        # x, y, z as every reader takes them (numeric, the lower-case name first); x and y alone are written too
        xyz = numeric_axes(schema)
        # (output name, column name or None for a color channel, type code, element of a vector column or None)
        self.columns = []
        self.held = None  # coordinates held in a list column or WKB points (xyz_arrays), written as x, y, z
        if None in xyz and first is not None:
            try:
                self.held = point_xyz(schema, first.path, "PLY output", first)
            except UsageError:  # none at all (a cloud of colors alone): vertices without them, said
                missing = [a for a, n in zip("xyz", xyz) if n is None]
                why = not_coordinates(schema)  # (a text x is no coordinate)
                self.note(f"the input has no {', '.join(missing)} coordinate{'s' * (len(missing) > 1)} (nor a list "
                          f"column of three numbers or WKB points{'; its ' + why if why else ''}): its vertices "
                          f"have no {', '.join(missing)} propert{'ies' if len(missing) > 1 else 'y'}")
        if self.held is not None:
            name = xyz_names(self.held)[0]  # one list column or WKB points
            code = "f4" if xyz_float32(schema, self.held) else "f8"  # float stays float, as x, y, z columns do
            self.columns += [(a, self.held, code, j) for j, a in enumerate("xyz")]
            self.note(f"coordinates in column {name!r} ({schema.field(name).type}) written as PLY "
                      f"{TYPE_NAMES[code]} x, y, z")
            xyz = [name]
        for a, name in zip("xyz", xyz if self.held is None else ()):
            if name is not None:
                code = _arrow_to_ply(schema.field(name).type)
                if code is None:
                    raise UnsupportedFormat(f"coordinate column {name!r} has type {schema.field(name).type}, "
                                            "not a number", first.path)
                # double stays double: float would lose the precision of georeferenced coordinates
                code = "f8" if code in ("f8", "i4", "u4") else "f4"
                self.columns.append((a, name, code, None))
                given = schema.field(name).type
                if name != a or str(given) != {"f4": "float", "f8": "double"}[code]:
                    self.note(f"coordinate column {name!r} ({given}) written as PLY {TYPE_NAMES[code]} {a!r}")
        for c in ("red", "green", "blue"):
            self.columns.append((c, None, "u1", None))
        if first is not None:
            self._note_colors(first, schema, colors)
        taken = {"x", "y", "z", "red", "green", "blue"}
        for f in schema:
            if f.name in xyz or f.name in colors:
                continue
            if pa.types.is_fixed_size_list(f.type) and _arrow_to_ply(f.type.value_type) is not None:
                code = _arrow_to_ply(f.type.value_type)
                parts = [f"{f.name}_{j}" for j in range(f.type.list_size)]
                if not _is_ply_name(f.name) or taken & set(parts):
                    self.note(f"column {f.name!r} ({f.type}) dropped: its element names {parts[0]}... are not "
                              "free PLY names")
                    continue
                taken.update(parts)
                self.columns += [(p, f.name, code, j) for j, p in enumerate(parts)]
                self.note(f"column {f.name!r} ({f.type}) written as PLY properties {', '.join(parts)}: "
                          "a PLY property is one number per point")
                continue
            code = _arrow_to_ply(f.type)
            if code is None:
                self.note(f"column {f.name!r} ({f.type}) dropped: {why_not_ply(f.type)}")
                continue
            if f.name in taken:
                self.note(f"column {f.name!r} dropped: the PLY output already has a property of that name")
                continue
            if not _is_ply_name(f.name):
                self.note(f"column {f.name!r} dropped: a PLY property name is ASCII without spaces")
                continue
            change = _type_change(f.type, code)
            if change:
                self.note(f"column {f.name!r} ({f.type}): {change}")
            taken.add(f.name)
            self.columns.append((f.name, f.name, code, None))
        if flag is not None:
            if flag in taken or not _is_ply_name(flag):
                raise UsageError(f"--flag {flag!r}: the input already has a property of that name, or it is not "
                                 "a PLY name", path)
            self.columns.append((flag, flag, "u1", None))
        self.rank = rank
        if rank is not None:
            # PLY has no 64-bit integers: uint when every rank fits, else double (exact below 2^53)
            self.check_rank_name(rank, taken)
            code = "u4" if provenance.get("target", 0) <= 1 << 32 else "f8"
            if code == "f8":
                self.note(f"property {rank!r} written as PLY double: the ranks pass 2^32 and PLY has no 64-bit "
                          "integer (exact up to 2^53)")
            self.columns.append((rank, rank, code, None))
        self.note_skipped_elements()
        self.dtype = np.dtype([(n, "<" + c) for n, _, c, _ in self.columns])
        lines = ["ply", "format binary_little_endian 1.0"]
        if first is not None and first.format == "ply":
            # an input written by prism-stream: its run's provenance is replaced by this run's, not kept first
            lines += [f"comment {c}" for c in first.header.comments if not _is_provenance(c)]
            lines += [f"obj_info {c}" for c in first.header.obj_info]
        self.before = lines
        # no whitespace in it (none between tokens, a space in a string escaped), so it can be cut anywhere
        # into comment lines whose ends no reader strips
        self.provenance_json = json.dumps(provenance, sort_keys=True, default=str,
                                          separators=(",", ":")).replace(" ", "\\u0020")
        self.after = [f"property {TYPE_NAMES[c]} {n}" for n, _, c, _ in self.columns] + ["end_header"]
        self.file = AtomicFile(path)
        try:
            self.out = open(self.file.tmp, "wb")
            self.out.write(self._head(0))
        except OSError as exc:
            self.file.discard()
            raise OutputError(f"cannot write the output: {exc.strerror or exc}", path) from None

    def _head(self, count: int) -> bytes:
        """The header for ``count`` vertices, of the same length whatever the count.

        The count is known only at the end (a directory-mode output holds one input's share of the sample),
        so the header is written first with 0 and rewritten by commit() in place. The digits the count takes
        are given back as spaces inside the provenance comment's JSON, after its opening brace, where JSON
        ignores them: no header line ends in whitespace (PCL warns of that) and no number is padded."""
        digits = str(count)
        if len(digits) > COUNT_WIDTH:
            raise OutputError(f"{count} vertices: more than a PLY output of this writer holds", self.path)
        pad = " " * (COUNT_WIDTH - len(digits))
        pieces = provenance_pieces(self.provenance_json)
        pieces[0] = "{" + pad + pieces[0][1:]
        lines = [*self.before, "comment " + PROVENANCE_COMMENT + pieces[0],
                 *("comment " + CONTINUED + p for p in pieces[1:]), "element vertex " + digits, *self.after]
        return ("\n".join(lines) + "\n").encode("ascii", "replace")

    def _note_colors(self, first: Source, schema: pa.Schema, colors: tuple) -> None:
        """Say how the input's colors become uchar red/green/blue, unless they already are that."""
        types = {str(schema.field(n).type) for n in colors if n in schema.names}
        if tuple(colors) == ("red", "green", "blue") and types == {"uint8"}:
            return
        how = eight_bit_rules(self.decisions)
        what = f"color field {colors[0]!r} (a packed word; alpha, if any, is dropped)" if len(colors) == 1 else \
            f"color columns {', '.join(colors)} ({', '.join(sorted(types))})"
        self.note(f"{what} written as uchar red, green, blue ({how}): a PLY output holds 8-bit color")

    def write(self, chunk: PointChunk, mask: np.ndarray, ranks: np.ndarray | None = None) -> None:
        i = self.cursor.source_index(chunk)
        rows = np.ones(len(mask), dtype=bool) if self.flag is not None else mask
        if not rows.any():
            return
        src = self.sources[i]
        batch = chunk.to_arrow(rows)
        rgb = colors_8bit(tuple(np.asarray(c)[rows] for c in chunk.rgb), self.decisions[i], src.path)
        out = np.empty(batch.num_rows, dtype=self.dtype)
        channel = iter(rgb)
        held = xyz_arrays(batch, self.held, src.path) if self.held is not None else None
        for name, col, code, part in self.columns:
            if col is None:
                out[name] = next(channel)
            elif held is not None and col == self.held:
                out[name] = held[part]
            elif col == self.flag:
                out[name] = mask
            elif col == self.rank:
                out[name] = ranks
            else:
                out[name] = self._values(batch.column(batch.schema.get_field_index(col)), col, code, part, src)
        try:
            self.out.write(out.tobytes())
        except OSError as exc:
            raise OutputError(f"cannot write the output: {exc.strerror or exc}", self.path) from None
        self.written += len(out)

    def _values(self, column: pa.Array, col: str, code: str, part, src: Source) -> np.ndarray:
        """One column's values as PLY ``code``: nulls in floats as NaN (counted), in integers a refusal."""
        if part is not None:  # one element of a vector column
            if column.null_count:
                self._refuse_nulls(col, column.null_count, "vector", src)
            flat = column.flatten()
            size = column.type.list_size
            if flat.null_count and code[0] != "f":
                self._refuse_nulls(col, flat.null_count, TYPE_NAMES[code], src)
            values = to_numpy(flat).reshape(-1, size)[:, part]
            nulls = int(np.asarray(flat.is_null()).reshape(-1, size)[:, part].sum()) if flat.null_count else 0
            name = f"{col}_{part}"
        else:
            nulls = column.null_count
            if nulls and code[0] != "f":
                self._refuse_nulls(col, nulls, TYPE_NAMES[code], src)
            values = to_numpy(column)
            name = col
        if nulls:
            self.nulls[name] = self.nulls.get(name, 0) + nulls
        return values.astype(code)

    def _refuse_nulls(self, col: str, n: int, kind: str, src: Source) -> None:
        raise UnsupportedFormat(f"column {col!r} has {n} points with no value (null) among those written; a PLY "
                                f"{kind} property cannot hold a missing value, so no PLY output is written "
                                "(fill the nulls, or write Parquet)", src.path)

    def _commit(self) -> None:
        for col, n in self.nulls.items():
            self.note(f"property {col!r}: {n} points with no value (null) written as NaN (PLY has no null)")
        head = self._head(self.written)  # an OutputError of its own past the count's width: raised first

        def finish():
            self.out.seek(0)
            self.out.write(head)
            self.out.close()

        self._publish_file(finish)

    def abort(self) -> None:
        self._discard_file(self.out.close)


CONTINUED = "prism-stream+ "  # the comments that carry the rest of a long provenance JSON, in order
PIECE = 900  # characters of JSON a comment line holds: Open3D's PLY reader (rply) aborts on lines over 1,023


def provenance_pieces(text: str) -> list[str]:
    """``text`` (JSON without whitespace) cut into pieces of at most PIECE characters, one comment line each."""
    return [text[i:i + PIECE] for i in range(0, max(len(text), 1), PIECE)]


def provenance_text(comments) -> str | None:
    """The provenance JSON text of a PLY header's comments (its first comment and the ones continuing it)."""
    out = None
    for c in comments:
        if c.startswith(PROVENANCE_COMMENT + "{"):
            out = c[len(PROVENANCE_COMMENT):]
        elif out is not None and c.startswith(CONTINUED):
            out += c[len(CONTINUED):]
    return out


def _is_provenance(comment: str) -> bool:
    return comment.startswith(PROVENANCE_COMMENT + "{") or comment.startswith(CONTINUED)


def read_provenance(path: str) -> dict | None:
    """The provenance a prism-stream PLY output carries in its comments, if any."""
    text = provenance_text(read_header(path).comments)
    return None if text is None else json.loads(text)
