"""``sample --denoise sor:K,STD``: the authors' pipeline (outlier removal, then PRISM) as a run.

The outliers are found as ``eval --denoise`` finds them (Open3D's rule,
streamed and exact: :func:`prism_stream.evaluate.denoise.sor_keep_streamed`),
into a keep mask of one byte a point in the run's work folder. Each source
is then wrapped in a :class:`CleanedSource`: the same file with its removed
points left out and its records numbered again in input order, so that the
rest of the run (pass one, the solve, pass two, every writer) samples the
cleaned cloud exactly as it would sample a file holding only those points
(SPEC 8). Temporary disk: the tiles and distances the removal writes are
said before they are written, and refused in one line when they cannot fit.
"""

from __future__ import annotations

import tempfile
import time

import numpy as np

from ..core.denoise import Denoise
from ..errors import OutputError, UsageError
from ..formats.base import Unit, _masked
from ..run.memory import release_memory
from ..run.progress import Progress
from ..run.staging import OUT_OF_ROOM, RESERVE, free_bytes, gib

BLOCK = 1 << 16  # records per entry of a cleaned source's index of kept points
TILE_POINTS = 2_000_000  # points per tile of the removal (a tile, its KD-tree and queries: about 200 MB at K = 100)


class CleanedSource:
    """A source with only the records its ``keep`` mask (booleans, one per record) keeps, numbered again from 0
    in input order; every other attribute is the wrapped source's."""

    def __init__(self, inner, keep: np.ndarray):
        self.inner = inner
        self.keep = keep
        n = int(inner.count)
        if len(keep) != n:
            raise AssertionError(f"{len(keep)} keep flags for {n} records")
        counts = np.zeros(-(-n // BLOCK), dtype=np.int64)
        for j, a in enumerate(range(0, n, BLOCK)):  # a memory map: read a block at a time
            counts[j] = int(np.count_nonzero(keep[a:a + BLOCK]))
        self.before = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)  # kept records before each block
        self.count = int(self.before[-1])
        self.removed = n - self.count

    @property
    def __class__(self):  # isinstance(cleaned, LasSource): the writers' choices are the file's (a LAS output's header)
        return type(self.inner)

    def __getattr__(self, name):
        if name == "inner":  # not set yet (unpickling, copying)
            raise AttributeError(name)
        return getattr(self.inner, name)

    def original(self, s: int) -> int:
        """The wrapped source's record index of the cleaned record ``s`` (the wrapped count for ``s`` = count)."""
        if s >= self.count:
            return int(self.inner.count)
        j = int(np.searchsorted(self.before, s, side="right")) - 1
        a = j * BLOCK
        return a + int(np.flatnonzero(self.keep[a:a + BLOCK])[s - self.before[j]])

    def whole(self) -> Unit:
        return Unit(self, 0, self.count)

    def units(self, unit_size: int) -> list:
        edges = list(range(0, self.count, max(1, unit_size))) + [self.count]
        return [Unit(self, a, b) for a, b in zip(edges[:-1], edges[1:])] or [Unit(self, 0, 0)]

    def _chunks(self, read, chunk_size: int, start: int, stop: int | None):
        stop = self.count if stop is None else min(stop, self.count)
        if start >= stop:
            return
        at = start
        for chunk in read(chunk_size, self.original(start), self.original(stop)):
            mask = np.asarray(self.keep[chunk.start:chunk.start + len(chunk)], dtype=bool)
            kept = int(np.count_nonzero(mask))
            if not kept:
                continue
            out = chunk.take(mask) if hasattr(chunk, "take") else _taken(chunk, mask)
            out.start = at
            yield out
            at += kept

    def color_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None):
        return self._chunks(self.inner.color_chunks, chunk_size, start, stop)

    def point_chunks(self, chunk_size: int, start: int = 0, stop: int | None = None):
        return self._chunks(self.inner.point_chunks, chunk_size, start, stop)

    def describe(self) -> dict:
        return {**self.inner.describe(), "points_in_file": int(self.inner.count), "points_removed": self.removed}

    def close(self) -> None:
        """Nothing: the run that opened the file closes it (local.sample)."""


def _taken(chunk, mask: np.ndarray):
    import copy

    out = copy.copy(chunk)
    for name, value in vars(chunk).items():
        setattr(out, name, _masked(value, mask))
    return out


def flag(request) -> str:
    """How the user asked for the removal: ``--denoise sor:K,STD``, or the preset that gave it."""
    label = Denoise.parse(request.options.denoise).label
    return f"--preset {request.preset} (its --denoise {label})" if request.preset is not None else f"--denoise {label}"


