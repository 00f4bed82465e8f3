"""The format registry: file extension to reader and writer.

Adding a format is one module here and one line in each table.
"""

from __future__ import annotations

import os

from ..errors import UnsupportedFormat, UsageError
from ..run.remote import is_remote
from .base import AtomicFile, ColorChunk, PointChunk, Sink, Source, Unit, public_name
from .e57 import E57Source
from .las import LasSource, las_sink
from .parquet import ParquetSink, ParquetSource
from .pcd import PcdSource
from .ply import PlySink, PlySource
from .xyz import XyzSource

READERS = {
    ".las": LasSource,
    ".laz": LasSource,
    ".copc.laz": LasSource,
    ".parquet": ParquetSource,
    ".pq": ParquetSource,
    ".ply": PlySource,
    ".pcd": PcdSource,
    ".e57": E57Source,
    ".xyz": XyzSource,
}



def copc_sink(path: str, sources: list[Source], provenance: dict, flag: str | None = None,
              rank: str | None = None, grid: tuple | None = None, selection: tuple | None = None) -> Sink:
    """COPC out (``.copc.laz``): the LAS writer's output rebuilt as an octree of LAZ chunks."""
    from .copc import CopcSink

    return CopcSink(path, sources, provenance, flag=flag, rank=rank, grid=grid, selection=selection)


WRITERS = {
    ".las": las_sink,
    ".laz": las_sink,
    ".copc.laz": copc_sink,
    ".parquet": ParquetSink,
    ".pq": ParquetSink,
    ".ply": PlySink,
}

__all__ = ["READERS", "WRITERS", "AtomicFile", "ColorChunk", "PointChunk", "Sink", "Source", "Unit",
           "open_source", "open_sink", "extension"]


def extension(path: str) -> str:
    """The lower-case extension that names the format: ``.copc.laz`` is one, COPC (read as any LAZ)."""
    base = os.path.basename(path.rstrip("/")).lower()
    if base.endswith(".copc.laz"):
        return ".copc.laz"
    return os.path.splitext(base)[1]


def open_source(path: str, ordinal: int, **options) -> Source:
    reader = READERS.get(extension(path))
    if reader is None:
        known = ", ".join(sorted(READERS))
        raise UnsupportedFormat(f"unknown input extension {extension(path) or '(none)'!r} (reads {known})", path)
    if not reader.reads_remote and is_remote(path):
        readable = ", ".join(sorted(e for e, r in READERS.items() if r.reads_remote))
        raise UnsupportedFormat(f"{extension(path)} files are read from local paths only (from the store: "
                                f"{readable}); copy it here first", path)
    return reader(path, ordinal, **options)


def check_sink(path: str, sources: list[Source], flag: str | None = None, geometry: bool = False,
               columns: str = "same", grid: tuple | None = None, selection: tuple | None = None) -> None:
    """Refuse, from the options and the headers alone, what :func:`open_sink` would refuse for ``path`` (the
    output's own name): called before pass one, so that no input is decoded for a run that cannot write."""
    writer = WRITERS.get(extension(path))
    if writer is None:
        known = ", ".join(sorted(WRITERS))
        raise UnsupportedFormat(f"unknown output extension {extension(path) or '(none)'!r} (writes {known})", path)
    if columns != "same" and writer is not ParquetSink:
        raise UsageError(f"--columns {columns} writes inputs with different columns together: it needs Parquet "
                         "output (or an output folder: one output per input)", path)
    if selection is not None and sources:
        from .parquet import common_schema, select_columns

        # Parquet writes the inputs' common columns; LAS and PLY the first input's layout
        schema = common_schema(sources, columns)[0] if writer is ParquetSink else sources[0].arrow_schema()
        select_columns(schema, sources, selection, sources[0].path)
        if writer in (las_sink, copc_sink) and isinstance(sources[0], LasSource):
            from .las import left_out

            left_out(sources[0], selection, flag)  # what a LAS record keeps whatever --drop says
    if geometry and writer is not ParquetSink:
        raise UsageError("--geometry adds a GeoParquet geometry column: it needs Parquet output", path)
    if writer in (las_sink, copc_sink) and flag is not None and sources and not all(
            isinstance(s, LasSource) for s in sources):
        raise UsageError("--flag with LAS output needs LAS/LAZ inputs; write Parquet for a flag column", path)
    if grid is not None:
        if writer not in (las_sink, copc_sink):
            raise UsageError("--scale and --offset set the coordinate grid of LAS, LAZ or COPC output", path)
        if sources and all(isinstance(s, LasSource) for s in sources):
            from .las import GRID_OF_LAS_INPUTS

            raise UsageError(GRID_OF_LAS_INPUTS, path)
    if writer is copc_sink:
        from .copc import refuse_clashes

        refuse_clashes(sources, selection)


def open_sink(path: str, sources: list[Source], provenance: dict, flag: str | None = None,
              geometry: bool = False, rank: str | None = None, columns: str = "same",
              grid: tuple | None = None, selection: tuple | None = None) -> Sink:
    """The writer of ``path``'s format; ``rank`` names the column of each point's rank (``write(..., ranks=)``);
    ``columns``: how inputs with different columns share one output (Parquet only). What it refuses is
    :func:`check_sink`'s, named as the output is published."""
    check_sink(public_name(path), sources, flag=flag, geometry=geometry, columns=columns, grid=grid,
               selection=selection)
    writer = WRITERS[extension(path)]
    if selection is not None:
        if writer is ParquetSink:
            return writer(path, sources, provenance, flag=flag, geometry=geometry, rank=rank, columns=columns,
                          selection=selection)
        if writer is PlySink:
            return writer(path, sources, provenance, flag=flag, rank=rank, selection=selection)
        return writer(path, sources, provenance, flag=flag, rank=rank, grid=grid, selection=selection)
    if columns != "same":
        return writer(path, sources, provenance, flag=flag, geometry=geometry, rank=rank, columns=columns)
    if geometry:
        return writer(path, sources, provenance, flag=flag, geometry=True, rank=rank)
    if grid is not None:
        return writer(path, sources, provenance, flag=flag, rank=rank, grid=grid)
    if rank is not None:
        return writer(path, sources, provenance, rank=rank)
    if flag is not None:
        return writer(path, sources, provenance, flag=flag)
    return writer(path, sources, provenance)
