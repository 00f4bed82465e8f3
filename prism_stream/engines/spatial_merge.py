"""PRISM's order and the merge of a spatial share (SPEC 9) with their T-sized arrays on disk.

A large target's spatial order already comes from the temporary folder (:mod:`.spatial_disk`). Here the
rest of :func:`.spatial.spaced` is done the same way, each step a sort in runs on disk
(:class:`..run.extsort.SortedRuns`) read back a block at a time:

- PRISM's order (:func:`prism_order_file`, :func:`.spatial.prism_order`'s order): the sample's points sorted
  by (bin priority, priority), which numbers each point's place in its bin (its layer), then sorted by
  (layer, bin priority). Ordering bins by their priority is ordering them by their place among the
  sample's bins; priorities are a bijection of keys and of ids, so no two points tie.
- The merge (:func:`merge_files`, :func:`..core.space.merge`'s): both orders' ids sorted together, so an id
  in both is a pair of neighbours; its place in each order, sorted once by each, tells each side where its
  ids stand in the other. The merge then walks the two orders place by place with those beside them: a side
  skips an id the other side has already passed (which it took), as the in-memory merge's marks do.
- The merged ids sorted by id, with each one's place: the run's sample in input order.

Memory: one sort's run (:data:`..run.extsort.RUN` records) and a block of each file, whatever T. Disk: each
sort's records once (at most 24 bytes and 2 T of them), the two orders' ids (8 bytes a place each), every
file removed once read; the sample's ids and places (16 bytes a target point) stay for pass two, which
reads them in step with the input (:class:`.spatial.IdSelector`, the ranks).
"""

from __future__ import annotations

import numpy as np

from ..core.kernels import bin_seed_mix, priorities_of_np, seed_mix
from ..run import staging
from ..run.extsort import SortedRuns

BY_BIN = np.dtype([("bin", "<u8"), ("prio", "<u8"), ("id", "<u8")])
BY_LAYER = np.dtype([("layer", "<u8"), ("bin", "<u8"), ("id", "<u8")])
BY_ID = np.dtype([("id", "<u8"), ("side", "<u8"), ("at", "<u8")])
PAIR = np.dtype([("at", "<u8"), ("other", "<u8")])
CHOSEN = np.dtype([("id", "<u8"), ("place", "<u8")])
READ = 1 << 20  # entries of a file read at a time
WALK = 1 << 18  # places of each order the merge's walk reads at a time, and places it hands out


class Sizes:
    """The sorts' run and block sizes (the tests make them small)."""

    def __init__(self, run: int | None = None, block: int | None = None):
        self.run, self.block = run, block

    def sort(self, folder: str, name: str, dtype, keys: tuple, open_file=None) -> SortedRuns:
        return SortedRuns(folder, name, dtype, keys, run=self.run, block=self.block, open_file=open_file)


def _ids_file(folder: str, name: str, open_file) -> staging.ArrayFile:
    return (open_file or staging.ArrayFile)(folder, name, np.uint64)


def prism_order_file(seed: int, kept, folder: str, sizes: Sizes, open_file=None) -> staging.ArrayFile:
    """PRISM's sample (``kept()``: (bin keys, ids) pairs) in rank order, as a file of ids in ``folder``."""
    by_bin = sizes.sort(folder, "space.prism.bins", BY_BIN, ("bin", "prio"), open_file)
    by_layer = sizes.sort(folder, "space.prism.layers", BY_LAYER, ("layer", "bin"), open_file)
    out = _ids_file(folder, "space.prism", open_file)
    try:
        bmix, pmix = bin_seed_mix(seed), seed_mix(seed)
        for keys, ids in kept():
            rec = np.empty(len(ids), BY_BIN)
            rec["id"] = ids
            rec["bin"] = priorities_of_np(np.asarray(keys).astype(np.uint64), bmix)
            rec["prio"] = priorities_of_np(rec["id"], pmix)
            by_bin.add(rec)
        last, run = None, 0  # the bin of the previous block's last point, and its points so far
        for block in by_bin.blocks():
            b = block["bin"]
            layer = _layers(b, last, run)
            rec = np.empty(len(b), BY_LAYER)
            rec["layer"], rec["bin"], rec["id"] = layer, b, block["id"]
            by_layer.add(rec)
            last, run = b[-1], int(layer[-1]) + 1
        for block in by_layer.blocks():
            out.append(block["id"])
        return out
    except BaseException:
        out.discard()
        raise
    finally:
        by_bin.discard()
        by_layer.discard()


def _layers(b: np.ndarray, last, run: int) -> np.ndarray:
    """Each point's place in its bin (``b``: the bins of a sorted block; ``last``: the previous block's last
    bin, None for the first block, whose points there numbered ``run``)."""
    n = len(b)
    new = np.empty(n, bool)
    new[0] = last is None or b[0] != last
    np.not_equal(b[1:], b[:-1], out=new[1:])
    at = np.arange(n, dtype=np.int64)
    layer = at - np.maximum.accumulate(np.where(new, at, 0))
    if not new[0]:  # the block's first bin goes on from the previous block
        starts = np.flatnonzero(new)
        layer[:starts[0] if len(starts) else n] += run
    return layer


def _positions(order: staging.ArrayFile, side: int, into: SortedRuns, limit: int) -> None:
    for a in range(0, min(order.size, limit), READ):
        ids = order.read(a, min(READ, min(order.size, limit) - a))
        rec = np.empty(len(ids), BY_ID)
        rec["id"], rec["side"], rec["at"] = ids, side, np.arange(a, a + len(ids), dtype=np.uint64)
        into.add(rec)


