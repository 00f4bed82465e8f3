"""The format registry: file extension to reader and writer.

Adding a format is one module here and one line in a table: a reader is a
:class:`.base.Source`, a writer a :class:`.base.Sink` opened by
``Sink.open(path, sources, provenance, options)`` (see ``xyzout.py``).
"""

from __future__ import annotations

import os

from ..errors import UnsupportedFormat
from ..run.remote import is_remote
from .base import AtomicFile, ColorChunk, PointChunk, Sink, Source, Unit, WriteOptions, public_name
from .copc import CopcSink
from .e57 import E57Source
from .las import LasSink, LasSource
from .parquet import ParquetSink, ParquetSource
from .pcd import PcdSource
from .ply import PlySink, PlySource
from .xyz import XyzSource
from .xyzout import XyzSink

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

WRITERS = {
    ".las": LasSink,
    ".laz": LasSink,
    ".copc.laz": CopcSink,
    ".parquet": ParquetSink,
    ".pq": ParquetSink,
    ".ply": PlySink,
    ".xyz": XyzSink,
}

__all__ = ["READERS", "WRITERS", "AtomicFile", "ColorChunk", "PointChunk", "Sink", "Source", "Unit", "WriteOptions",
           "check_sink", "extension", "open_sink", "open_source", "writer_of"]


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


def writer_of(path: str) -> type[Sink]:
    """The writer class of ``path``'s extension, or a one-line refusal listing the ones there are."""
    writer = WRITERS.get(extension(path))
    if writer is None:
        known = ", ".join(sorted(WRITERS))
        raise UnsupportedFormat(f"unknown output extension {extension(path) or '(none)'!r} (writes {known})", path)
    return writer


def check_sink(path: str, sources: list[Source], options: WriteOptions = WriteOptions()) -> None:
    """Refuse, from the options and the headers alone, what :func:`open_sink` would refuse for ``path`` (the
    output's own name): called before pass one, so that no input is decoded for a run that cannot write."""
    writer_of(path).refuse(path, sources, options)


def open_sink(path: str, sources: list[Source], provenance: dict, options: WriteOptions = WriteOptions()) -> Sink:
    """The writer of ``path``'s format for ``sources``, with ``provenance`` in its metadata; what it refuses is
    :func:`check_sink`'s, named as the output is published."""
    check_sink(public_name(path), sources, options)
    return WRITERS[extension(path)].open(path, sources, provenance, options)
