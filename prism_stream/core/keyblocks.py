"""Per-bin arrays merged a range of keys at a time.

Histograms, bounds and evidence of many units are merged per bin: what a bin's merged entry is depends
on that bin's entries alone. Merged whole, the parts are concatenated, sorted (an int64 index as long as
all of them) and gathered: over 2^24 bins, four parts of 8.6M bins each took 3.3 GiB above the parts to
merge a Dask prior. Cut into ranges of keys holding about ``BLOCK`` entries of each part, the same merge
runs range by range, the temporaries one range's, and the results (sorted by key within each range, the
ranges in key order) are joined: the same arrays to the bit.
"""

from __future__ import annotations

from typing import Callable, Iterator, Sequence

import numpy as np

BLOCK = 1 << 20  # entries of each part a range holds at most (besides one key's duplicates)


def in_key_order(keys: np.ndarray, *columns: np.ndarray) -> tuple:
    """``keys`` and ``columns`` ordered by key (stable: the entries of one key keep their order); the same
    arrays when they already are."""
    if len(keys) < 2 or not (keys[1:] < keys[:-1]).any():
        return (keys, *columns)
    order = np.argsort(keys, kind="stable")
    return (keys[order], *(c[order] for c in columns))


def spans(keys: Sequence[np.ndarray], block: int | None = None) -> Iterator[list[tuple[int, int]]]:
    """Ranges of the key space, in key order, as each part's ``[start, stop)`` in it: every key of every part
    in exactly one range, and no part holding more than ``block`` entries in one range besides the duplicates
    of one key. Each part's keys are sorted (not necessarily distinct).

    The cuts are every part's every ``block``-th key: between two cuts, a part has no cut of its own, so at
    most ``block`` entries (and the copies of its last key there). ``block``: :data:`BLOCK` unless given."""
    block = BLOCK if block is None else block
    if any((k[1:] < k[:-1]).any() for k in keys):
        raise ValueError("keyblocks.spans: a part's keys are not in order")  # ranges of them would be wrong
    cuts = [k[block::block] for k in keys if len(k) > block]
    if not cuts:
        yield [(0, len(k)) for k in keys]
        return
    cuts = np.unique(np.concatenate(cuts))
    bounds = [np.concatenate([[0], np.searchsorted(k, cuts, side="left"), [len(k)]]) for k in keys]
    for i in range(len(cuts) + 1):
        yield [(int(b[i]), int(b[i + 1])) for b in bounds]


def merged(merge: Callable[[list[tuple]], tuple], parts: Sequence[tuple], block: int | None = None) -> tuple:
    """``merge(parts)`` computed a range of keys at a time and joined: each part a tuple of equally long
    arrays whose first is its keys, sorted; ``merge`` takes such parts and returns a tuple of arrays
    ordered by key, each entry depending only on the entries of its own key. Ranges no part has an entry
    in are skipped; parts with no entry in a range are left out of it. A merge of few entries runs whole.
    ``block``: :data:`BLOCK` unless given."""
    block = BLOCK if block is None else block
    parts = [p for p in parts if len(p[0])]
    if sum(len(p[0]) for p in parts) <= 2 * block:
        return merge(parts)
    pieces = []
    for span in spans([p[0] for p in parts], block):
        some = [tuple(a[lo:hi] for a in p) for p, (lo, hi) in zip(parts, span) if hi > lo]
        if some:
            pieces.append(merge(some))
    return tuple(np.concatenate(columns) for columns in zip(*pieces))
