"""An independent, in-memory PRISM written from SPEC.md sections 1 to 5 alone.

The engine streams, caches keys, keeps bounded heaps and computes cutoffs;
this module does none of that. It holds every point in memory, solves the
quotas by brute force over k, and selects by sorting each bin by
(priority, id). It must not import the engine's kernels, scan, plan,
cutoff or select modules: agreeing with them is what the tests check.

Every function works on plain numpy arrays; ``sample`` takes the colors of
each source and returns, per source, the record indices kept (ascending,
which is input order).
"""

from __future__ import annotations

import math

import numpy as np

U64 = np.uint64
ID_SHIFT = 40


class OracleUsageError(ValueError):
    """Options the SPEC calls a usage error (T > N, ratio outside (0, 1], k < 1...)."""


class OracleInputError(ValueError):
    """Input the SPEC calls an input error (float colors outside [0, 1], NaN)."""


# -- SPEC 3: splitmix64 and priorities (numpy uint64 wraps mod 2^64) --------

def splitmix64(x) -> np.ndarray:
    """splitmix64 of every uint64 in ``x`` (an array, or a scalar as a 0-d array)."""
    z = np.array(x, dtype=np.uint64, copy=True)
    with np.errstate(over="ignore"):
        z = z + U64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> U64(30))) * U64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> U64(27))) * U64(0x94D049BB133111EB)
    return z ^ (z >> U64(31))


def splitmix64_int(x: int) -> int:
    """The same in plain Python integers: a second, numpy-free reference."""
    mask = (1 << 64) - 1
    z = (x + 0x9E3779B97F4A7C15) & mask
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & mask
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
    return z ^ (z >> 31)


def point_ids(ordinal: int, n: int) -> np.ndarray:
    """id = (source ordinal << 40) | record index, for records 0..n-1 of one source."""
    return (U64(ordinal) << U64(ID_SHIFT)) | np.arange(n, dtype=np.uint64)


def priority(ids, seed: int) -> np.ndarray:
    """priority(id, seed) = splitmix64(id ^ splitmix64(seed))."""
    mix = U64(splitmix64_int(seed % (1 << 64)))
    return splitmix64(np.asarray(ids, dtype=np.uint64) ^ mix)


def bin_priority(keys, seed: int) -> np.ndarray:
    """bin_priority(key, seed) = splitmix64(key ^ splitmix64(seed + 1))."""
    mix = U64(splitmix64_int((seed + 1) % (1 << 64)))
    return splitmix64(np.asarray(keys, dtype=np.uint64) ^ mix)


# -- SPEC 1: color depth, decided per file ----------------------------------

def color_depth(channels, option: str = "auto") -> str:
    """The file's decision: "8", "16" or "float" (all values <= 255 means 8-bit)."""
    r, g, b = (np.asarray(c) for c in channels)
    if any(c.dtype.kind == "f" for c in (r, g, b)):
        return "float"
    top = max((int(c.max()) for c in (r, g, b) if c.size), default=0)
    if option == "8":
        if top > 255:
            raise OracleUsageError(f"color depth 8 forced but values reach {top}")
        return "8"
    if option == "16":
        return "16"
    return "8" if top <= 255 else "16"


def to_8bit(channels, option: str = "auto"):
    """The three channels as 8-bit integers (int64), and the depth decision."""
    decision = color_depth(channels, option)
    out = []
    for c in channels:
        c = np.asarray(c)
        if decision == "float":
            c = c.astype(np.float64)
            if not np.all((c >= 0.0) & (c <= 1.0)):  # NaN fails both comparisons
                raise OracleInputError("float color outside [0, 1]")
            v = np.clip(np.floor(255.0 * c), 0, 255).astype(np.int64)
        elif decision == "16":
            v = c.astype(np.int64) >> 8
        else:
            v = c.astype(np.int64)
        out.append(v)
    return tuple(out), decision


# -- SPEC 2: bin keys -------------------------------------------------------

