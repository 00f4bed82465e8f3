"""Temporary disk, predicted before it is used.

A run's temporary files are the one-read path's candidate spill (every point
that may still be selected: its 12-byte index entry and its record), or the
two-read path's key cache (4 bytes a point), beside the output while it is
written. Before pass one a :class:`TempForecast` puts numbers on them from
the headers alone:

- the spill: exact per-bin heaps keeping T of N points in random order hold
  sum_i min(1, T / i) ~ T (1 + ln(N / T)) candidates over the run; the
  candidate filter stays within twice that (docs/DESIGN.md, "Priority
  levels"; bench/RESULTS_SCALE.md). For a fixed ``--k`` the target is not
  known before pass one, so T is bounded by K times the bins there can be;
- a point's spilled bytes: the index entry and the format's record (a LAS
  record as the header sizes it; other formats their columns' widths).

The local engine reads once only when the bound, the output and a reserve
fit in the free space of the temporary folder; otherwise it reads twice
from the start, and refuses in one line when even the key cache cannot fit.
While pass one runs, the spill stops at the same budget (free space less the
output and the reserve): input spatially sorted can make it pass the random-
order bound, and the run then reads twice rather than fill the disk.
``--plan`` prints the forecast, with the per-bin expectation its histogram
allows.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from ..core import space
from ..errors import OutputError
from . import remote
from .staging import RESERVE, free_bytes, gib  # noqa: F401 - tempspace.RESERVE, and patched by the tests

INDEX_BYTES = 12  # a candidate's bin key (uint32) and id (uint64) in the spill's index
FRAME_BYTES = 1024  # a pickled frame's own bytes, one a chunk with candidates (LAS about 550, Parquet 1,100)
KEY_BYTES = 4  # a point's key in the two-read path's cache
VARIABLE_BYTES = 16  # a guess for a column of variable width (a string) per point
RANK_BYTES = 36  # a ranked point's temporaries: place, priority and rank (20 bytes), and DuckDB's sort of them


def exact_heap_spill(n, t):
    """The candidates exact heaps keep of ``n`` points in random order to hold the ``t`` of lowest priority:
    sum over i <= n of min(1, t / i) = t (1 + H_n - H_t) ~ t (1 + ln(n / t)); ``n`` where ``t >= n``.

    Works on scalars and on numpy arrays (one bin each)."""
    n = np.asarray(n, dtype=np.float64)
    t = np.minimum(np.asarray(t, dtype=np.float64), n)
    held = t > 0
    safe = np.where(held, t, 1.0)
    out = np.where(held, t * (1.0 + np.log(np.where(held, n, 1.0) / safe)), 0.0)
    return out if out.ndim else float(out)


def spill_bound(n: int, t: int) -> int:
    """The candidate filter's random-order bound, 2 T (1 + ln(N / T)), at most N."""
    if n <= 0 or t <= 0:
        return 0
    return int(min(n, math.ceil(2 * exact_heap_spill(n, t))))


def target_bound(options, n: int) -> int:
    """T for ``n`` points, or (a fixed ``--k``: T is known only after pass one) the most it can be, K for
    every bin there can be."""
    t = options.target(n)
    if t is not None:
        return min(int(t), n)
    return int(min(n, int(options.k) * min(n, options.spec.key_space)))


def record_bytes(source) -> float:
    """What one point of ``source`` takes in a spill frame: a LAS record as its header sizes it, else its
    columns' widths (of those it decodes, when it decodes some alone: ``spilled_schema``); a column of no
    fixed width by what the file's own metadata says it holds a row (``column_bytes``), else a guess."""
    header = getattr(source, "header", None)
    fmt = getattr(header, "point_format", None)
    if fmt is not None and hasattr(fmt, "size"):
        return float(fmt.size)
    try:
        schema = source.spilled_schema() if hasattr(source, "spilled_schema") else source.arrow_schema()
        measured = source.column_bytes() if hasattr(source, "column_bytes") else {}
    except (NotImplementedError, OSError, ValueError):
        return 64.0
    return max(sum(field_bytes(f.type, measured.get(f.name)) for f in schema), 1.0)


def field_bytes(kind, measured: float | None = None) -> float:
    """A value's bytes in Arrow memory: its bit width; a fixed-size list's values; else ``measured`` (the
    file's bytes a row) and an offset, or :data:`VARIABLE_BYTES`, whichever is larger."""
    try:
        return kind.bit_width / 8
    except ValueError:  # strings, lists: no fixed width
        pass
    if pa.types.is_fixed_size_list(kind):
        return kind.list_size * field_bytes(kind.value_type)
    return max(VARIABLE_BYTES, (measured or 0.0) + 4.0)


def _device(path: str | None) -> int | None:
    if path is None or remote.is_remote(path):
        return None
    probe = os.path.abspath(path)
    while probe and not os.path.exists(probe):
        parent = os.path.dirname(probe)
        if parent == probe:
            return None
        probe = parent
    try:
        return os.stat(probe).st_dev
    except OSError:
        return None


