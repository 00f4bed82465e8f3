"""Tables over the key space or a slot budget, touched only where bins are, without huge pages.

numpy advises the kernel to back every array of 4 MiB or more with 2 MiB
pages (``madvise(MADV_HUGEPAGE)``). The filter's tables are large and
sparse (8 bytes for each of 2^24 keys, heaps at a 192 MiB budget), made with
``np.zeros`` so that the OS maps a page only where a bin writes: with that
advice each first write takes a whole 2 MiB page, and on a machine whose
free memory is fragmented the kernel compacts memory to find one, in the
writing thread. On the 2-core test machine that cost a streamed run of the
bundled cloud 0.2-1.3 s in a fresh process, against 0.16-0.2 s without
(bench/PROFILE.md). :func:`sparse_zeros` makes these tables without the
advice; every other array keeps numpy's setting.
"""

from __future__ import annotations

import numpy as np

from .constants import OCCUPIED_SHIFT

try:
    from numpy._core.multiarray import _set_madvise_hugepage
except ImportError:  # numpy 1.x
    try:
        from numpy.core.multiarray import _set_madvise_hugepage
    except ImportError:  # no such switch: numpy's default
        _set_madvise_hugepage = None


def sparse_zeros(shape, dtype) -> np.ndarray:
    """``np.zeros(shape, dtype)`` on pages of the OS's smallest size, whatever numpy's huge-page setting (the
    setting is numpy's one switch: it is off only for this allocation, and put back)."""
    if _set_madvise_hugepage is None:
        return np.zeros(shape, dtype=dtype)
    previous = _set_madvise_hugepage(False)
    try:
        return np.zeros(shape, dtype=dtype)
    finally:
        _set_madvise_hugepage(previous)


def marked_runs(marks: np.ndarray, shift: int, size: int, block: int = 1 << 20) -> list[tuple[int, int]]:
    """The key ranges [a, b) of a table of ``size`` keys whose blocks of 2^``shift`` keys are marked
    (``marks[i]`` != 0 for block i), runs of neighbours joined, each at most ``block`` keys: a scan of a
    sparse table over them reads only the pages that may hold something."""
    on = np.flatnonzero(marks)
    if not len(on):
        return []
    cut = np.flatnonzero(np.diff(on) != 1) + 1
    starts, ends = on[np.r_[0, cut]], on[np.r_[cut - 1, len(on) - 1]] + 1
    per = max(1, block >> shift)
    out = []
    for s, e in zip(starts.tolist(), ends.tolist()):
        for a in range(s, e, per):
            lo, hi = a << shift, min(min(e, a + per) << shift, size)
            if lo < hi:
                out.append((lo, hi))
    return out


def marks_for(size: int) -> np.ndarray:
    """A byte for each block of 2^OCCUPIED_SHIFT keys of a table of ``size`` keys, all unmarked."""
    return np.zeros(max(1, -(-size >> OCCUPIED_SHIFT)), np.uint8)


def mark(marks: np.ndarray, keys) -> None:
    """Mark the blocks of ``keys`` (counts written by numpy rather than a kernel)."""
    marks[np.asarray(keys, dtype=np.int64) >> OCCUPIED_SHIFT] = 1


def table_runs(marks: np.ndarray, size: int, block: int = 1 << 20) -> list[tuple[int, int]]:
    """:func:`marked_runs` of a table's marks (blocks of 2^OCCUPIED_SHIFT keys)."""
    return marked_runs(marks, OCCUPIED_SHIFT, size, block)