def _beside(pairs, order: staging.ArrayFile, limit: int):
    """``order``'s ids a block at a time, each with where it is in the other order (-1: not there), from
    ``pairs`` (blocks of (at, other), sorted by at)."""
    pending = np.zeros(0, PAIR)
    pairs = iter(pairs)
    done = False
    size = min(order.size, limit)
    for a in range(0, size, WALK):
        ids = order.read(a, min(WALK, size - a))
        b = a + len(ids)
        while not done and (len(pending) == 0 or int(pending["at"][-1]) < b):
            more = next(pairs, None)
            if more is None:
                done = True
            else:
                pending = np.concatenate([pending, more])
        cut = int(np.searchsorted(pending["at"], np.uint64(b)))
        here, pending = pending[:cut], pending[cut:]
        other = np.full(len(ids), -1, np.int64)
        other[(here["at"] - np.uint64(a)).astype(np.int64)] = here["other"].astype(np.int64)
        yield np.array(ids), other, a  # (a copy: the bytes read are read-only, the loop's types writable)


def merge_files(spatial: staging.ArrayFile, prism: staging.ArrayFile, a: int, t: int, folder: str,
                sizes: Sizes, open_file=None) -> tuple[staging.ArrayFile, staging.ArrayFile, int]:
    """:func:`..core.space.merge` of the spatial order's ids (its first ``t``) and PRISM's (``t`` of them),
    each a file in ``folder`` (both removed once read), then sorted by id: files of the chosen ids ascending
    and of each one's place in the merge (the caller's to remove), and how many places the spatial order
    filled."""
    both = sizes.sort(folder, "space.merge.ids", BY_ID, ("id", "side"), open_file)
    s_pairs = sizes.sort(folder, "space.merge.spatial", PAIR, ("at",), open_file)
    p_pairs = sizes.sort(folder, "space.merge.prism", PAIR, ("at",), open_file)
    chosen = sizes.sort(folder, "space.merge.chosen", CHOSEN, ("id",), open_file)
    try:
        _positions(spatial, 0, both, t)
        _positions(prism, 1, both, t)
        carry = None  # the previous block's last record
        for block in both.blocks():
            if carry is not None:
                block = np.concatenate([carry, block])
            same = np.flatnonzero(block["id"][1:] == block["id"][:-1])  # (spatial, PRISM) neighbours
            if len(same):
                s_at, p_at = block["at"][same], block["at"][same + 1]
                s_pairs.add(_pairs(s_at, p_at))
                p_pairs.add(_pairs(p_at, s_at))
            carry = block[-1:] if len(same) == 0 or same[-1] != len(block) - 2 else block[:0]
            if len(carry) == 0:
                carry = None
        filled = _walk(_beside(s_pairs.blocks(), spatial, t), _beside(p_pairs.blocks(), prism, t),
                       min(spatial.size, t), a, t, chosen)
        ids = _ids_file(folder, "space.chosen", open_file)
        places = None
        try:
            places = (open_file or staging.ArrayFile)(folder, "space.places", np.int64)
            for block in chosen.blocks():
                ids.append(block["id"])
                places.append(block["place"].astype(np.int64))
            if ids.size != t:
                raise AssertionError(f"the spatial share's merge chose {ids.size} points for a target of {t}")
        except BaseException:
            ids.discard()
            if places is not None:
                places.discard()
            raise
        return ids, places, filled
    finally:
        for s in (both, s_pairs, p_pairs, chosen):
            s.discard()
        spatial.discard()
        prism.discard()


def _pairs(at: np.ndarray, other: np.ndarray) -> np.ndarray:
    rec = np.empty(len(at), PAIR)
    rec["at"], rec["other"] = at, other
    return rec


def _walk(s_blocks, p_blocks, ns: int, a: int, t: int, chosen: SortedRuns) -> int:
    """The merge place by place (:func:`..core.jit.merge_walk`, a block of each order at a time): a side skips
    an id the other side has passed, since the other side took it. Returns the places the spatial order
    filled."""
    none_ids, none_other = np.zeros(0, np.uint64), np.zeros(0, np.int64)
    s_ids, s_other = p_ids, p_other = none_ids, none_other
    # place, the next position of each order, filled, ns, the blocks' first positions, the share, t
    state = np.array([0, 0, 0, 0, ns, 0, 0, a, t], np.int64)
    out = np.empty(WALK, np.uint64)
    try:
        return _walked(s_blocks, p_blocks, state, out, chosen, (s_ids, s_other, p_ids, p_other))
    finally:  # the orders' pairs' runs closed now, even on an error
        s_blocks.close()
        p_blocks.close()


def _walked(s_blocks, p_blocks, state: np.ndarray, out: np.ndarray, chosen: SortedRuns, first: tuple) -> int:
    from ..core import kernels

    s_ids, s_other, p_ids, p_other = first
    t = int(state[8])
    while True:
        place = int(state[0])
        n, need = kernels.merge_walk(s_ids, s_other, p_ids, p_other, state, out)
        if n:
            rec = np.empty(n, CHOSEN)
            rec["id"], rec["place"] = out[:n], np.arange(place, place + n, dtype=np.uint64)
            chosen.add(rec)
        if need == 1:
            s_ids, s_other, state[5] = _next(s_blocks)
        elif need == 2:
            p_ids, p_other, state[6] = _next(p_blocks)
        elif state[0] >= t:
            return int(state[3])


def _next(blocks):
    got = next(blocks, None)
    if got is None:  # (a StopIteration would end a caller's loop quietly)
        raise AssertionError("the spatial share's merge ran past the end of an order")
    return got
