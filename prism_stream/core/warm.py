"""Load numba's compiler state and the cached kernels on a background thread, once per process.

The first call of any kernel costs a large part of a second (bench/PROFILE.md):
numba builds its typing and target registries and imports what they need
(scipy's BLAS among them); each later kernel's cached code still takes a few
hundredths of a second to load.
Begun at the start of a run, that overlaps opening the inputs and decoding
the first chunk. A kernel called before it ends waits for it (numba's
compile lock), so a run is never slower than loading on first use.

Most of that goes to importing ``scipy.linalg``: numba checks
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
        kernels.push_bottom_range(keys, ids, mix, i32, np.int64(0), (i64, i64, i64, u64))
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
        from . import aot

        if all(name in aot.kernels() for name in ALWAYS):
            return True  # compiled ahead of time: nothing to load from numba's cache
        from . import jit

        return all(getattr(jit, name)._cache._cache_file._load_index() for name in ALWAYS)
    except Exception:  # noqa: BLE001 - an announcement is never worth a failed run
        return True


def wait(timeout: float | None = None) -> None:
    """Until the loading begun by :func:`warm_up` ends (the tests)."""
    if _thread is not None:
        _thread.join(timeout)
