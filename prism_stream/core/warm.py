"""Load numba's compiler state and the cached kernels on a background thread, once per process.

The first call of any kernel costs about 0.4 s: numba builds its typing and
target registries and imports what they need (scipy's BLAS among them).
Begun at the start of a run, that overlaps opening the inputs and decoding
the first chunk. A kernel called before it ends waits for it (numba's
compile lock), so a run is never slower than loading on first use.
"""

from __future__ import annotations

import threading

_started = False
_lock = threading.Lock()


def _load() -> None:
    try:
        import numpy as np

        from .kernels import splitmix64_array

        splitmix64_array(np.zeros(1, dtype=np.uint64))
    except Exception:  # noqa: BLE001 - a failure here shows again, with its message, on first real use
        pass


def warm_up() -> None:
    """Start loading the kernels (no-op after the first call)."""
    global _started
    with _lock:
        if _started:
            return
        _started = True
    threading.Thread(target=_load, name="prism-stream-kernels", daemon=True).start()