@dataclass(frozen=True)
class TempForecast:
    """The temporary disk a run will use, from the headers (see the module)."""

    folder: str  # where the temporaries go (the temporary folder)
    free: int  # its free bytes now
    points: int  # N
    target: int  # T (a fixed --k: its bound)
    spill_expected: int  # candidates exact heaps would keep (random order)
    spill_bound: int  # the filter's random-order bound
    point_bytes: float  # a spilled point's bytes, index and record
    chunks: int  # the input's chunks: at most one spill frame each
    key_cache_bytes: int  # the two-read path's cache
    output_bytes: int  # the output, where it goes to the same disk (else 0)
    rank_bytes: int = 0  # the ranks' temporaries (``rank``), beside the spill or the key cache
    space_bytes: int = 0  # a spatial share's points on disk (``--space`` with a large target), beside them

    def spill_bytes(self, points: int, frames: int | None = None) -> int:
        """The bytes of a spill of ``points`` in ``frames`` frames (default: as many as can be)."""
        frames = min(points, self.chunks) if frames is None else frames
        return int(points * self.point_bytes + frames * FRAME_BYTES)

    @property
    def spill_bytes_expected(self) -> int:
        return self.spill_bytes(self.spill_expected)

    @property
    def spill_bytes_bound(self) -> int:
        return self.spill_bytes(self.spill_bound)

    @property
    def budget(self) -> int:
        """The most the spill may take while pass one runs (free space less the output and the reserve)."""
        return self.free - self.output_bytes - self.rank_bytes - self.space_bytes - RESERVE

    @property
    def one_read_fits(self) -> bool:
        return self.spill_bytes_bound <= self.budget

    @property
    def two_reads_fit(self) -> bool:
        return self.key_cache_bytes <= self.budget

    def too_big_for_one_read(self) -> str:
        return (f"the candidate spill may reach {gib(self.spill_bytes_bound)} ({self.spill_bound:,} points), more "
                f"than the {gib(max(0, self.budget))} free in {self.folder} leaves")

    def refuse_two_reads(self) -> None:
        """Raise, naming the folder, when even the two-read path's key cache cannot fit."""
        if not self.two_reads_fit:
            space_share = f", the spatial share's points {gib(self.space_bytes)}" if self.space_bytes else ""
            raise OutputError(f"not enough temporary space: reading {self.points:,} points twice caches "
                              f"{gib(self.key_cache_bytes)} of bin keys (the output another "
                              f"{gib(self.output_bytes)}, ranks {gib(self.rank_bytes)}{space_share}), and "
                              f"{gib(self.free)} is free; give --temp-dir on a larger disk", self.folder)

    def as_dict(self) -> dict:
        return {"folder": self.folder, "free_bytes": self.free, "spill_points_expected": self.spill_expected,
                "spill_points_bound": self.spill_bound, "spill_bytes_expected": self.spill_bytes_expected,
                "spill_bytes_bound": self.spill_bytes_bound, "key_cache_bytes": self.key_cache_bytes,
                "output_bytes": self.output_bytes, "rank_bytes": self.rank_bytes,
                "space_bytes": self.space_bytes, "reserve_bytes": RESERVE}


def forecast(sources, options, folder: str, output: str | None = None, plan=None,
             chunk_size: int = 1 << 16, rank: bool = False) -> TempForecast:
    """The forecast for ``sources`` (every count known) sampled with ``options``, temporaries in ``folder``.

    The output (T points at the input's record size, which a compressed output stays under) counts only
    where ``output`` lies on ``folder``'s disk; ``rank``: the ranks' temporaries of T points count too. With ``plan`` (after pass one, for ``--plan``) the
    expectation is the per-bin sum of :func:`exact_heap_spill` and T is exact."""
    n = int(sum(s.count for s in sources))
    t = int(plan.kept) if plan is not None else target_bound(options, n)
    if plan is not None:
        expected = int(np.ceil(exact_heap_spill(plan.counts, plan.quotas).sum())) if len(plan.counts) else 0
    else:
        expected = int(math.ceil(exact_heap_spill(n, t))) if n else 0
    sizes = [record_bytes(s) for s in sources]
    per_point = INDEX_BYTES + (float(np.average(sizes, weights=[max(1, s.count) for s in sources]))
                               if sources else 0.0)
    same_disk = output is not None and _device(output) is not None and _device(output) == _device(folder)
    output_bytes = int(t * (per_point - INDEX_BYTES)) if same_disk else 0
    return TempForecast(folder=os.path.abspath(folder), free=free_bytes(folder), points=n, target=t,
                        spill_expected=min(n, expected), spill_bound=spill_bound(n, t),
                        point_bytes=per_point, chunks=sum(-(-s.count // max(1, chunk_size)) for s in sources),
                        key_cache_bytes=KEY_BYTES * n,
                        output_bytes=output_bytes, rank_bytes=RANK_BYTES * t if rank else 0,
                        space_bytes=_space_bytes(options, n))


def _space_bytes(options, n: int) -> int:
    """A spatial share's points on disk (a target whose scan's cells would not fit in memory), else 0."""
    t = options.target(n) if getattr(options, "space", None) is not None else None
    return space.disk_bytes(n, t) if t is not None and space.on_disk(t) else 0

