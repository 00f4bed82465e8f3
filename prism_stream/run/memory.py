"""Freed memory back to the OS between the phases of a run.

Arrow's allocator (mimalloc) and glibc's keep memory a phase has freed for the next allocation: pass one's
decoded batches and its chunk-sized arrays stay resident through the cutoff scan, a few hundred MB that count
in the run's peak RSS as if they were live (measured in bench/RESULTS_SCALE.md). A Dask worker would read them
as a leak and pause.
"""

from __future__ import annotations

import pyarrow as pa


def _load_libc():
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.malloc_trim  # noqa: B018 - glibc only
        return libc
    except (OSError, AttributeError):
        return None


_LIBC = _load_libc()


def release_memory() -> None:
    """Hand the freed memory of Arrow's pool and of glibc's heaps back to the OS (a few ms)."""
    pa.default_memory_pool().release_unused()
    if _LIBC is not None:
        _LIBC.malloc_trim(0)