def refuse(request, sources, per_file: bool = False) -> None:
    """What ``--denoise`` refuses from the options and the headers, before any point is read (``per_file``:
    each file is a cloud of its own)."""
    if request.options.denoise is None:
        return
    cleaner = Denoise.parse(request.options.denoise)
    if request.flag is not None:
        raise UsageError(f"{flag(request)} removes points and --flag writes every point: flag the points of a "
                         "cleaned copy, or sample without the removal")
    unknown = [s for s in sources if s.count is None]
    if unknown:
        raise UsageError(f"{flag(request)} needs every input's size before it reads (a query's result has none): "
                         "write the query's result to a file first", unknown[0].path)
    for cloud in ([[s] for s in sources] if per_file else [sources]):
        n = sum(int(s.count) for s in cloud)
        if 0 < n < cleaner.neighbours:
            what = f"the cloud's {n:,} points" if len(cloud) == 1 else f"the {n:,} points of its {len(cloud)} files"
            raise UsageError(f"{flag(request)}: K = {cleaner.neighbours:,} neighbours is more than {what}",
                             cloud[0].path if len(cloud) == 1 else None)


def load() -> None:
    """Import the removal (scipy's KD-tree, which imports scipy.linalg) now: a run calls it before the
    kernels' warm-up, which keeps scipy.linalg from loading while numba starts (``core/warm.py``)."""
    from ..evaluate import denoise  # noqa: F401


def clean(sources, request, tmp: str, files: list) -> tuple[list, dict]:
    """The sources with the outliers ``request``'s ``--denoise`` finds left out (:class:`CleanedSource`), and
    what the removal did (the summary's ``denoise``). The keep mask stays in ``tmp`` for the run."""
    from ..evaluate.denoise import sor_keep_streamed, temporary_bytes

    cleaner = Denoise.parse(request.options.denoise)
    n = sum(int(s.count) for s in sources)
    t0 = time.perf_counter()
    folder = tempfile.mkdtemp(prefix="sor-", dir=tmp)

    forecast: dict = {}

    def room(need: int) -> None:
        """Refuse before a byte is written when ``need`` (the tiles and distances), the keep mask and the
        reserve do not fit; the forecast goes in the summary."""
        free = free_bytes(folder)
        forecast.update(temp_bytes_forecast=int(need) + n, free_bytes=int(free))
        if need + n + RESERVE > free:
            raise OutputError(f"not enough temporary space: removing outliers from {n:,} points writes about "
                              f"{gib(need)} of tiles and distances, and {gib(free)} is free; give --temp-dir on "
                              "a larger disk", folder)

    room(temporary_bytes(n, (2, 2)))  # before any read: evenly spread points, tiles both ways
    cloud = _counted_cloud().over(sources, files, request.chunk_size, request.color_depth)
    cloud.bar = Progress(f"denoise {cleaner.label}: reading", 2 * n, request.progress)  # bounds, then tiles
    try:
        with cloud.bar:
            keep, facts = sor_keep_streamed(cloud, folder, cleaner.neighbours, cleaner.std_ratio, TILE_POINTS,
                                            room=room)
    except OSError as exc:
        if exc.errno in OUT_OF_ROOM:
            raise OutputError(f"the temporary disk filled while removing outliers ({exc.strerror})",
                              folder) from None
        raise
    release_memory()  # the last tile's tree and queries: pass one's tables take their place
    cleaned, offset = [], 0
    for s in sources:
        cleaned.append(CleanedSource(s, keep[offset:offset + int(s.count)]))
        offset += int(s.count)
    info = {"method": cleaner.label, "points_before": n, "removed": int(facts["removed"]),
            "tiles": int(facts["tiles"]), "redone_points": int(facts["redone_points"]),
            "mu": facts.get("mu"), "sigma": facts.get("sigma"), "seconds": round(time.perf_counter() - t0, 4),
            **forecast}
    return cleaned, info


def _counted_cloud():
    """The evaluation's :class:`~prism_stream.evaluate.cloud.Cloud` with its reads on a progress bar (scipy and
    the evaluation load only for a run that removes outliers)."""
    from ..evaluate.cloud import Cloud

    class Counted(Cloud):
        bar = None

        def chunks(self, chunk_size=None):
            for c in super().chunks(chunk_size):
                if self.bar is not None:
                    self.bar.update(len(c))
                yield c

    return Counted