def chroma(r, g, b):
    """Each channel (2*255*v + s) // (2*s) with s = r+g+b; s = 0 gives (0, 0, 0)."""
    r, g, b = (np.asarray(c, dtype=np.int64) for c in (r, g, b))
    s = r + g + b
    safe = np.where(s == 0, 1, s)
    out = [np.where(s == 0, 0, (2 * 255 * c + safe) // (2 * safe)) for c in (r, g, b)]
    return tuple(out)


def bin_keys(r, g, b, color_space: str = "rgb", bits: int = 0) -> np.ndarray:
    """key = (r << 2w) | (g << w) | b on the (chroma-normalized) channels >> bits, w = 8 - bits."""
    r, g, b = (np.asarray(c, dtype=np.int64) for c in (r, g, b))
    if color_space == "chroma":
        r, g, b = chroma(r, g, b)
    elif color_space != "rgb":
        raise OracleUsageError(color_space)
    w = 8 - bits
    r, g, b = r >> bits, g >> bits, b >> bits
    return (r << (2 * w)) | (g << w) | b


# -- SPEC 4: quotas, by brute force over k ----------------------------------

def target(n: int, ratio: float | None = None, count: int | None = None) -> int:
    """T = floor(r * N + 0.5) for a ratio, or the count itself."""
    if ratio is not None:
        if not (0.0 < ratio <= 1.0):
            raise OracleUsageError(f"ratio {ratio} outside (0, 1]")
        return int(math.floor(ratio * n + 0.5))
    if count > n:
        raise OracleUsageError(f"count {count} > N = {n}")
    return int(count)


def capped_sum(counts, k: int) -> int:
    """S(k) = sum over bins of min(n_b, k)."""
    return int(np.minimum(np.asarray(counts, dtype=np.int64), k).sum())


def quotas(counts, keys, *, rule: str, t: int | None = None, k: int | None = None, seed: int = 0):
    """q_b for every bin, and the k the rule chose (k*, K or the fixed k).

    ``rule`` is "k", "paper" or "exact". Returns (quotas, k, extra).
    """
    counts = np.asarray(counts, dtype=np.int64)
    keys = np.asarray(keys, dtype=np.int64)
    top = int(counts.max()) if counts.size else 0
    if rule == "k":
        if k < 1:
            raise OracleUsageError("k < 1")
        return np.minimum(counts, k), k, 0
    if rule == "paper":
        # S(k) is constant from max n_b on, and ties go to the smaller k, so k <= max(1, top)
        best = None
        for cand in range(1, max(1, top) + 1):
            d = abs(capped_sum(counts, cand) - t)
            if best is None or d < best[0]:
                best = (d, cand)
        kstar = best[1]
        return np.minimum(counts, kstar), kstar, 0
    if rule == "exact":
        big_k = 0
        while big_k < top and capped_sum(counts, big_k + 1) <= t:
            big_k += 1
        q = np.minimum(counts, big_k)
        extra = t - int(q.sum())
        eligible = np.flatnonzero(counts > big_k)
        if extra > len(eligible):
            raise OracleUsageError("T > N")
        # bin priorities of distinct keys are distinct (splitmix64 is a bijection); key breaks ties anyway
        bp = bin_priority(keys[eligible], seed)
        order = np.lexsort((keys[eligible], bp))
        q[eligible[order[:extra]]] += 1
        return q, big_k, extra
    raise OracleUsageError(rule)


# -- SPEC 5: selection -------------------------------------------------------

def select(keys, ids, quota_of_key: dict, seed: int) -> np.ndarray:
    """Positions (into keys/ids) kept: in each bin the q_b smallest (priority, id)."""
    keys = np.asarray(keys, dtype=np.int64)
    ids = np.asarray(ids, dtype=np.uint64)
    pr = priority(ids, seed)
    order = np.lexsort((ids, pr, keys))  # by bin, then priority, then id
    sk = keys[order]
    starts = np.flatnonzero(np.r_[True, sk[1:] != sk[:-1]])
    rank = np.arange(len(sk)) - np.repeat(starts, np.diff(np.r_[starts, len(sk)]))
    q = np.array([quota_of_key[int(x)] for x in sk[starts]], dtype=np.int64)
    limit = np.repeat(q, np.diff(np.r_[starts, len(sk)]))
    keep = np.zeros(len(keys), dtype=bool)
    keep[order[rank < limit]] = True
    return np.flatnonzero(keep)


# -- the whole method ---------------------------------------------------------

class Result:
    """What the oracle decided: kept indices per source and the solve's numbers."""

    def __init__(self, kept, points, bins, target, k, extra, depths, counts, quotas, keys):
        self.kept = kept  # list of ascending record-index arrays, one per source
        self.points = points
        self.bins = bins
        self.target = target
        self.k = k
        self.extra = extra
        self.depths = depths
        self.counts = counts
        self.quotas = quotas
        self.keys = keys

    @property
    def kept_total(self) -> int:
        return int(sum(len(k) for k in self.kept))

    def per_bin(self) -> dict:
        return {int(k): int(q) for k, q in zip(self.keys, self.quotas) if q}


def sample(sources, *, ratio=None, count=None, k=None, mode="exact", color_space="rgb", bits=0,
           color_depth="auto", seed=0) -> Result:
    """PRISM over ``sources`` (a list of (r, g, b) channel triples, in source-ordinal order)."""
    given = [v for v in (ratio, count, k) if v is not None]
    if len(given) != 1:
        raise OracleUsageError("exactly one of ratio, count, k")
    all_keys, all_ids, depths, sizes = [], [], [], []
    for ordinal, channels in enumerate(sources):
        (r, g, b), decision = to_8bit(channels, color_depth)
        all_keys.append(bin_keys(r, g, b, color_space, bits))
        all_ids.append(point_ids(ordinal, len(r)))
        depths.append(decision)
        sizes.append(len(r))
    keys = np.concatenate(all_keys) if all_keys else np.zeros(0, np.int64)
    ids = np.concatenate(all_ids) if all_ids else np.zeros(0, np.uint64)
    n = len(keys)
    bin_key, bin_count = np.unique(keys, return_counts=True)
    if k is not None:
        rule, t = "k", None
    else:
        rule, t = mode, target(n, ratio, count)
    q, kk, extra = quotas(bin_count, bin_key, rule=rule, t=t, k=k, seed=seed)
    keep = select(keys, ids, dict(zip(bin_key.tolist(), q.tolist())), seed)
    bounds = np.cumsum([0] + sizes)
    kept = [keep[(keep >= a) & (keep < b)] - a for a, b in zip(bounds[:-1], bounds[1:])]
    return Result(kept, n, len(bin_key), t, kk, extra, depths, bin_count, q, bin_key)


def ranks(sources, *, color_space="rgb", bits=0, color_depth="auto", seed=0) -> list:
    """Every point's PRISM rank (exact mode), one int64 array per source, from the issue's formula.

    With j the point's position by (priority, id) within its bin (1-based) and B_j
    the bins holding at least j points ordered by bin priority:
    rank = S(j - 1) + (position of its bin in B_j). Written from the definition,
    one layer at a time, sharing nothing with the engine's sort.
    """
    all_keys, all_ids, sizes = [], [], []
    for ordinal, channels in enumerate(sources):
        (r, g, b), _ = to_8bit(channels, color_depth)
        all_keys.append(bin_keys(r, g, b, color_space, bits))
        all_ids.append(point_ids(ordinal, len(r)))
        sizes.append(len(r))
    keys = np.concatenate(all_keys)
    ids = np.concatenate(all_ids)
    pr = priority(ids, seed)
    order = np.lexsort((ids, pr, keys))
    sk = keys[order]
    starts = np.flatnonzero(np.r_[True, sk[1:] != sk[:-1]])
    j = np.empty(len(keys), dtype=np.int64)
    j[order] = np.arange(len(sk)) - np.repeat(starts, np.diff(np.r_[starts, len(sk)])) + 1
    bin_key, bin_count = np.unique(keys, return_counts=True)
    bp = bin_priority(bin_key, seed)
    count_of = dict(zip(bin_key.tolist(), bin_count.tolist()))
    out = np.empty(len(keys), dtype=np.int64)
    by_layer = np.argsort(j, kind="stable")  # the points of layer 1, then of layer 2, ...
    layer_start = np.searchsorted(j[by_layer], np.arange(1, int(j.max()) + 2 if len(j) else 2))
    held = -1
    for layer in range(1, int(bin_count.max()) + 1 if len(bin_count) else 1):
        if np.count_nonzero(bin_count >= layer) != held:  # B_j shrinks as j grows: the same size, the same set
            holding = bin_key[bin_count >= layer]
            held = len(holding)
            ordered = holding[np.lexsort((holding, bp[bin_count >= layer]))]
            position = {int(k): i for i, k in enumerate(ordered)}
        base = capped_sum(bin_count, layer - 1)
        here = by_layer[layer_start[layer - 1]:layer_start[layer]]  # the points with j == layer
        out[here] = [base + position[int(k)] for k in keys[here]]
    assert all(count_of[int(k)] >= jj for k, jj in zip(keys[:5], j[:5]))
    bounds = np.cumsum([0] + sizes)
    return [out[a:b] for a, b in zip(bounds[:-1], bounds[1:])]



# -- SPEC 9: a spatial share -------------------------------------------------

def space_share(text: str) -> int:
    """A as millionths, from its decimal text (SPEC 9: at most six digits after the point, in [0, 1])."""
    raw = str(text).strip()
    whole, _, frac = raw.partition(".")
    ascii_digits = all(part == "" or (part.isascii() and part.isdigit()) for part in (whole, frac))
    if raw in ("", ".") or not ascii_digits or len(frac) > 6:
        raise OracleUsageError(f"--space {text!r}")
    a = int(whole or 0) * 10**6 + int((frac + "000000")[:6] or 0)
    if a > 10**6:
        raise OracleUsageError(f"--space {text!r}")
    return a


def level_exponents(level: int) -> tuple[int, int, int]:
    """SPEC 9: the cell sides at ``level`` are 2^ex, 2^ey, 2^ez with ex = floor(l / 3), ey = floor((l + 1) / 3),
    ez = floor((l + 2) / 3): one level finer halves x, then y, then z."""
    return level // 3, (level + 1) // 3, (level + 2) // 3


def level_cells(xyz: np.ndarray, level: int) -> np.ndarray:
    return np.column_stack([np.floor(xyz[:, axis] * 2.0 ** -e) for axis, e in
                            enumerate(level_exponents(level))]).astype(np.int64)


def _top_level(xyz: np.ndarray) -> int:
    """The finest level whose every cell index is -1 or 0, searched level by level from above the largest
    magnitude (SPEC 9)."""
    big = float(np.max(np.abs(xyz))) if xyz.size else 0.0
    if big == 0.0:
        return 0
    level = 3 * (math.frexp(big)[1] + 1)  # every side 2^e > every |coordinate|: every index -1 or 0
    while True:
        cells = level_cells(xyz, level - 1)
        if cells.min() < -1 or cells.max() > 0:
            return level
        level -= 1


def _cell_priority(seed: int, level: int, cells: np.ndarray) -> np.ndarray:
    h = splitmix64(np.full(len(cells), splitmix64_int((seed + 2) % (1 << 64)), np.uint64) ^ U64(level % (1 << 64)))
    for axis in range(3):
        h = splitmix64(h ^ cells[:, axis].astype(np.int64).view(np.uint64))
    return h


def _unique_rows(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(cells, axis=0, return_inverse=True)``, by a sort on the three columns (five times faster), or on
    one int64 packing them in the same order where their ranges allow."""
    if not len(cells):
        return cells[:0], np.zeros(0, np.int64)
    lo, hi = cells.min(axis=0), cells.max(axis=0)
    span = [int(top) - int(low) + 1 for low, top in zip(lo, hi)]
    if span[0] * span[1] * span[2] < 1 << 62:
        packed = ((cells[:, 0] - lo[0]) * span[1] + (cells[:, 1] - lo[1])) * span[2] + (cells[:, 2] - lo[2])
        by = np.argsort(packed, kind="stable")
    else:
        by = np.lexsort((cells[:, 2], cells[:, 1], cells[:, 0]))
    ordered = cells[by]
    new = np.empty(len(by), bool)
    new[:1] = True
    np.any(ordered[1:] != ordered[:-1], axis=1, out=new[1:])
    inverse = np.empty(len(by), np.int64)
    inverse[by] = np.cumsum(new) - 1
    return ordered[new], inverse


def spatial_order(xyz: np.ndarray, rarity: np.ndarray, prio: np.ndarray, t: int, seed: int) -> np.ndarray:
    """SPEC 9's spatial order (point indices), level by level over every point, down to the first level with
    at least ``t`` occupied cells (or 186 levels below the top one)."""
    n = len(xyz)
    if n == 0:
        return np.zeros(0, np.int64)
    listed = np.zeros(n, bool)
    out = []
    top = _top_level(xyz)
    place = np.empty(n, np.int64)
    place[np.lexsort((prio, rarity))] = np.arange(n)  # each point's place by (rarity, priority), ties none
    for level in range(top, top - 187, -1):
        uniq, cell = _unique_rows(level_cells(xyz, level))
        mass = np.bincount(cell, minlength=len(uniq))  # the points of each cell
        by = np.argsort(cell * n + place)  # each cell's points by (rarity, priority): one int64 key, not three
        first = by[np.r_[True, cell[by][1:] != cell[by][:-1]]]  # the winner of each cell, cells ascending
        new = first[~listed[first]]
        cp = _cell_priority(seed, level, uniq[cell[new]])
        new = new[np.lexsort((prio[new], cp, -mass[cell[new]]))]  # the most points first, then cell priority
        listed[new] = True
        out.append(new)
        if len(uniq) >= t:
            break
    return np.concatenate(out)


def space_sample(sources, coordinates, *, space, ratio=None, count=None, color_space="rgb", bits=0,
                 color_depth="auto", seed=0) -> list:
    """SPEC 9 over ``sources`` ((r, g, b) per source) and ``coordinates`` ((n, 3) float64 per source): the kept
    record indices per source (ascending)."""
    if (ratio is None) == (count is None):
        raise OracleUsageError("--space needs exactly one of ratio, count")
    a = space_share(space)
    keys, coarse, ids, sizes = [], [], [], []
    for ordinal, channels in enumerate(sources):
        (r, g, b), _ = to_8bit(channels, color_depth)
        keys.append(bin_keys(r, g, b, color_space, bits))
        coarse.append(bin_keys(r, g, b, color_space, max(bits, 4)))
        ids.append(point_ids(ordinal, len(r)))
        sizes.append(len(r))
    keys, coarse, ids = np.concatenate(keys), np.concatenate(coarse), np.concatenate(ids)
    xyz = np.concatenate([np.asarray(c, np.float64).reshape(-1, 3) for c in coordinates])
    n = len(keys)
    t = target(n, ratio, count)
    prio = priority(ids, seed)
    _, inverse, counts = np.unique(coarse, return_inverse=True, return_counts=True)
    rarity = counts[inverse.ravel()]
    spatial = spatial_order(xyz, rarity, prio, t, seed)
    rank = np.concatenate(ranks(sources, color_space=color_space, bits=bits, color_depth=color_depth, seed=seed))
    prism_order = np.argsort(rank, kind="stable")
    taken = np.zeros(n, bool)
    i_s = i_p = 0
    for place in range(t):
        spatial_place = (a * (place + 1) + 500000) // 10**6 > (a * place + 500000) // 10**6
        while i_s < len(spatial) and taken[spatial[i_s]]:
            i_s += 1
        if spatial_place and i_s < len(spatial):
            taken[spatial[i_s]] = True
            continue
        while taken[prism_order[i_p]]:
            i_p += 1
        taken[prism_order[i_p]] = True
    keep = np.flatnonzero(taken)
    bounds = np.cumsum([0] + sizes)
    return [keep[(keep >= lo) & (keep < hi)] - lo for lo, hi in zip(bounds[:-1], bounds[1:])]


# -- reading clouds without the engine ----------------------------------------

def read_las_colors(path):
    """The red, green, blue fields of a LAS/LAZ file, as stored (laspy, not the engine)."""
    import laspy

    las = laspy.read(str(path))
    return np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)


def read_parquet_colors(path, names=("red", "green", "blue")):
    """Three color columns of a Parquet file (pyarrow, not the engine)."""
    import pyarrow.parquet as pq

    t = pq.read_table(str(path), columns=list(names))
    return tuple(t.column(n).to_numpy() for n in names)


def lzf_decompress(data: bytes, size: int) -> bytes:
    """The LZF format (liblzf, as PCL's binary_compressed uses it), decoded byte by byte.

    A control byte below 32 starts a run of ctrl + 1 literal bytes; any other is a
    back-reference: length ctrl >> 5 (7 means "add the next byte"), plus 2, copied from
    ((ctrl & 31) << 8) + next byte + 1 bytes back. Raises OracleInputError on a stream that
    reads past its end, reaches before the start or does not give exactly ``size`` bytes.
    """
    out = bytearray()
    i = 0
    while i < len(data):
        ctrl = data[i]
        i += 1
        if ctrl < 32:
            run = data[i:i + ctrl + 1]
            if len(run) != ctrl + 1:
                raise OracleInputError("LZF literal run past the end of the stream")
            out += run
            i += ctrl + 1
            continue
        length = ctrl >> 5
        if length == 7:
            if i >= len(data):
                raise OracleInputError("LZF length byte past the end of the stream")
            length += data[i]
            i += 1
        if i >= len(data):
            raise OracleInputError("LZF offset byte past the end of the stream")
        back = ((ctrl & 31) << 8) + data[i] + 1
        i += 1
        if back > len(out):
            raise OracleInputError("LZF back-reference before the start of the output")
        for _ in range(length + 2):  # byte by byte: a reference may overlap what it writes
            out.append(out[-back])
        if len(out) > size:
            break
    if len(out) != size:
        raise OracleInputError(f"LZF stream gives {len(out)} bytes, not {size}")
    return bytes(out)


PCD_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")


def read_pcd(path) -> dict:
    """The points of a PCD file (ascii, binary or binary_compressed) as {field: array}, NaN points dropped.

    Written from the PCD format (PCL's file_formats page), not from the engine: a header of
    keyword lines up to DATA, then WIDTH x HEIGHT = POINTS records; binary records are packed
    little-endian, binary_compressed is two uint32 sizes and one LZF block holding the fields
    one after another, ascii is one point per line. Records with a NaN x, y or z are not
    points (an organized cloud's holes). Anything else malformed raises OracleInputError.
    """
    raw = open(path, "rb").read()
    header, pos = {}, 0
    while "DATA" not in header:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise OracleInputError("PCD header has no DATA line")
        line = raw[pos:end].strip()
        pos = end + 1
        if not line or line.startswith(b"#"):  # a comment is free text, in any bytes
            continue
        key, *words = line.decode("ascii").split()
        if key not in PCD_KEYS or key in header:
            raise OracleInputError(f"PCD header line {line[:40]!r}")
        header[key] = words
    names = header["FIELDS"]
    sizes = [int(v) for v in header["SIZE"]]
    types = header["TYPE"]
    counts = [int(v) for v in header.get("COUNT", ["1"] * len(names))]
    width, = (int(v) for v in header["WIDTH"])
    height, = (int(v) for v in header.get("HEIGHT", ["1"]))
    points, = (int(v) for v in header.get("POINTS", [str(width * height)]))
    if not (len(names) == len(sizes) == len(types) == len(counts)) or points != width * height or points < 0:
        raise OracleInputError("PCD header fields disagree")
    kinds = {"F": "f", "U": "u", "I": "i"}
    dtype = np.dtype([(n, f"<{kinds[t]}{s}", (c,) if c > 1 else ())
                      for n, s, t, c in zip(names, sizes, types, counts)])
    data, = header["DATA"]
    body = raw[pos:]
    if data == "binary":
        if len(body) < points * dtype.itemsize:
            raise OracleInputError("PCD binary data shorter than its header says")
        rec = np.frombuffer(body, dtype=dtype, count=points)
    elif data == "binary_compressed":
        if len(body) < 8:
            raise OracleInputError("PCD binary_compressed data has no sizes")
        packed, unpacked = (int(v) for v in np.frombuffer(body[:8], "<u4"))
        if unpacked != points * dtype.itemsize or packed > len(body) - 8:
            raise OracleInputError("PCD binary_compressed sizes disagree with the header or the file")
        flat = lzf_decompress(body[8:8 + packed], unpacked)
        rec, at = np.zeros(points, dtype=dtype), 0
        for n in dtype.names:
            field = dtype.fields[n][0]
            nbytes = points * field.itemsize
            rec[n] = np.frombuffer(flat[at:at + nbytes], dtype=field.base).reshape((points,) + field.shape)
            at += nbytes
    elif data == "ascii":
        # a line ends at LF only (a CR is blank space, as for PCL); what follows the points is not read
        lines = [ln.split() for ln in body.split(b"\n") if ln.strip()][:points]
        lines = [[v.decode("ascii") for v in ln] for ln in lines]
        if len(lines) < points or any(len(ln) != sum(counts) for ln in lines[:points]):
            raise OracleInputError("PCD ascii data does not hold the points its header declares")
        rec, col = np.zeros(points, dtype=dtype), 0
        for n, t, c in zip(names, types, counts):
            field = dtype.fields[n][0].base
            cells = [ln[col:col + c] for ln in lines[:points]]
            col += c
            if n in ("rgb", "rgba"):
                # the packed color word, whatever its TYPE: PCL prints it as an unsigned integer; a value
                # that is not one (an old writer's float print) stands for the float's bits
                words = np.array([[_ascii_word(v) for v in cell] for cell in cells], dtype=np.uint32)
                values = words.view(field)
            else:
                values = np.array([[float(v) if t == "F" else int(v) for v in cell] for cell in cells], dtype=field)
            rec[n] = values if c > 1 else values[:, 0]
    else:
        raise OracleInputError(f"PCD DATA {data}")
    holes = np.zeros(points, dtype=bool)
    for axis in ("x", "y", "z"):
        if axis in dtype.names:
            holes |= np.isnan(rec[axis])
    return {n: np.asarray(rec[n][~holes]) for n in dtype.names}


def _ascii_word(text: str) -> int:
    """A PCD ascii color value as its 32-bit word: an integer 0..2^32-1 is the word, any other number a float32's
    bits."""
    value = float(text)
    if math.isfinite(value) and value == math.floor(value) and 0 <= value < 2 ** 32:
        return int(value)
    return int(np.array([value], dtype=np.float32).view(np.uint32)[0])


def pcd_colors(word):
    """The 8-bit channels of packed 0x??RRGGBB color words (a float word by its bits, not its value)."""
    w = np.ascontiguousarray(word).view(np.uint32)
    return (w >> 16) & 255, (w >> 8) & 255, w & 255


# -- the outlier removal of --denoise (SPEC 8): Open3D's rule ----------------

def open3d_sor_reference(xyz: np.ndarray, k: int, std_ratio: float, brute: bool = False,
                         with_distances: bool = False):
    """Open3D's ``PointCloud::RemoveStatisticalOutliers``, written here from its published definition.

    Each point's k nearest neighbours (itself included) by a KD-tree (``brute``: by sorting every distance);
    d_i the mean of their distances; mu the sum of the positive d_i over N; sigma with Bessel's correction
    over the positive d_i; a point is kept when 0 < d_i < mu + std_ratio * sigma. Every sum runs left to
    right, as ``std::accumulate`` does (a cumulative sum, not numpy's pairwise one).
    """
    from scipy.spatial import cKDTree

    n = len(xyz)
    k = min(k, n)
    if brute:
        dist = np.sort(np.sqrt(((xyz[:, None, :] - xyz[None, :, :]) ** 2).sum(axis=2)), axis=1)[:, :k]
    else:
        dist = np.asarray(cKDTree(xyz).query(xyz, k=k)[0]).reshape(n, k)
    d = np.cumsum(dist, axis=1)[:, -1] / k
    pos = d > 0
    mu = np.cumsum(np.where(pos, d, 0.0))[-1] / n
    sigma = math.sqrt(np.cumsum(np.where(pos, (d - mu) * (d - mu), 0.0))[-1] / (n - 1))
    keep = pos & (d < mu + std_ratio * sigma)
    return (keep, d, mu + std_ratio * sigma) if with_distances else keep
