"""XYZRGB text out (``.xyz``): one point a line, as CloudCompare, Agisoft and most viewers read it.

The first line names the columns (``//X Y Z R G B`` and the rest, as
CloudCompare's own ASCII export writes them: a line starting with ``//`` is
a comment to readers that do not look for names); the second carries the
provenance (``// prism-stream {...}``). Coordinates are written in the
shortest text that reads back as the same double; colors as 8-bit integers
(the run's color-depth decision), as a text reader expects them; every other
numeric column as a number. What text cannot hold is said, never silently
lost (a note and a warning each).

This module is also the small example of a writer: a :class:`.base.Sink`
with ``open``, ``write``, ``_commit`` and ``abort``, and one line in
``formats.WRITERS``.
"""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa

from ..errors import OutputError, UsageError
from .arrow import from_numpy, string_scalar
from .base import AtomicFile, PointChunk, Sink, Source, WriteOptions
from .columns import one_layout, select_columns
from .conversion import SourceCursor, color_fields, colors_8bit, depth_decisions, eight_bit_rules
from .parquet import point_xyz, xyz_arrays, xyz_names

PROVENANCE_LINE = "// prism-stream "


def _numeric(t: pa.DataType) -> bool:
    return pa.types.is_integer(t) or pa.types.is_floating(t) or pa.types.is_boolean(t)


class XyzSink(Sink):
    """``x y z red green blue`` and every other numeric column, space-separated, one point a line."""

    @classmethod
    def refuse_own(cls, path: str, sources: list, options: WriteOptions) -> None:
        if sources:  # the points' coordinates must be there to write
            point_xyz(sources[0].arrow_schema(), sources[0].path, "XYZ output", sources[0])

    @classmethod
    def open(cls, path: str, sources: list[Source], provenance: dict, options: WriteOptions) -> "XyzSink":
        return cls(path, sources, provenance, options)

    def __init__(self, path: str, sources: list[Source], provenance: dict, options: WriteOptions):
        super().__init__(path, sources, provenance)
        if not sources:
            raise UsageError("XYZ output needs at least one input", path)
        self.note_crs_not_written("XYZ text")
        self.flag, self.rank = options.flag, options.rank
        self.decisions = depth_decisions(sources, provenance)
        self.cursor = SourceCursor(sources)
        first = sources[0]
        schema = select_columns(one_layout(sources, "one XYZ output needs one column layout"), sources, options.selection, first.path)
        # x, y, z columns, or a list column or WKB points (written as x y z)
        self.xyz = point_xyz(schema, first.path, "XYZ output", first)
        held = xyz_names(self.xyz)
        colors = color_fields(first)
        self.others = []  # the other columns written, in the input's order
        header = {a: a.upper() for a in "xyzrgb"}  # the header's names by their lower case (readers match so)
        for f in schema:
            if f.name in held or f.name in colors:
                continue
            if not _numeric(f.type):
                self.note(f"column {f.name!r} ({f.type}) dropped: an XYZ line holds numbers")
            elif not f.name or any(c in f.name for c in " ,") or not f.name.isprintable():
                # (a reader splits the header line at spaces, tabs and commas, as the points' lines)
                self.note(f"column {f.name!r} dropped: its name would not fit the header line")
            elif f.name.lower() in header:  # X beside x: a header naming one column twice
                self.note(f"column {f.name!r} dropped: the header line already names a column "
                          f"{header[f.name.lower()]}")
            else:
                self.others.append(f.name)
                header[f.name.lower()] = f.name
        if not (colors == ("red", "green", "blue") and {str(schema.field(c).type) for c in colors} == {"uint8"}):
            self.note(f"colors {', '.join(colors)} written as 8-bit R G B ({eight_bit_rules(self.decisions)}): XYZ "
                      "text holds 8-bit color")
        taken = {n.lower() for n in ("x", "y", "z", "r", "g", "b", *self.others)}
        for name in (self.flag, self.rank):
            if name is not None and (name.lower() in taken or " " in name):
                raise UsageError(f"{name!r}: the input already has a column of that name, or it has a space", path)
        names = ["X", "Y", "Z", "R", "G", "B", *self.others, *(n for n in (self.flag, self.rank) if n is not None)]
        self.nulls: dict[str, int] = {}
        self.file = AtomicFile(path)
        try:
            self.out = open(self.file.tmp, "w", encoding="utf-8", newline="\n")
            self.out.write("//" + " ".join(names) + "\n")
            self.out.write(PROVENANCE_LINE + json.dumps(provenance, sort_keys=True, default=str) + "\n")
        except OSError as exc:
            self.file.discard()
            raise OutputError(f"cannot write the output: {exc.strerror or exc}", path) from None

    def _text(self, values, name: str) -> pa.Array:
        column = from_numpy(values) if not isinstance(values, (pa.Array, pa.ChunkedArray)) else values
        if pa.types.is_boolean(column.type):
            column = column.cast(pa.uint8())
        elif pa.types.is_floating(column.type) and column.type != pa.float64():
            column = column.cast(pa.float64())  # a float32's shortest text as a double: the value read back is it
        if column.null_count:
            self.nulls[name] = self.nulls.get(name, 0) + column.null_count
        import pyarrow.compute as pc  # on first use: a run that writes no text does not load it

        text = column.cast(pa.string())
        return pc.fill_null(text, "nan") if column.null_count else text

    def write(self, chunk: PointChunk, mask: np.ndarray, ranks: np.ndarray | None = None) -> None:
        i = self.cursor.source_index(chunk)
        rows = np.ones(len(mask), dtype=bool) if self.flag is not None else mask
        if not rows.any():
            return
        batch = chunk.to_arrow(rows)
        column = {n: batch.column(batch.schema.get_field_index(n)) for n in self.others}
        rgb = colors_8bit(tuple(np.asarray(c)[rows] for c in chunk.rgb), self.decisions[i], self.sources[i].path)
        if isinstance(self.xyz, list):  # each column's own text (its type's shortest)
            xyz = [(batch.column(batch.schema.get_field_index(n)), n) for n in self.xyz]
        else:
            xyz = list(zip(xyz_arrays(batch, self.xyz, self.sources[i].path), "xyz"))
        parts = [self._text(c, n) for c, n in xyz] + [self._text(c, "rgb") for c in rgb]
        parts += [self._text(column[n], n) for n in self.others]
        if self.flag is not None:
            parts.append(self._text(mask.astype(np.uint8), self.flag))
        if self.rank is not None:
            parts.append(self._text(np.asarray(ranks, dtype=np.int64), self.rank))
        import pyarrow.compute as pc

        lines = pc.binary_join_element_wise(*parts, string_scalar(" "))
        try:
            self.out.write("\n".join(lines.to_pylist()) + "\n")
        except OSError as exc:
            raise OutputError(f"cannot write the output: {exc.strerror or exc}", self.path) from None
        self.written += len(lines)

    def _commit(self) -> None:
        for name, n in self.nulls.items():
            self.note(f"column {name!r}: {n} points with no value (null) written as nan")
        self._publish_file(self.out.close)

    def abort(self) -> None:
        self._discard_file(self.out.close)


def read_provenance(path: str) -> dict | None:
    """The provenance a prism-stream XYZ output carries on its second line, if any."""
    with open(path, encoding="utf-8", errors="replace") as f:
        for _, line in zip(range(2), f):
            if line.startswith(PROVENANCE_LINE):
                return json.loads(line[len(PROVENANCE_LINE):])
    return None
