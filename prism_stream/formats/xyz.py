"""XYZRGB text in (``.xyz``, ``.txt`` exports of Agisoft, CloudCompare...): one point a line.

Columns are ``x y z red green blue`` and any further numbers, separated by
spaces, tabs or commas. Colors are integers (the per-file 8/16-bit rule of
SPEC 1) or, if any color has a fraction, floats in [0, 1]. Lines starting
with ``#`` or ``//`` and blank lines are not points. The further columns take
their names from a header (the last ``//`` or ``#`` line before the first
point, as CloudCompare writes ``//X Y Z R G B Intensity``, or a first line of
names, ``X,Y,Z,R,G,B,Intensity``: a first line with no number in it, which
must then name every column) when it names x y z r g b (or red green blue)
first and one name a column; else, and for a name that is empty, taken or
``field_<j>``, ``field_7``, ``field_8``... Counting the points takes one
quick read at open; then the file is parsed a chunk of lines at a time.
"""

from __future__ import annotations

import os
from typing import Iterator

import numpy as np
import pyarrow as pa

from ..errors import CorruptInput, NoColorError, UnsupportedFormat
from .base import ColorChunk, PointChunk, Source, columns_to_arrow
from .guard import reading
from .xyzout import PROVENANCE_LINE

PROVENANCE = PROVENANCE_LINE.encode()  # our XYZ writer's provenance line, not a header of the columns
NAMES = ("x", "y", "z", "red", "green", "blue")
LINES = 1 << 16


BOM = b"\xef\xbb\xbf"  # UTF-8's byte order mark, which some Windows tools put before the first line


def _is_point(line: bytes) -> bool:
    s = line.strip().removeprefix(BOM)
    return bool(s) and not s.startswith((b"#", b"//"))


def _split(line: bytes) -> list:
    return line.removeprefix(BOM).replace(b",", b" ").split()


def _header_names(tokens: list, width: int) -> tuple[str, ...] | None:
    """The names of the columns after the colors, if ``tokens`` are a header of lines ``width`` values wide:
    x y z, then r g b or red green blue (any case), then one name a column."""
    names = [t.decode("utf-8", "replace") for t in tokens]
    low = [n.lower() for n in names]
    if len(names) != width or low[:3] != ["x", "y", "z"] or low[3:6] not in (["r", "g", "b"], ["red", "green", "blue"]):
        return None
    return tuple(names[6:])


def _extra_names(header: tuple[str, ...] | None, width: int) -> tuple[str, ...]:
    """Column 7's name and the rest: the header's where it gives one that is free, else ``field_<j>``."""
    taken = {n.lower() for n in NAMES}
    out = []
    for j in range(6, width):
        name = header[j - 6] if header is not None else ""
        if not name or not name.isprintable() or name.lower() in taken or name.lower().startswith("field_"):
            name = f"field_{j + 1}"
        taken.add(name.lower())
        out.append(name)
    return tuple(out)


def _is_number(token: bytes) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


class XyzPointChunk(PointChunk):
    def __init__(self, ordinal: int, start: int, values: np.ndarray, names, color_kind: str):
        self.ordinal = ordinal
        self.start = start
        self.names = names
        self.columns = {}
        for j, n in enumerate(names):
            v = values[:, j]
            self.columns[n] = v.astype(np.uint16) if (3 <= j < 6 and color_kind == "int") else v
        self.rgb = tuple(self.columns[n] for n in NAMES[3:])

    def to_arrow(self, mask: np.ndarray | None = None) -> pa.RecordBatch:
        return columns_to_arrow({n: self.columns[n] for n in self.names}, mask)


class XyzSource(Source):
    format = "xyz"
    spills = True  # point chunks implement take; the default spill state (the chunk) pickles

    def __init__(self, path: str, ordinal: int, **_):
        self.path = path
        self.ordinal = ordinal
        self.count, width, fractional = 0, None, False
        comment, self.header_row = None, False  # the last comment line before the first point; a line of names
        with reading(path, "cannot read the XYZ text"), open(path, "rb") as f:
            for line in f:
                if not _is_point(line):
                    text = line.strip().removeprefix(BOM)
                    if width is None and text and not self.header_row and not text.startswith(PROVENANCE):
                        comment = _split(text.lstrip(b"/#"))  # a comment, not our provenance, before any names row
                    continue
                row = _split(line)
                if width is None and not self.header_row and not any(_is_number(v) for v in row):
                    comment, self.header_row = row, True  # a first line of names, not a point
                    continue
                if width is None:
                    width = len(row)
                    if width < 6:
                        raise NoColorError(f"lines hold {width} values; XYZRGB needs x y z red green blue", path)
                elif len(row) != width:
                    raise CorruptInput(f"point {self.count} has {len(row)} values, the first has {width}", path)
                try:
                    colors = [float(v) for v in row[3:6]]
                except ValueError:
                    raise CorruptInput(f"point {self.count}: color {b' '.join(row[3:6]).decode('ascii', 'replace')!r} "
                                       "is not a number", path) from None
                fractional = fractional or any(c != int(c) for c in colors if np.isfinite(c))
                self.count += 1
        if width is None:
            raise UnsupportedFormat("no points in the text (expected lines of x y z red green blue)", path)
        header = _header_names(comment or [], width)
        if self.header_row and header is None:
            raise CorruptInput(f"the first line ({b' '.join(comment[:8]).decode('utf-8', 'replace')!r}) is neither a "
                               f"point nor the names of the {width} columns (x y z r g b ...)", path)
        self.width = width
        self.color_kind = "float" if fractional else "int"
        self.names = NAMES + _extra_names(header, width)
        self.color_fields = NAMES[3:]

    def _chunks(self, chunk_size: int, start: int, stop: int | None) -> Iterator[XyzPointChunk]:
        stop = self.count if stop is None else min(stop, self.count)
        if stop <= start:
            return
        chunk_size = max(1, min(chunk_size, LINES))
        with reading(self.path), open(self.path, "rb") as f:
            pos, rows, names_left = 0, [], self.header_row
            for line in f:
                if not _is_point(line):
                    continue
                if names_left:  # the first line of names
                    names_left = False
                    continue
                if pos >= start:
                    rows.append(_split(line))
                pos += 1
                if len(rows) == chunk_size or pos == stop:
                    yield self._chunk(pos - len(rows), rows)
                    rows = []
                if pos == stop:
                    return
        raise CorruptInput("the file changed while it was read", self.path)

    def _chunk(self, first: int, rows) -> XyzPointChunk:
        try:
            values = np.array(rows, dtype=np.float64).reshape(len(rows), self.width)
        except ValueError:
            raise CorruptInput(f"a value near point {first} is not a number", self.path) from None
        if self.color_kind == "int":
            c = values[:, 3:6]
            if not ((c >= 0) & (c <= 65535)).all():
                raise CorruptInput(f"a color near point {first} is outside 0..65535", self.path)
        return XyzPointChunk(self.ordinal, first, values, self.names, self.color_kind)

    def color_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[ColorChunk]:
        for c in self._chunks(chunk_size, start, stop):
            yield ColorChunk(c.start, c.rgb)

    def point_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[XyzPointChunk]:
        yield from self._chunks(chunk_size, start, stop)

    def arrow_schema(self) -> pa.Schema:
        return XyzPointChunk(self.ordinal, 0, np.zeros((0, self.width)), self.names, self.color_kind).to_arrow().schema

    def describe(self) -> dict:
        return {"format": "xyz", "columns": list(self.names), "colors": self.color_kind,
                "bytes": os.path.getsize(self.path)}
