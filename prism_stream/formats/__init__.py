"""The format registry: file extension to reader and writer.

Adding a format is one module here and one line in each table.
"""

from __future__ import annotations

import glob
import os

from ..errors import InputNotFound, UnsupportedFormat
from .base import AtomicFile, ColorChunk, PointChunk, Sink, Source, Unit
from .las import LasSink, LasSource
from .parquet import ParquetSink, ParquetSource
from .parquet import expand as expand_parquet_dir

READERS = {
    ".las": LasSource,
    ".laz": LasSource,
    ".parquet": ParquetSource,
    ".pq": ParquetSource,
}

WRITERS = {
    ".las": LasSink,
    ".laz": LasSink,
    ".parquet": ParquetSink,
    ".pq": ParquetSink,
}

__all__ = ["READERS", "WRITERS", "AtomicFile", "ColorChunk", "PointChunk", "Sink", "Source", "Unit",
           "expand_inputs", "open_source", "open_sink", "extension"]


def extension(path: str) -> str:
    base = os.path.basename(path.rstrip("/")).lower()
    if base.endswith(".copc.laz"):
        return ".laz"
    return os.path.splitext(base)[1]


def expand_inputs(inputs) -> list[str]:
    """Paths, globs and Parquet directories to a list of files.

    A glob or a directory expands in sorted path order; the order of the
    arguments themselves is kept, since it fixes each source's ordinal.
    """
    if isinstance(inputs, (str, os.PathLike)):
        inputs = [inputs]
    files: list[str] = []
    for item in inputs:
        item = os.fspath(item)
        if any(c in item for c in "*?["):
            matches = sorted(p for p in glob.glob(item, recursive=True) if os.path.isfile(p))
            if not matches:
                raise InputNotFound("the pattern matches no file", item)
            files.extend(matches)
        elif os.path.isdir(item):
            files.extend(expand_parquet_dir(item))
        elif os.path.isfile(item):
            files.append(item)
        elif os.path.exists(item):
            raise UnsupportedFormat("not a regular file", item)
        else:
            raise InputNotFound("no such file", item)
    seen = set()
    for f in files:
        key = os.path.realpath(f)
        if key in seen:
            raise UnsupportedFormat("given twice; each input file may appear once", f)
        seen.add(key)
    return files


def open_source(path: str, ordinal: int, **options) -> Source:
    reader = READERS.get(extension(path))
    if reader is None:
        known = ", ".join(sorted(READERS))
        raise UnsupportedFormat(f"unknown input extension {extension(path) or '(none)'!r} (reads {known})", path)
    return reader(path, ordinal, **options)


def open_sink(path: str, sources: list[Source], provenance: dict) -> Sink:
    writer = WRITERS.get(extension(path))
    if writer is None:
        known = ", ".join(sorted(WRITERS))
        raise UnsupportedFormat(f"unknown output extension {extension(path) or '(none)'!r} (writes {known})", path)
    return writer(path, sources, provenance)
