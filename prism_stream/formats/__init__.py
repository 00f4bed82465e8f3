"""The format registry: file extension to reader and writer.

Adding a format is one module here and one line in a table: a reader is a
:class:`.base.Source`, a writer a :class:`.base.Sink` opened by
``Sink.open(path, sources, provenance, options)`` (see ``xyzout.py``).
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Mapping

from ..errors import UnsupportedFormat
from ..run.remote import is_remote
from .base import AtomicFile, ColorChunk, PointChunk, Sink, Source, Unit, WriteOptions, public_name


class _Registry(Mapping):
    """Extension -> class, each format's module imported the first time its class is asked for: a run imports
    the formats it reads and writes, not every one (laspy, with the pyproj and requests it imports, is a tenth
    of a second of a Parquet run's start; bench/RESULTS_STARTUP.md). ``in`` and the keys import nothing."""

    def __init__(self, names: dict[str, str]):
        self._names = names  # extension -> "module:Class" (a module of this package)
        self._classes: dict[str, type] = {}

    def __getitem__(self, ext: str) -> type:
        found = self._classes.get(ext)
        if found is None:
            module, name = self._names[ext].split(":")
            found = self._classes[ext] = getattr(importlib.import_module(f".{module}", __name__), name)
        return found

    def __contains__(self, ext) -> bool:
        return ext in self._names

    def __iter__(self):
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)


READERS = _Registry({
    ".las": "las:LasSource",
    ".laz": "las:LasSource",
    ".copc.laz": "las:LasSource",
    ".parquet": "parquet:ParquetSource",
    ".pq": "parquet:ParquetSource",
    ".ply": "ply:PlySource",
    ".pcd": "pcd:PcdSource",
    ".e57": "e57:E57Source",
    ".xyz": "xyz:XyzSource",
})

WRITERS = _Registry({
    ".las": "las:LasSink",
    ".laz": "las:LasSink",
    ".copc.laz": "copc:CopcSink",
    ".parquet": "parquet:ParquetSink",
    ".pq": "parquet:ParquetSink",
    ".ply": "ply:PlySink",
    ".xyz": "xyzout:XyzSink",
})

__all__ = ["READERS", "WRITERS", "AtomicFile", "ColorChunk", "PointChunk", "Sink", "Source", "Unit", "WriteOptions",
           "check_sink", "extension", "open_sink", "open_source", "writer_of"]


def extension(path: str) -> str:
    """The lower-case extension that names the format: ``.copc.laz`` is one, COPC (read as any LAZ)."""
    base = os.path.basename(path.rstrip("/")).lower()
    if base.endswith(".copc.laz"):
        return ".copc.laz"
    return os.path.splitext(base)[1]


def open_source(path: str, ordinal: int, **options) -> Source:
    ext = extension(path)
    if ext not in READERS:
        known = ", ".join(sorted(READERS))
        raise UnsupportedFormat(f"unknown input extension {ext or '(none)'!r} (reads {known})", path)
    reader = READERS[ext]
    if not reader.reads_remote and is_remote(path):
        readable = ", ".join(sorted(e for e, r in READERS.items() if r.reads_remote))
        raise UnsupportedFormat(f"{ext} files are read from local paths only (from the store: "
                                f"{readable}); copy it here first", path)
    return reader(path, ordinal, **options)


def writer_of(path: str) -> type[Sink]:
    """The writer class of ``path``'s extension, or a one-line refusal listing the ones there are."""
    ext = extension(path)
    if ext not in WRITERS:
        known = ", ".join(sorted(WRITERS))
        raise UnsupportedFormat(f"unknown output extension {ext or '(none)'!r} (writes {known})", path)
    return WRITERS[ext]


def check_sink(path: str, sources: list[Source], options: WriteOptions = WriteOptions()) -> None:
    """Refuse, from the options and the headers alone, what :func:`open_sink` would refuse for ``path`` (the
    output's own name): called before pass one, so that no input is decoded for a run that cannot write."""
    writer_of(path).refuse(path, sources, options)


def open_sink(path: str, sources: list[Source], provenance: dict, options: WriteOptions = WriteOptions()) -> Sink:
    """The writer of ``path``'s format for ``sources``, with ``provenance`` in its metadata; what it refuses is
    :func:`check_sink`'s, named as the output is published."""
    check_sink(public_name(path), sources, options)
    return WRITERS[extension(path)].open(path, sources, provenance, options)
