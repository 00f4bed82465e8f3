"""The constants the numba loops (:mod:`.jit`) and their numpy front door (:mod:`.kernels`) share."""

from __future__ import annotations

import numpy as np

ID_SHIFT = 40
MAX_RECORDS_PER_SOURCE = 1 << ID_SHIFT

# rule[key]: a capped bin's slot s as s + 1; these two for bins that need no priority comparison. "Drop" is 0, so a
# rule table is np.zeros, whose pages the OS maps only where bins are: np.full over 2^24 keys wrote 64 MiB of
# pages a table, up to 0.6 s of a run in a fresh process (bench/PROFILE.md)
RULE_DROP = 0
RULE_KEEP = -1
FLOOR_NONE = 255  # a bin's floor (candidates.CandidateFilter.tighten): it can give no more points

# The candidate filter's dense table packs a bin's count (low 40 bits) and its heap slot + 1 (the bits
# above; NO_HEAP: every point a candidate), so that a point costs one random access into the key space.
COUNT_BITS = 40
COUNT_MASK = (1 << COUNT_BITS) - 1
NO_HEAP = (1 << 23) - 1
# The filter's ``state`` array is [slots used, slots available, no more slots, then one mark a block of
# 2^OCCUPIED_SHIFT keys]: a key's block is marked when the key is first seen (``jit._slot``), so the scans of the
# table at the end (the histogram, the standing rules) read only the marked blocks. Reading the whole table read
# its 128 MiB of pages the OS had never mapped: 32,000 page faults, 50-100 ms of every streamed run and unit.
OCCUPIED_SHIFT = 12
STATE_MARKS = 3  # the first mark's place in ``state``

# A compaction's count of a quota's q-th smallest priority (cutoffs.SlotRadix, jit.radix_count): 2^RADIX_BITS
# buckets of a priority's top bits a slot in its first pass, of the next bits in its second
RADIX_BITS = 8

SMALL_ARRAY = 1 << 20  # arrays up to this length may take the numpy twins where numba is not loaded yet

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
