"""The hot loops' front door: constants, the hash in pure Python and numpy, and the numba loops on demand.

The numba functions live in :mod:`.jit` and load on first attribute access
(``kernels.bin_keys``, ``from .kernels import candidate_scan``): importing
numba and loading its cached machine code costs most of a second, which a
run that never calls them (a small input held in memory, ``--version``,
``--help``) does not pay. The ``*_np`` functions compute the same values
with numpy alone, for those runs; ``tests/test_kernels_numpy.py`` holds
them equal to the numba loops.
"""

from __future__ import annotations

import numpy as np

from .constants import (_GOLDEN, _MIX1, _MIX2, COUNT_BITS, COUNT_MASK, FLOOR_NONE, ID_SHIFT,  # noqa: F401 - kernels.X
                        MAX_RECORDS_PER_SOURCE, NO_HEAP, OCCUPIED_SHIFT, RULE_DROP, RULE_KEEP, SMALL_ARRAY,
                        STATE_MARKS)


def seed_mix(seed: int) -> np.uint64:
    """splitmix64(seed) as the value ids are xored with (SPEC 3)."""
    return splitmix64_scalar(seed)


def bin_seed_mix(seed: int) -> np.uint64:
    return splitmix64_scalar((seed + 1) % (1 << 64))


def splitmix64_scalar(x: int) -> np.uint64:
    """Pure-Python splitmix64 on an int: the reference the kernels are tested against."""
    mask = (1 << 64) - 1
    z = (x + 0x9E3779B97F4A7C15) & mask
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & mask
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
    return np.uint64(z ^ (z >> 31))


# ---- numpy twins of the numba loops ---------------------------------------------------------------------

def splitmix64_np(x: np.ndarray) -> np.ndarray:
    """splitmix64 of every uint64 word (numpy wraps uint64 arithmetic modulo 2^64, as the loops do)."""
    with np.errstate(over="ignore"):
        z = np.asarray(x, dtype=np.uint64) + _GOLDEN
        z = (z ^ (z >> np.uint64(30))) * _MIX1
        z = (z ^ (z >> np.uint64(27))) * _MIX2
        return z ^ (z >> np.uint64(31))


def priorities_of_np(ids: np.ndarray, mix) -> np.ndarray:
    """:func:`.jit.priorities_of`: the priority of each id (SPEC 3)."""
    return splitmix64_np(np.asarray(ids, dtype=np.uint64) ^ np.uint64(mix))


def bin_keys_np(r, g, b, shift: int, chroma: bool, bits: int) -> np.ndarray:
    """:func:`.jit.bin_keys`: the bin key of each point from integer channels (SPEC 2)."""
    rv, gv, bv = (np.asarray(c).astype(np.int64) >> shift for c in (r, g, b))
    if chroma:
        s = rv + gv + bv
        d = 2 * np.maximum(s, 1)  # s = 0 only where all three are 0, whose keys are 0 either way
        rv, gv, bv = ((2 * 255 * c + s) // d for c in (rv, gv, bv))
    w = 8 - bits
    return ((rv >> bits) << (2 * w) | (gv >> bits) << w | (bv >> bits)).astype(np.uint32)


_INT64_MAX = np.iinfo(np.int64).max


def loop_channels(r, g, b) -> tuple:
    """The three channels as one of the few array types the numba loops are compiled for: uint8 when all
    three are, uint16 when all are uint8 or uint16, else int64; C-contiguous, as read-only views, but for
    three strided uint16 fields (a LAS record's red, green and blue), which the loops read where they lie.

    Any other type (a Parquet file's int32 colors, a strided uint8 field, an Arrow buffer's read-only flag)
    would compile each loop anew, seconds a loop, in every process that meets it first and in none ahead of
    time (``python -m prism_stream.engines.warm`` compiles these). The values are unchanged; a uint64 value
    past int64 becomes int64's largest, which no color depth holds either. A LAS read's fields were copied
    out before, three passes over its records a read (2% of a 100M-point LAZ run, bench/PROFILE.md); read
    in place, the loops' key pass reads each record's three channels together.
    """
    arrays = [np.asarray(c) for c in (r, g, b)]
    if all(_field(a) for a in arrays):  # three fields of one record: read where they lie (numba's layout "A")
        return tuple(_read_only_view(a) for a in arrays)
    kinds = {a.dtype for a in arrays}
    if kinds == {np.dtype(np.uint8)}:
        dtype = np.uint8
    elif kinds <= {np.dtype(np.uint8), np.dtype(np.uint16)}:
        dtype = np.uint16
    else:
        dtype = np.int64
    out = []
    for a in arrays:
        if a.dtype == np.uint64 and a.size and int(a.max()) > _INT64_MAX:
            a = np.minimum(a, np.uint64(_INT64_MAX))
        out.append(read_only(a, dtype))  # the loops read the channels: one type whether writable or not
    return tuple(out)


def _field(a) -> bool:
    """A strided uint16 field (a record's color): all three channels so, or none (a mix of layouts would be
    a type of its own, in no build)."""
    return a.dtype == np.uint16 and a.ndim == 1 and a.flags.aligned and not a.flags.c_contiguous


def _read_only_view(a) -> np.ndarray:
    v = a.view()
    v.flags.writeable = False
    return v


def read_only(a, dtype) -> np.ndarray:
    """``a`` as a C-contiguous read-only view of ``dtype`` (a copy only of another type or layout): the one
    array type the loops that only read keys or ids are compiled for (a spill index is a read-only memory
    map; computed ids are the same type once viewed so), whoever made the array."""
    a = np.ascontiguousarray(a, dtype=dtype)
    return _read_only_view(a) if a.flags.writeable else a


def channel_range_np(r, g, b) -> tuple[int, int]:
    """:func:`.jit.channel_range`: (smallest, largest) value over the three channels."""
    if not len(r):
        return 0, 0
    return (min(int(np.min(c)) for c in (r, g, b)), max(int(np.max(c)) for c in (r, g, b)))


def __getattr__(name: str):
    """The numba loops, imported on first use and then bound here like any module attribute (lazily for the
    start-up cost alone: :mod:`.jit` imports nothing of this module)."""
    if name.startswith("__"):
        raise AttributeError(name)
    from . import aot

    compiled = aot.kernels().get(name)  # the ahead-of-time build, where there is one (then numba only if needed)
    if compiled is not None:
        globals()[name] = compiled
        return compiled
    from . import jit

    try:
        value = getattr(jit, name)
    except AttributeError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    globals()[name] = value
    return value
