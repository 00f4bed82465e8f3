"""The input cloud as the evaluation reads it: coordinates and colors, streamed.

The baselines and the metrics read inputs exactly as the sampler does
(:func:`prism_stream.formats.open_source`, ``point_chunks``), with the same
point identity (SPEC 3: ``(ordinal << 40) | record index``). What they need
beyond the sampler is the coordinates of a chunk, which each format exposes
differently; :func:`coordinates` finds them.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import pyarrow as pa

from ..core.bins import BinSpec, decided_keys
from ..errors import CorruptInput, UnsupportedFormat, UsageError
from ..formats import open_source
from ..formats.columns import LISTS_FIRST, kept_coordinates, not_coordinates, wkb_typed
from ..run.inputs import expand_inputs
from ..run.request import cores
from ..core.kernels import ID_SHIFT
from ..core.histogram import Histogram, merge_units
from ..core.passes import scan
from ..formats.arrow import to_numpy

RGB8 = BinSpec("rgb", 0)  # the metric's color bins: the 8-bit RGB triples
DEFAULT_CHUNK = 1 << 20


def coordinates(chunk, path: str = "") -> np.ndarray:
    """The (n, 3) float64 coordinates of a point chunk, in the file's units.

    A format's chunk may offer them as ``xyz``; LAS chunks carry scaled
    ``points.x/y/z``; otherwise they come from the chunk's Arrow batch: x/y/z
    columns (any case), a fixed-size list of three (``xyz``, ``position``...),
    WKB points (GeoParquet) or a list of three numbers a row: the column
    :func:`..formats.columns.kept_coordinates` chooses by the schema.
    """
    xyz = getattr(chunk, "xyz", None)
    if xyz is not None:
        return np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    pts = getattr(chunk, "points", None)
    if pts is not None and all(hasattr(pts, c) for c in "xyz"):
        return np.column_stack([np.asarray(pts.x, np.float64), np.asarray(pts.y, np.float64),
                                np.asarray(pts.z, np.float64)])
    return arrow_coordinates(chunk.to_arrow(), path)


def arrow_coordinates(batch: pa.RecordBatch, path: str = "") -> np.ndarray:
    """(n, 3) float64 coordinates of a batch, from the columns :func:`..formats.columns.kept_coordinates`
    chooses by its schema (the writers of x, y, z read the same ones)."""
    names = batch.schema.names
    held = kept_coordinates(batch.schema)
    if len(held) == 3:
        return np.column_stack([to_numpy(batch.column(names.index(n))).astype(np.float64) for n in held])
    if held:
        i = names.index(held[0])
        kind = batch.schema.field(i).type
        if wkb_typed(kind):
            return wkb_points(batch.column(i), path, names[i])
        col = batch.column(i)
        if col.null_count or col.flatten().null_count:  # a null row (flattened, the rows after it would shift)
            # or a null inside one: no coordinates
            raise UnsupportedFormat(f"the coordinate column {names[i]!r} holds null rows or values; distances (eval, "
                                    "--denoise) and --space need numeric x/y/z", path)
        if not pa.types.is_fixed_size_list(kind):  # a list column (as DuckDB reads a fixed-size list): 3 each
            import pyarrow.compute as pc

            if len(col) and not pc.all(pc.equal(pc.list_value_length(col), 3)).as_py():
                raise UnsupportedFormat(f"the coordinate column {names[i]!r} holds lists that are not 3 numbers "
                                        f"each ({LISTS_FIRST}); distances (eval, --denoise) and --space need "
                                        "numeric x/y/z", path)
        return to_numpy(col.flatten()).astype(np.float64).reshape(-1, 3)
    why = not_coordinates(batch.schema)
    if why:
        raise UnsupportedFormat(f"the coordinate {why}; distances (eval, --denoise) and --space need numeric "
                                "x/y/z", path)
    raise UnsupportedFormat(f"no coordinates found (columns: {', '.join(names[:12])}); "
                            "distances (eval, --denoise) and --space need x/y/z", path)


def check_coordinates(sources) -> None:
    """Refuse, before a point is decoded, sources whose columns hold no coordinates (the one-line refusal
    :func:`arrow_coordinates` gives, naming the source)."""
    for src in sources:
        arrow_coordinates(pa.RecordBatch.from_pylist([], schema=src.arrow_schema()), src.path)


def wkb_points(col: pa.Array, path: str = "", name: str = "geometry") -> np.ndarray:
    """(n, 3) of WKB points (ISO or EWKB, 2D or with Z (z 0 for 2D), either byte order), as the writers read
    them (:func:`..formats.geo.wkb_xyz`)."""
    from ..formats.geo import wkb_xyz

    try:
        return np.column_stack(wkb_xyz(col, name, path))
    except CorruptInput as exc:
        raise UnsupportedFormat(f"{exc.message}; distances (eval, --denoise) and --space need points", path) from None


@dataclass
class Chunk:
    """One run of records of one source, with what the evaluation needs of it."""

    ordinal: int
    start: int  # record index in its source
    offset: int  # index of the first point in the whole cloud (sources in order)
    xyz: np.ndarray
    raw: object  # the format's point chunk, for a sink

    @property
    def first_id(self) -> int:
        return (self.ordinal << ID_SHIFT) | self.start

    def __len__(self) -> int:
        return self.xyz.shape[0]


class Cloud:
    """The inputs of one evaluation, opened as the sampler opens them.

    A context manager; ``chunks()`` streams every source in order, and the
    bounding box and the color histogram are computed once, on first use.
    """

    def __init__(self, inputs, *, rgb_columns=None, chunk_size: int = DEFAULT_CHUNK, threads: int | None = 1,
                 color_depth: str = "auto", label: str | None = None):
        self.files = expand_inputs(inputs)
        self.label = label
        self.rgb_columns = rgb_columns
        self.threads = threads or cores()
        self.chunk_size = int(chunk_size)
        self.color_depth = color_depth
        self.sources = []
        try:
            for i, f in enumerate(self.files):
                self.sources.append(open_source(f, i, threads=self.threads, rgb_columns=rgb_columns))
        except BaseException:
            self.close()
            raise
        self._hold(self.sources)

    def _hold(self, sources: list) -> None:
        """The open sources, each one's first point's place in the cloud, and nothing computed yet."""
        self.sources = list(sources)
        self.offsets = np.concatenate([[0], np.cumsum([s.count for s in self.sources])]).astype(np.int64)
        self._bounds = None
        self._histogram = None
        self.decisions: dict[int, str] = {}

    @classmethod
    def over(cls, sources: list, files: list, chunk_size: int = DEFAULT_CHUNK, color_depth: str = "auto") -> "Cloud":
        """A cloud over sources a caller has opened (and closes: :meth:`close` leaves them open), every count
        known (``sample --denoise``)."""
        cloud = cls.__new__(cls)
        cloud.files, cloud.label, cloud.rgb_columns, cloud.threads = list(files), None, None, 1
        cloud.chunk_size, cloud.color_depth, cloud._borrowed = int(chunk_size), color_depth, True
        cloud._hold(sources)
        return cloud

    @property
    def name(self) -> str:
        """A short dataset label: the file name, or the first one and a count."""
        if self.label:
            return self.label
        base = os.path.basename(self.files[0]) if self.files else "-"
        return base if len(self.files) == 1 else f"{base} (+{len(self.files) - 1})"

    @property
    def points(self) -> int:
        return int(self.offsets[-1])

    def chunks(self, chunk_size: int | None = None) -> Iterator[Chunk]:
        """Every point chunk of every source, in input order, with its coordinates."""
        size = chunk_size or self.chunk_size
        for src in self.sources:
            seen = 0
            for raw in src.point_chunks(size):
                if raw.start != seen:
                    raise CorruptInput(f"reader skipped from record {seen} to {raw.start}", src.path)
                xyz = coordinates(raw, src.path)
                if not np.all(np.isfinite(xyz)):
                    raise CorruptInput("non-finite coordinates; distances (eval, --denoise) need every point placed",
                                       src.path)
                yield Chunk(src.ordinal, raw.start, int(self.offsets[src.ordinal]) + raw.start, xyz, raw)
                seen += len(xyz)
            if seen != src.count:
                raise CorruptInput(f"header declares {src.count} points but {seen} could be read", src.path)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners of the bounding box, from one streamed pass."""
        if self._bounds is None:
            lo = np.full(3, np.inf)
            hi = np.full(3, -np.inf)
            for c in self.chunks():
                if len(c):
                    lo = np.minimum(lo, c.xyz.min(axis=0))
                    hi = np.maximum(hi, c.xyz.max(axis=0))
            if not np.all(np.isfinite(lo)):
                raise UsageError("the input has no points to evaluate", self.files[0] if self.files else None)
            self._bounds = (lo, hi)
        return self._bounds

    def histogram(self) -> Histogram:
        """The input's 8-bit RGB histogram, with the sampler's color-depth decisions (SPEC 1)."""
        if self._histogram is None:
            units = []
            for src in self.sources:
                for unit in src.units(max(1, src.count)):
                    units.append(scan(unit, RGB8, self.color_depth, self.chunk_size))
            self._histogram, self.decisions = merge_units(units, self.color_depth)
        return self._histogram

    def keys_of(self, ordinal: int, rgb) -> np.ndarray:
        """8-bit RGB bin keys of some points of source ``ordinal`` (its depth decision applied)."""
        self.histogram()
        return decided_keys(RGB8, rgb, self.decisions.get(ordinal, "8"), self.sources[ordinal].path)

    def close(self) -> None:
        if getattr(self, "_borrowed", False):
            return
        for s in self.sources:
            s.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
