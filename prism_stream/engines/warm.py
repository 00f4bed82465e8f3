"""Compile every numba kernel into numba's cache ahead of use: ``python -m prism_stream.engines.warm``.

It streams small generated clouds through the local engine the ways runs
do, so it lives above the core it compiles (:mod:`..core.warm` loads the
cache at the start of a run).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
import warnings

import laspy
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..core import kernels
from ..core.candidates import CandidateFilter, Standing
from ..core.cutoffs import SlotRadix
from ..core.quotas import Options
from ..run import spill
from .local import sample


def compile_kernels() -> float:
    """Fill numba's cache ahead of use: stream small generated clouds through the engine the ways runs do
    (8-bit, 16-bit and float colors; LAS and Parquet; one read and two; each rule; ranks), so that later
    processes load machine code instead of compiling it. Returns the seconds it took.

    ``python -m prism_stream.engines.warm`` runs it (``make test`` does, after installing): a machine that
    runs many short processes at once (a test suite, a batch) then never compiles the same kernel in
    several of them.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    n = 5_000
    colors = rng.integers(0, 256, (n, 3))
    before = os.environ.get("PRISM_STREAM_MEMORY_POINTS")
    os.environ["PRISM_STREAM_MEMORY_POINTS"] = "0"  # the streaming path, which the kernels serve
    try:
        with tempfile.TemporaryDirectory(prefix="prism-stream-warm-") as tmp:
            inputs = []
            # LAS and LAZ: a LAZ file's color reads (a two-read run's pass one) give the records' strided
            # fields, where an uncompressed file's are copied out
            for name, scale in (("c8.las", 1), ("c16.las", 257), ("c16.laz", 257)):
                header = laspy.LasHeader(point_format=3, version="1.2")
                pts = laspy.ScaleAwarePointRecord.zeros(n, header=header)
                pts.red, pts.green, pts.blue = (colors * scale).T.astype(np.uint16)
                path = os.path.join(tmp, name)
                with laspy.open(path, mode="w", header=header) as w:
                    w.write_points(pts)
                inputs.append(path)
            # uint8, uint16 (contiguous, where a LAS record's are strided), int32 (read as int64:
            # kernels.loop_channels) and float colors
            for name, values in (("u8.parquet", colors.astype(np.uint8)), ("u16.parquet", colors.astype(np.uint16)),
                                 ("i32.parquet", colors.astype(np.int32)), ("f.parquet", colors / 255.0)):
                path = os.path.join(tmp, name)
                pq.write_table(pa.table({"x": rng.random(n), "red": values[:, 0], "green": values[:, 1],
                                         "blue": values[:, 2]}), path)
                inputs.append(path)
            out = os.path.join(tmp, "out.parquet")
            runs = [dict(ratio=0.05), dict(ratio=0.05, reads="two"), dict(ratio=0.05, mode="paper"), dict(k=2),
                    dict(ratio=0.05, rank="prism_rank"), dict(ratio=0.05, quant_step=2.5)]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # generated clouds: what a run warns of is not news here
                for path in inputs:
                    for options in runs:
                        sample(path, out, overwrite=True, **options)
                sample(inputs[0], out, overwrite=True, ratio=0.05, space="0.5")  # the spatial share's cells
                # 8-bit values in 16-bit fields, then a 16-bit one: the filter's bins made again (heap_refill)
                late = os.path.join(tmp, "late16.las")
                header = laspy.LasHeader(point_format=3, version="1.2")
                pts = laspy.ScaleAwarePointRecord.zeros(n, header=header)
                pts.red, pts.green, pts.blue = colors.T.astype(np.uint16)
                pts.red[-1] = 4000
                with laspy.open(late, mode="w", header=header) as w:
                    w.write_points(pts)
                sample(late, out, overwrite=True, ratio=0.05, chunk_size=1_000)
                share, spill.COMPACT_SHARE = spill.COMPACT_SHARE, 0.0  # a spill compacted at every chunk, its
                try:  # bins full enough to be capped (512 of them), a file decided at once (uint8 Parquet)
                    sample(os.path.join(tmp, "u8.parquet"), out, overwrite=True, ratio=0.05, chunk_size=1_000,
                           quant_bits=5)
                finally:
                    spill.COMPACT_SHARE = share
            # a cluster unit's prior's levels and, once it saw points, its evidence (engines/dask/tasks.py)
            opts = Options(ratio=0.05)
            unit = CandidateFilter(opts.spec, opts, n)
            one = np.array([5], dtype=np.uint32)
            unit.count_elsewhere(one, np.array([10]), one, np.array([1 << 40], dtype=np.uint64),
                                 (one, np.array([3], dtype=np.uint8), np.array([10], dtype=np.int64)))
            loops = kernels.loop_channels(*colors.T.astype(np.uint8))
            unit.chunk(*loops, 0, 0, False)
            unit.evidence()
            # what only a cluster's tasks call: keys without counts, a unit's priorities (cutoffs.unit_bottoms)
            fields = colors.astype(np.uint16)  # a row a point: each column strided, as a LAS record's fields
            for c in (loops, kernels.loop_channels(*np.ascontiguousarray(fields.T)), kernels.loop_channels(*fields.T)):
                kernels.bin_keys(*c, 0, False, 0)
            kernels.priorities(np.uint64(0), n, kernels.seed_mix(0))
            kernels.priorities_of(kernels.read_only(np.arange(n, dtype=np.uint64), np.uint64), kernels.seed_mix(0))
            # the merge of a spatial share past the scan's budget, a block at a time (engines/spatial_merge.py)
            kernels.merge_walk(np.zeros(1, np.uint64), np.full(1, -1, np.int64), np.zeros(1, np.uint64),
                               np.full(1, -1, np.int64), np.array([0, 0, 0, 0, 1, 0, 0, 500_000, 1], np.int64),
                               np.empty(4, np.uint64))
            # a compaction's counting of wide quotas (cutoffs.SlotRadix)
            rules = Standing(np.arange(1, 3, dtype=np.int32), np.ones(2, dtype=np.int32), kernels.seed_mix(0))
            keys, ids = np.array([0, 1, 1], dtype=np.uint32), np.arange(3, dtype=np.uint64)
            SlotRadix(rules, np.arange(2)).upper_cuts(np.array([1, 1]), lambda f: f.add_ids(keys, ids))
    finally:
        if before is None:
            os.environ.pop("PRISM_STREAM_MEMORY_POINTS", None)
        else:
            os.environ["PRISM_STREAM_MEMORY_POINTS"] = before
    return time.perf_counter() - t0


if __name__ == "__main__":
    if "--aot" in sys.argv[1:]:  # the warm-up, then its kernels compiled ahead of time (run/aot.py)
        from ..run import aot

        if "--if-stale" in sys.argv[1:] and aot.load():
            sys.exit(0)  # a build of these very sources is there
        sys.stderr.write("prism-stream: compiling kernels ahead of time (numba's cache, then a C extension)...\n")
        try:
            aot.build(compile_kernels)
        except Exception as exc:  # noqa: BLE001 - optional: numba's JIT serves every run without it
            sys.stderr.write(f"prism-stream: no ahead-of-time kernels ({type(exc).__name__}: {exc}); runs load "
                             "them from numba's cache instead\n")
    else:
        sys.stderr.write("prism-stream: compiling kernels into numba's cache...\n")
        sys.stderr.write(f"prism-stream: kernels compiled and cached in {compile_kernels():.1f} s\n")
