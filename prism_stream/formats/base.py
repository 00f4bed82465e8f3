"""The small reader/writer interface every format implements.

A *source* is one input file. It reads in two ways, as the two passes need:
``color_chunks`` (only the color channels, as cheaply as the format allows)
and ``point_chunks`` (every attribute). Both take a record range, so a work
unit is just (source, start, stop). A *sink* takes point chunks with a keep
mask and commits atomically: it writes under a temporary name
(:mod:`..run.staging`) and renames at the end, or removes what it wrote;
``with open_sink(...) as sink:`` does one or the other.
"""

from __future__ import annotations

import copy
import os
import warnings
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import pyarrow as pa

from ..errors import OutputError, PrismError, PrismWarning, UsageError
from ..run.staging import AtomicFile, public_name  # noqa: F401 - the formats import AtomicFile from here
from .arrow import from_numpy, rows_of
from .columns import common_schema, select_columns


def arrow_array(values: np.ndarray) -> pa.Array:
    """A numpy column as Arrow; a 2-D one (a vector per point) as a fixed-size list."""
    values = np.ascontiguousarray(values)
    if values.ndim == 1:
        return from_numpy(values)
    return pa.FixedSizeListArray.from_arrays(from_numpy(values.reshape(-1)), values.shape[1])


def rows(records: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``records[mask]`` for a structured array (a mask of booleans or of indices), as a ``take``: under an
    index numpy copies structured records field by field, several times slower (bench/PROFILE.md)."""
    at = np.flatnonzero(mask) if mask.dtype == np.bool_ else mask
    return records.take(at)


def columns_to_arrow(columns, mask: np.ndarray | None = None) -> pa.RecordBatch:
    """Named numpy columns (a dict, or a structured array's fields) as a record batch, optionally masked."""
    names = list(columns.dtype.names) if isinstance(columns, np.ndarray) else list(columns)
    arrays = [arrow_array(columns[n] if mask is None else columns[n][mask]) for n in names]
    return pa.RecordBatch.from_arrays(arrays, names=names)


@dataclass
class ColorChunk:
    start: int  # record index of the first point in its source
    rgb: tuple  # three arrays of equal length

    def __len__(self) -> int:
        return len(self.rgb[0])


class PointChunk:
    """A run of records with every attribute; formats subclass it."""

    start: int
    rgb: tuple

    def __len__(self) -> int:
        return len(self.rgb[0])

    def to_arrow(self, mask: np.ndarray | None = None) -> pa.RecordBatch:
        raise NotImplementedError

    def take(self, mask: np.ndarray) -> "PointChunk":
        """The masked records as a chunk of the same kind (the candidates pass one keeps for pass two).

        ``mask`` is booleans, or the indices of the records to keep. Every per-point attribute is masked:
        numpy arrays, Arrow record
        batches, laspy point records, and tuples or dicts of them (the
        colors, named columns); anything else (a header, names) is shared.
        """
        out = copy.copy(self)
        for name, value in vars(self).items():
            setattr(out, name, _masked(value, mask))
        return out


def _masked(value, mask: np.ndarray):
    if isinstance(value, pa.RecordBatch):
        return rows_of(value, mask)
    if isinstance(value, np.ndarray):
        return rows(value, mask) if value.dtype.names else value[mask]
    if hasattr(value, "point_format") and hasattr(value, "array"):
        # laspy's point records (a header has a point format too, but no records)
        return value[mask]
    if isinstance(value, tuple):
        return tuple(_masked(v, mask) for v in value)
    if isinstance(value, dict):
        return {k: _masked(v, mask) for k, v in value.items()}
    return value


@dataclass(frozen=True)
class Unit:
    """A work unit: records [start, stop) of one source."""

    source: "Source"
    start: int
    stop: int

    def color_chunks(self, chunk_size: int) -> Iterator[ColorChunk]:
        return self.source.color_chunks(chunk_size, self.start, self.stop)

    def point_chunks(self, chunk_size: int) -> Iterator[PointChunk]:
        return self.source.point_chunks(chunk_size, self.start, self.stop)

    @property
    def points(self) -> int | None:
        """Records in the unit; None while a source's count is unknown (a query before pass one)."""
        return None if self.stop is None else self.stop - self.start


class Source:
    """One input file. Subclasses set ``count`` and implement the readers."""

    format = "?"
    path: str
    ordinal: int
    count: int  # points, as the file declares them (checked against the data)
    # what pass two says when its read of the source differs from pass one's
    changed = "the file changed between the two passes"
    reread_may_differ = False  # pass two checks its keys against pass one's (a query run twice)
    reads_remote = False  # reads a URL (s3://...) through file objects (run/remote.py), not only a local path

    def whole(self) -> "Unit":
        """The whole source as one work unit."""
        return Unit(self, 0, self.count)

    def units(self, unit_size: int) -> list[Unit]:
        """Record ranges of about ``unit_size`` points, aligned to the format's natural blocks."""
        edges = list(range(0, self.count, max(1, unit_size))) + [self.count]
        return [Unit(self, a, b) for a, b in zip(edges[:-1], edges[1:])] or [Unit(self, 0, 0)]

    def color_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[ColorChunk]:
        raise NotImplementedError

    def point_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None) -> Iterator[PointChunk]:
        raise NotImplementedError

    def arrow_schema(self) -> pa.Schema:
        """Schema of ``to_arrow`` batches (what a Parquet sink writes)."""
        raise NotImplementedError

    # The one-read path keeps pass one's candidates on disk: ``spill_state(chunk, at)`` gives the records at
    # the indices ``at`` as something picklable (by default the chunk's ``take``: same kind, fewer records), and
    # ``restore`` makes a chunk of them again, marked with the source's ordinal so that a sink knows whose
    # records these are.
    spills = False  # True when point chunks implement ``take`` and survive the round trip

    def spill_state(self, chunk: PointChunk, at: np.ndarray):
        return chunk.take(at)

    def restore(self, state) -> PointChunk:
        state.ordinal = self.ordinal
        return state

    def describe(self) -> dict:
        """Format facts for provenance (version, point format, schema...)."""
        return {"format": self.format}

    def prestart(self) -> None:
        """Start what the reads will need ahead of them (LAZ: its decoder processes); nothing by default."""

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


@dataclass(frozen=True)
class WriteOptions:
    """What a run asks of a writer beside the points: every writer is opened with it whole
    (:meth:`Sink.open`) and refuses what it cannot do (:meth:`Sink.refuse`)."""

    flag: str | None = None  # write every point, with this flag column (1 = kept)
    geometry: bool = False  # add a GeoParquet geometry column
    rank: str | None = None  # add each point's rank in a column of this name
    columns: str = "same"  # how inputs with different columns share one output (Parquet)
    grid: tuple | None = None  # (scales, offsets or None): the LAS grid of points converted from other formats
    selection: tuple | None = None  # ("keep" or "drop", names): --keep/--drop


class Sink:
    """An output; ``write`` gets chunks and their keep masks, ``commit`` publishes, ``abort`` removes.

    Used as a context manager: committed when the block ends normally,
    aborted (nothing left behind) when it raises.

    A writer of the registry (``formats.WRITERS``) is opened by :meth:`open`
    and says by its class attributes which options it takes; :meth:`refuse`
    refuses the rest, from the options and the inputs' headers alone.
    """

    takes_columns = False  # --columns union/intersection
    takes_geometry = False  # --geometry
    takes_grid = False  # --scale/--offset

    @classmethod
    def open(cls, path: str, sources: list, provenance: dict, options: WriteOptions) -> "Sink":
        """The writer of ``path`` for these inputs (the one constructor every writer of the registry has)."""
        raise NotImplementedError

    @classmethod
    def refuse(cls, path: str, sources: list, options: WriteOptions) -> None:
        """Refuse what this writer cannot write, before a point is decoded (``path``: as the user named it)."""
        if options.columns != "same" and not cls.takes_columns:
            raise UsageError(f"--columns {options.columns} writes inputs with different columns together: it needs "
                             "Parquet output (or an output folder: one output per input)", path)
        # what --columns refuses (a type no one type holds...); Parquet writes the inputs' common columns, the
        # other formats the first input's layout
        common = common_schema(sources, options.columns)[0] if cls.takes_columns and sources else None
        if options.selection is not None and sources:
            schema = common if cls.takes_columns else sources[0].arrow_schema()
            select_columns(schema, sources, options.selection, sources[0].path)
        cls.refuse_selection(path, sources, options)
        if options.geometry and not cls.takes_geometry:
            raise UsageError("--geometry adds a GeoParquet geometry column: it needs Parquet output", path)
        if options.grid is not None and not cls.takes_grid:
            raise UsageError("--scale and --offset set the coordinate grid of LAS, LAZ or COPC output", path)
        cls.refuse_own(path, sources, options)

    @classmethod
    def refuse_selection(cls, path: str, sources: list, options: WriteOptions) -> None:
        """What this format refuses of --keep/--drop beyond a name the inputs lack."""

    @classmethod
    def refuse_own(cls, path: str, sources: list, options: WriteOptions) -> None:
        """What this format alone refuses."""

    def __init__(self, path: str, sources: list[Source], provenance: dict):
        self.path = path
        self.sources = sources
        self.provenance = provenance
        self.written = 0
        self.notes: list[str] = []  # what this output changed or left out, and why (one line each)

    def note(self, message: str) -> None:
        """Say that the output changes or leaves out something of the input: kept in ``notes``, and
        warned when the output is committed (a run that fails has no output to warn about).

        The output-fidelity rule: nothing is dropped or changed silently.
        """
        self.notes.append(f"{public_name(self.path)}: {message}")  # a staged output: where it is published

    def note_depths(self, sources, provenance: dict) -> None:
        """Inputs of different color depths in one output that writes colors as they are (Parquet, LAS from
        LAS): its color columns hold both scales, which a sample of it reads as one. An empty input has none."""
        from .conversion import depth_decisions

        by: dict = {}
        for s, d in zip(sources, depth_decisions(sources, provenance)):
            if s.count != 0:
                by.setdefault({"8": "8-bit", "16": "16-bit", "float": "fractional"}.get(d, d), []).append(
                    os.path.basename(s.path))
        if len(by) > 1:
            said = "; ".join(f"{k} in {', '.join(v[:3])}{' and more' if len(v) > 3 else ''}" for k, v in by.items())
            self.note(f"the inputs' colors differ in depth ({said}): written as they are, one output's color "
                      "columns hold both scales, which a sample of it reads as one; an output folder (one output "
                      "per input) keeps them apart")

    def note_crs_not_written(self, kind: str) -> None:
        """A format with no place for a CRS (PLY, XYZ): say that the inputs' CRS is not written."""
        from .geo import source_crs

        names = sorted({crs.name for crs in (source_crs(s) for s in self.sources) if crs is not None})
        if names:
            self.note(f"the input's CRS ({'; '.join(names)}) is not written: {kind} has no place for one "
                      "(LAS, LAZ, COPC and Parquet outputs keep it)")

    def note_skipped_elements(self) -> None:
        """PLY inputs: the elements other than the vertices (faces...) are not part of the cloud."""
        for s in self.sources:
            skipped = s.describe().get("skipped_elements") if s.format == "ply" else None
            if skipped:
                listed = ", ".join(f"{name} ({n} records)" for name, n in skipped.items())
                self.note(f"PLY element(s) {listed} of {os.path.basename(s.path)} not written: "
                          "the output holds the vertices (points) only")

    def write(self, chunk: PointChunk, mask: np.ndarray, ranks: np.ndarray | None = None) -> None:
        """Write the chunk's points under ``mask`` (``ranks``: the rank of each, for a sink opened with a rank column)."""
        raise NotImplementedError

    def check_rank_name(self, name: str, taken, limit: int | None = None) -> None:
        """Refuse a rank column whose name the input already uses (an output ranked before)."""
        if name in set(taken):
            raise UsageError(f"the input already has a {name!r} attribute (a ranked output?); rank the original "
                             "input, or drop that attribute first", self.sources[0].path if self.sources else self.path)
        if limit is not None and len(name.encode()) > limit:
            raise UsageError(f"rank column {name!r}: names hold at most {limit} bytes here", self.path)

    quiet = False  # True: the caller says the notes (a Dask task's sink, whose driver warns them once)

    def commit(self) -> None:
        """Publish the output; then warn of every note (what it changed or left out of the input)."""
        self._commit()
        for text in self.notes if not self.quiet else ():
            warnings.warn(text, PrismWarning, stacklevel=2)

    def own_notes(self) -> list[str]:
        """The notes without the output's name in front (a staged output's, said under its published name)."""
        prefix = public_name(self.path) + ": "
        return [n[len(prefix):] if n.startswith(prefix) else n for n in self.notes]

    def _commit(self) -> None:
        raise NotImplementedError

    def abort(self) -> None:
        raise NotImplementedError

    def _publish_file(self, finish) -> None:
        """``finish()`` (write the last bytes, close the staged file ``self.file``), then publish it; a failure
        removes it and is the output's one-line error."""
        try:
            finish()
        except OSError as exc:
            self.file.discard()
            raise OutputError(f"cannot write the output: {exc.strerror or exc}", self.path) from None
        self.file.commit()

    def _discard_file(self, close) -> None:
        """``close()`` the staged file, whatever it raises, and remove it."""
        try:
            close()
        except BaseException:  # noqa: BLE001 - the half-written file is deleted next
            pass
        self.file.discard()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        try:
            if exc_type is None:
                self.commit()
            else:
                self.abort()
        except PrismError as failed:
            self._name_the_output(failed)
            raise
        if isinstance(exc, PrismError):
            self._name_the_output(exc)
        return False

    def _name_the_output(self, error: PrismError) -> None:
        """An error about a staged output names where it would have been published, as the notes do."""
        if error.path is not None and os.fspath(error.path) == os.fspath(self.path):
            error.path = public_name(self.path)
