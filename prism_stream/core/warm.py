"""Load numba's compiler state and the cached kernels on a background thread, once per process.

The first call of any kernel costs about 0.4 s: numba builds its typing and
target registries and imports what they need (scipy's BLAS among them); each
later kernel's cached code still takes a few hundredths of a second to load.
Begun at the start of a run, that overlaps opening the inputs and decoding
the first chunk. A kernel called before it ends waits for it (numba's
compile lock), so a run is never slower than loading on first use.

Of those 0.4 s, 0.2 to 0.3 go to importing ``scipy.linalg``: numba checks
once per process whether a BLAS is there, for ``np.dot`` and the like, which
no kernel here uses. A process that runs no numba code of its own (the
command line) calls :func:`without_blas` first, and the check finds none.
"""

from __future__ import annotations

import sys
import threading

_started = False
_blas = True
_lock = threading.Lock()
_thread: threading.Thread | None = None


def _frozen(dtype) -> "np.ndarray":
    import numpy as np

    a = np.zeros(0, dtype=dtype)
    a.flags.writeable = False  # a spill index is a read-only memory map: the kernels' cached type says so
    return a


def _load() -> None:
    try:
        import numpy as np

        from . import kernels

        kernels.splitmix64_array(np.zeros(1, dtype=np.uint64))
        # the kernels of the end of a one-read run take arrays of fixed types (a spill index: read-only uint32
        # keys and uint64 ids), so their cached code loads here, beside the decoding, not after it
        u64, i64, i32 = (np.zeros(0, dtype=t) for t in (np.uint64, np.int64, np.int32))
        mix = np.uint64(0)
        kernels.priorities_of(u64, mix)
        keys, ids = _frozen(np.uint32), _frozen(np.uint64)
        kernels.push_bottom_range(keys, ids, mix, i32, np.int64(0), i64, i64, i64, u64)
        kernels.keep_mask_ids(keys, ids, mix, i32, u64)
    except Exception:  # noqa: BLE001 - a failure here shows again, with its message, on first real use
        pass
    finally:
        if "scipy.linalg" in sys.modules and sys.modules["scipy.linalg"] is None:
            del sys.modules["scipy.linalg"]  # importable again (``prism-stream eval`` and the like)


def without_blas() -> None:
    """Numba's first kernel in this process looks for no BLAS (see above): numba's own linear algebra
    (``np.dot`` in a kernel) is then unavailable to the whole process, so only a program that has none
    calls this, before :func:`warm_up`."""
    global _blas
    _blas = False


def warm_up() -> None:
    """Start loading the kernels (no-op after the first call)."""
    global _started, _thread
    with _lock:
        if _started:
            return
        _started = True
        if not _blas and "scipy.linalg" not in sys.modules:
            sys.modules["scipy.linalg"] = None  # an import of it fails at once, until _load ends
        _thread = threading.Thread(target=_load, name="prism-stream-kernels", daemon=True)
        _thread.start()


# The kernels every streaming run calls (the warm-up loads them): cached once any streaming run has ended.
ALWAYS = ("splitmix64_array", "priorities_of", "push_bottom_range", "keep_mask_ids")


def cached() -> bool:
    """Whether numba's cache holds machine code, for this build of the sources, of the kernels every
    streaming run calls.

    False on the first streaming run after an install or an upgrade: that run compiles them (several
    seconds) into the cache (``__pycache__`` beside the sources, or ``NUMBA_CACHE_DIR``). A kernel that only
    some runs call (a format's color type, the two-read path) compiles, more briefly, on its first use.
    Reads numba's cache indexes (a private API): if they cannot be read, says True, so nothing is announced.
    """
    try:
        from . import jit

        return all(getattr(jit, name)._cache._cache_file._load_index() for name in ALWAYS)
    except Exception:  # noqa: BLE001 - an announcement is never worth a failed run
        return True


def wait(timeout: float | None = None) -> None:
    """Until the loading begun by :func:`warm_up` ends (the tests)."""
    if _thread is not None:
        _thread.join(timeout)


def compile_kernels() -> float:
    """Fill numba's cache ahead of use: stream small generated clouds through the engine the ways runs do
    (8-bit, 16-bit and float colors; LAS and Parquet; one read and two; each rule; ranks), so that later
    processes load machine code instead of compiling it. Returns the seconds it took.

    ``python -m prism_stream.core.warm`` runs it (``make test`` does, after installing): a machine that
    runs many short processes at once (a test suite, a batch) then never compiles the same kernel in
    several of them.
    """
    import os
    import tempfile
    import time
    import warnings

    import laspy
    import numpy as np
    import pyarrow as pa
    import pyarrow.parquet as pq

    from ..engines.local import sample

    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    n = 5_000
    colors = rng.integers(0, 256, (n, 3))
    before = os.environ.get("PRISM_STREAM_MEMORY_POINTS")
    os.environ["PRISM_STREAM_MEMORY_POINTS"] = "0"  # the streaming path, which the kernels serve
    try:
        with tempfile.TemporaryDirectory(prefix="prism-stream-warm-") as tmp:
            inputs = []
            for name, scale in (("c8.las", 1), ("c16.las", 257)):
                header = laspy.LasHeader(point_format=3, version="1.2")
                pts = laspy.ScaleAwarePointRecord.zeros(n, header=header)
                pts.red, pts.green, pts.blue = (colors * scale).T.astype(np.uint16)
                path = os.path.join(tmp, name)
                with laspy.open(path, mode="w", header=header) as w:
                    w.write_points(pts)
                inputs.append(path)
            # uint8, int32 (read as int64: kernels.loop_channels) and float colors
            for name, values in (("u8.parquet", colors.astype(np.uint8)), ("i32.parquet", colors.astype(np.int32)),
                                 ("f.parquet", colors / 255.0)):
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
                from ..run import spill

                share, spill.COMPACT_SHARE = spill.COMPACT_SHARE, 0.0  # a spill compacted at every chunk, its
                try:  # bins full enough to be capped (512 of them), a file decided at once (uint8 Parquet)
                    sample(inputs[2], out, overwrite=True, ratio=0.05, chunk_size=1_000, quant_bits=5)
                finally:
                    spill.COMPACT_SHARE = share
            # a cluster unit's evidence and a prior's levels (engines/dask/tasks.py)
            from .candidates import CandidateFilter
            from .quotas import Options

            opts = Options(ratio=0.05)
            unit = CandidateFilter(opts.spec, opts, 100)
            unit.evidence()
            one = np.array([5], dtype=np.uint32)
            unit.count_elsewhere(one, np.array([10]), one, np.array([1 << 40], dtype=np.uint64),
                                 (one, np.array([3], dtype=np.uint8), np.array([10], dtype=np.int64)))
    finally:
        if before is None:
            os.environ.pop("PRISM_STREAM_MEMORY_POINTS", None)
        else:
            os.environ["PRISM_STREAM_MEMORY_POINTS"] = before
    return time.perf_counter() - t0


if __name__ == "__main__":
    sys.stderr.write("prism-stream: compiling kernels into numba's cache...\n")
    sys.stderr.write(f"prism-stream: kernels compiled and cached in {compile_kernels():.1f} s\n")
