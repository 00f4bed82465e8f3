"""The ranks of a run's sample (``--rank``): every kept point's rank, in input order, for pass two to write.

:mod:`..core.ranks` says what a rank is and computes it in memory; this module
runs it over the run's temporary files, with DuckDB once the sample is too
large for memory.
"""

from __future__ import annotations

from typing import Callable, Iterable, Iterator

import numpy as np
import pyarrow as pa

from ..core import kernels
from ..formats.arrow import from_numpy, to_numpy
from ..core import ranks as ranking
from ..run.progress import Progress
from ..run.staging import ArrayFile

# Up to this many points are ranked in memory with numpy; more go through DuckDB, which sorts within its
# memory limit and spills the rest to the temporary folder. bench/rankers.py measures both: numpy is faster
# below a few million points (no DuckDB start-up), DuckDB as fast from about 4M and faster above, with its
# memory bounded: so DuckDB from 4M points on.
IN_MEMORY = 1 << 22


class Ranks:
    """The kept points' ranks in input order (a temporary file, or an array), read as pass two writes them."""

    def __init__(self, column: str, order: str, values, method: str):
        self.column = column
        self.order = order
        self.values = values  # an ArrayFile, or anything with its read(at, n) and size
        self.method = method
        self.at = 0

    def next(self, n: int) -> np.ndarray:
        out = self.values.read(self.at, n)
        self.at += n
        return out

    def facts(self) -> dict:
        return {"column": self.column, "order": self.order, "points": self.values.size, "method": self.method}


class Held:
    """An array read as an :class:`ArrayFile` is."""

    def __init__(self, values: np.ndarray):
        self.values = values
        self.size = len(values)

    def read(self, at: int, n: int) -> np.ndarray:
        return self.values[at:at + n]


def held_ranks(plan, run, keys: np.ndarray, ids: np.ndarray) -> Ranks:
    """The ranks of a sample held in memory (its points' bin keys and ids, in input order), with numpy alone:
    the same two sorts :func:`rank_points` makes on its files."""
    with run.timed("rank"):
        order = ranking.BinOrder(plan)
        place = order.place[np.searchsorted(plan.keys, keys)]
        priority = kernels.priorities_of_np(np.ascontiguousarray(ids, dtype=np.uint64), order.seed_mix)
        values = ranking.rank_sample(place, priority, plan.bins)
    return Ranks(run.request.rank, run.request.order, Held(values), "numpy")


def rank_points(plan, run, kept) -> Ranks:
    """The rank of every point ``kept()`` yields (as (bin keys, ids), in input order).

    Up to :data:`IN_MEMORY` points are ranked with numpy; more with
    DuckDB, which spills its sort to the run's temporary folder. Either way the
    ranks land in a temporary file that pass two reads in step with the points it writes.
    """
    request = run.request
    with run.timed("rank"):
        order = ranking.BinOrder(plan)
        place = ArrayFile(run.tmp, "rank.place", np.uint32)
        priority = ArrayFile(run.tmp, "rank.priority", np.uint64)
        out = ArrayFile(run.tmp, "rank.values", np.int64)
        with Progress("ranks", plan.kept, request.progress) as bar:
            for keys, ids in kept():
                p, q = order.of(keys, ids)
                place.append(p)
                priority.append(q)
                bar.update(len(keys))
        n = place.size
        if n <= IN_MEMORY:
            method = "numpy"
            out.append(ranking.rank_sample(place.read(0, n), priority.read(0, n), plan.bins))
        else:
            method = "duckdb"
            step = 1 << 20

            def batches():
                for a in range(0, n, step):
                    yield place.read(a, min(step, n - a)), priority.read(a, min(step, n - a))

            for values in rank_sample_duckdb(batches, run.tmp, threads=request.workers):
                out.append(values)
        place.discard()
        priority.discard()
        if out.size != plan.kept:
            raise AssertionError(f"ranked {out.size} points, the plan keeps {plan.kept}")
    return Ranks(request.rank, request.order, out, method)


def rank_sample_duckdb(batches: Callable[[], Iterable[tuple[np.ndarray, np.ndarray]]], folder: str,
                       memory_limit: str = "256MB", threads: int = 1, rows: int = 1 << 20) -> Iterator[np.ndarray]:
    """:func:`rank_sample` with DuckDB's window functions, which spill to ``folder``: ranks, ``rows`` at a time.

    ``batches()`` yields (bin place, priority) arrays of the sample's points in
    their order; the ranks come back in that order.
    """
    import duckdb  # on first use: most runs rank nothing, or in memory

    schema = pa.schema([("seq", pa.int64()), ("b", pa.uint32()), ("p", pa.uint64())])

    def arrow():
        seq = 0
        for place, priority in batches():
            n = len(place)
            yield pa.record_batch([from_numpy(np.arange(seq, seq + n, dtype=np.int64)), from_numpy(place),
                                   from_numpy(priority)], schema=schema)
            seq += n

    points = pa.RecordBatchReader.from_batches(schema, arrow())
    con = duckdb.connect(config={"memory_limit": memory_limit, "temp_directory": folder, "threads": threads,
                                 "preserve_insertion_order": True})
    try:
        con.register("points", points)
        result = con.sql("""
            SELECT rank FROM (
                SELECT seq, row_number() OVER (ORDER BY j, b) - 1 AS rank FROM (
                    SELECT seq, b, row_number() OVER (PARTITION BY b ORDER BY p) AS j FROM points))
            ORDER BY seq""").fetch_arrow_reader(rows)
        for batch in result:
            yield to_numpy(batch.column(0)).astype(np.int64, copy=False)
    finally:
        con.close()
