"""The filter's sparse tables are made without numpy's huge-page advice (prism_stream/core/sparse.py): a first
write then maps a 4 KiB page, not a 2 MiB one the kernel may compact memory to find (bench/PROFILE.md)."""

from __future__ import annotations

import numpy as np
import pytest

from prism_stream.core import sparse
from prism_stream.core.sparse import sparse_zeros


def _advised(array: np.ndarray) -> bool | None:
    """Whether the mapping that holds the middle of ``array`` is advised for huge pages (``hg`` in its VmFlags;
    None: no /proc/self/smaps)."""
    at = array.ctypes.data + array.nbytes // 2  # the middle: numpy advises from a page boundary on
    try:
        text = open("/proc/self/smaps").read()
    except OSError:
        return None
    inside = False
    for line in text.splitlines():
        head = line.split()[0]
        if "-" in head and all(c in "0123456789abcdef-" for c in head):
            lo, hi = (int(x, 16) for x in head.split("-"))
            inside = lo <= at < hi
        elif inside and line.startswith("VmFlags:"):
            return "hg" in line.split()[1:]
    return None


@pytest.mark.parametrize("setting", [True, False])
def test_numpys_setting_is_put_back(setting):
    if sparse._set_madvise_hugepage is None:
        assert sparse_zeros(3, np.int64).tolist() == [0, 0, 0]
        return
    before = sparse._set_madvise_hugepage(setting)
    try:
        table = sparse_zeros((1 << 20,), np.int64)
        assert table.dtype == np.int64 and table.shape == (1 << 20,) and not table.any()
        assert sparse._set_madvise_hugepage(setting) == setting
    finally:
        sparse._set_madvise_hugepage(before)


def test_the_table_is_not_advised_for_huge_pages_where_numpys_arrays_are():
    """Where numpy's large arrays are advised for huge pages (Linux with transparent huge pages: ``hg`` in
    the mapping's flags), the sparse table is not."""
    if sparse._set_madvise_hugepage is None:
        return
    before = sparse._set_madvise_hugepage(True)
    try:
        advised = np.zeros(64 << 20, dtype=np.uint8)
        table = sparse_zeros(64 << 20, np.uint8)
        for a in (advised, table):
            a[::1 << 21] = 1  # a byte in each 2 MiB
        numpys, ours = _advised(advised), _advised(table)
        if numpys:  # numpy's advice took (a kernel with transparent huge pages): ours must not have it
            assert ours is False, (numpys, ours)
    finally:
        sparse._set_madvise_hugepage(before)
