"""The quota solve (SPEC 4): from the global histogram to a frozen Plan.

The Plan is what every engine shares: the bin spec, the seed, the totals and
each bin's quota. It serializes to JSON (arrays as base64) so that it can be
broadcast to workers and written into output metadata.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import math
from dataclasses import asdict, dataclass, field
from functools import cached_property

import numpy as np

from . import kernels
from .kernels import SMALL_ARRAY
from .bins import COLOR_DEPTHS, BinSpec
from ..errors import UsageError
from .histogram import Histogram
from .names import MODES, SEED_MAX

COUNT_MAX = (1 << 63) - 1  # counts and caps are int64 in the plan


@dataclass(frozen=True)
class Options:
    """What to sample: exactly one of ratio, count or k, and how to bin."""

    ratio: float | None = None
    count: int | None = None
    k: int | None = None
    mode: str = "exact"
    color_space: str = "rgb"
    quant_bits: int = 0
    color_depth: str = "auto"
    seed: int = 0
    quant_step: float | None = None
    denoise: str | None = None  # sor:K,STD: the cloud sampled is the input without its outliers (SPEC 8)
    space: str | None = None  # A: a share of the target placed spatially (SPEC 9); None or "0": PRISM alone

    def __post_init__(self):
        given = [n for n in ("ratio", "count", "k") if getattr(self, n) is not None]
        if len(given) != 1:
            raise UsageError("give exactly one of --ratio, --count or --k")
        if self.ratio is not None and not (0.0 < float(self.ratio) <= 1.0) or (
            self.ratio is not None and math.isnan(float(self.ratio))
        ):
            raise UsageError(f"--ratio must be in (0, 1], not {self.ratio}")
        if self.count is not None and not (1 <= int(self.count) <= COUNT_MAX):
            raise UsageError(f"--count must be an integer in 1..2**63-1, not {self.count}")
        if self.k is not None and not (1 <= int(self.k) <= COUNT_MAX):
            raise UsageError(f"--k must be an integer in 1..2**63-1, not {self.k}")
        if self.mode not in MODES:
            raise UsageError(f"--mode must be one of {', '.join(MODES)}, not {self.mode!r}")
        if self.color_depth not in COLOR_DEPTHS:
            raise UsageError(f"--color-depth must be one of {', '.join(COLOR_DEPTHS)}, not {self.color_depth!r}")
        if not (0 <= int(self.seed) <= SEED_MAX):
            raise UsageError(f"--seed must be in 0..2**64-1, not {self.seed}")
        self.spec  # validates
        if self.denoise is not None:
            from .denoise import Denoise

            object.__setattr__(self, "denoise", Denoise.parse(self.denoise).label)
        if self.space is not None:
            self._check_space()

    def _check_space(self) -> None:
        from .space import parse_share, share_text

        try:
            a = parse_share(self.space)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        if a == 0:
            object.__setattr__(self, "space", None)  # the paper's PRISM: the same run, the same provenance
            return
        object.__setattr__(self, "space", share_text(a))
        if self.k is not None or self.mode != "exact":
            raise UsageError("--space needs a target (--ratio or --count) in exact mode: its spatial places and "
                             "PRISM's are interleaved in one order whose every prefix is a sample")
        if self.quant_step is not None:
            raise UsageError("--space ranks colors by their 4-bit coarse color, which a --quant-step bin does not "
                             "fall in; use --quant-bits")

    @property
    def share(self) -> int:
        """The spatial share in millionths (SPEC 9), 0 without --space."""
        from .space import parse_share

        return 0 if self.space is None else parse_share(self.space)

    @property
    def spec(self) -> BinSpec:
        return BinSpec(self.color_space, int(self.quant_bits), None if self.quant_step is None else float(self.quant_step))

    @property
    def rule(self) -> str:
        """The quota rule actually applied: ``k`` for a fixed k, else the mode."""
        return "k" if self.k is not None else self.mode

    def target(self, n: int) -> int | None:
        """T for N points, or None for a fixed-k run."""
        if self.ratio is not None:
            return int(math.floor(float(self.ratio) * n + 0.5))
        if self.count is not None:
            if int(self.count) > n:
                raise UsageError(f"--count {self.count:,} is more than the {n:,} points of the input")
            return int(self.count)
        return None

    def as_dict(self) -> dict:
        d = asdict(self)
        if d["quant_step"] is None:  # provenance of bit-quantized runs stays as it was
            del d["quant_step"]
        if d["denoise"] is None:  # and of runs that remove no outliers
            del d["denoise"]
        if d["space"] is None:  # and of runs without a spatial share
            del d["space"]
        return d


def _spread(counts: np.ndarray) -> dict:
    """The bin sizes' minimum, median, 90th and 99th percentiles and maximum (numpy's linear percentiles), on one
    copy of the counts, 4 bytes a bin where they fit (``np.percentile`` alone copies them at 8 bytes a bin and
    partitions that copy: 128 MiB over 2^24 bins)."""
    narrow = int(counts.min()) >= 0 and int(counts.max()) <= np.iinfo(np.uint32).max
    pct = np.percentile(counts.astype(np.uint32) if narrow else counts.copy(), [0, 50, 90, 99, 100],
                        overwrite_input=True)
    return {"min": int(pct[0]), "median": float(pct[1]), "p90": float(pct[2]), "p99": float(pct[3]),
            "max": int(pct[4])}


@dataclass(frozen=True)
class Plan:
    """The solved quotas, frozen: the value every engine's pass two runs on."""

    options: Options
    points: int  # N
    target: int | None  # T (None for --k)
    k: int  # k* (paper mode), K (exact mode) or the fixed k
    extra: int  # E: bins that get K + 1 in exact mode
    keys: np.ndarray = field(repr=False)  # uint32, sorted
    counts: np.ndarray = field(repr=False)  # n_b, int64
    quotas: np.ndarray = field(repr=False)  # q_b, int64
    sources: tuple = ()  # SourceScan.as_dict() of each source, ordinal order

    @property
    def spec(self) -> BinSpec:
        return self.options.spec

    @property
    def seed(self) -> int:
        return int(self.options.seed)

    @property
    def bins(self) -> int:
        return int(self.keys.shape[0]) if self.keys is not None else self.totals["bins"]

    @cached_property
    def kept(self) -> int:
        return int(self.quotas.sum())

    @property
    def capped(self) -> np.ndarray:
        """Mask of bins that keep some but not all of their points."""
        return (self.quotas > 0) & (self.quotas < self.counts)

    @cached_property
    def totals(self) -> dict:
        """What the summary and every output's provenance say of the per-bin arrays, computed once."""
        c = self.counts
        q = self.quotas
        d = {
            "bins": self.bins,
            "kept": self.kept,
            "bins_capped": int(self.capped.sum()),
            "bins_kept_whole": int(((q == c) & (c > 0)).sum()),
            "bins_dropped": int((q == 0).sum()),
        }
        if len(c):
            d["bin_size"] = _spread(c)
        return d

    def without_bins(self) -> "Plan":
        """This plan without its per-bin arrays (``keys``, ``counts`` and ``quotas`` are None): its scalars and
        :attr:`totals` alone, which is all a run's pass two and summary read once the cutoffs' rules are made
        from the arrays. Over 2^24 bins the arrays are 320 MiB (20 bytes a bin), held for nothing through the
        cutoff scan and pass two, where a run's memory peaks (docs/DESIGN.md, "Memory"). A plan already
        without them is returned as it is."""
        if self.keys is None:
            return self
        light = dataclasses.replace(self, keys=None, counts=None, quotas=None)
        light.__dict__.update(totals=self.totals, kept=self.kept)  # cached_property's own store: the values carried
        return light

    def summary(self) -> dict:
        """The plan's scalars and the spread of points over bins (no per-bin arrays)."""
        t = self.totals
        d = {
            "rule": self.options.rule,
            "mode": self.options.mode,
            "seed": self.seed,
            "color_space": self.options.color_space,
            "quant_bits": int(self.options.quant_bits),
            **({"quant_step": self.options.quant_step} if self.options.quant_step is not None else {}),
            "color_depth_option": self.options.color_depth,
            "points": self.points,
            "bins": t["bins"],
            "target": self.target,
            "k_star" if self.options.rule == "paper" else "k": self.k,
            "extra": self.extra,
            "kept": t["kept"],
            "ratio_achieved": (t["kept"] / self.points) if self.points else 0.0,
            "bins_capped": t["bins_capped"],
            "bins_kept_whole": t["bins_kept_whole"],
            "bins_dropped": t["bins_dropped"],
        }
        if "bin_size" in t:
            d["bin_size"] = dict(t["bin_size"])
        d["sources"] = list(self.sources)
        return d

    def to_json(self) -> str:
        def enc(a):
            return base64.b64encode(np.ascontiguousarray(a).tobytes()).decode("ascii")

        return json.dumps(
            {
                "options": self.options.as_dict(),
                "points": self.points,
                "target": self.target,
                "k": self.k,
                "extra": self.extra,
                "keys": enc(self.keys.astype("<u4")),
                "counts": enc(self.counts.astype("<i8")),
                "quotas": enc(self.quotas.astype("<i8")),
                "sources": list(self.sources),
            }
        )

    def json_length(self) -> int:
        """``len(self.to_json())`` without making it (over 2^24 bins it is 425 MB): the arrays' base64 lengths
        added to the rest's."""
        bins = self.bins
        empty = dataclasses.replace(self, keys=np.zeros(0, np.uint32), counts=np.zeros(0, np.int64),
                                    quotas=np.zeros(0, np.int64))
        return len(empty.to_json()) + sum(4 * -(-(width * bins) // 3) for width in (4, 8, 8))

    @staticmethod
    def from_json(text: str) -> "Plan":
        d = json.loads(text)

        def dec(s, dt):
            return np.frombuffer(base64.b64decode(s), dtype=dt).astype(dt[1:])

        options = dict(d["options"])
        if "bits" in options:  # plans written by 0.1.0 called it bits
            options["quant_bits"] = options.pop("bits")
        return Plan(
            options=Options(**options),
            points=d["points"],
            target=d["target"],
            k=d["k"],
            extra=d["extra"],
            keys=dec(d["keys"], "<u4"),
            counts=dec(d["counts"], "<i8"),
            quotas=dec(d["quotas"], "<i8"),
            sources=tuple(d["sources"]),
        )

    def __eq__(self, other):
        if not isinstance(other, Plan):
            return NotImplemented
        return self.to_json() == other.to_json()

    __hash__ = None


def count_profile(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(values, below, at_least): the distinct bin counts ascending; the sum of n_b over the bins whose count is
    below each value; and how many bins hold at least it (one more entry each: beyond the largest value).

    S(k) needs only these, a few thousand entries where a cloud has millions of bins: the solve keeps no
    sorted copy of the counts and no prefix sum over every bin (three arrays of 8 bytes a bin at 2^24 bins)."""
    values, freq = np.unique(counts, return_counts=True)
    below = np.zeros(len(values) + 1, dtype=np.int64)
    np.cumsum(values.astype(np.int64) * freq, out=below[1:])
    at_least = np.zeros(len(values) + 1, dtype=np.int64)
    np.cumsum(freq, out=at_least[1:])
    at_least = len(counts) - at_least
    return values, below, at_least


def capped_total(profile, k: int) -> int:
    """S(k) = sum over bins of min(n_b, k), from the histogram's :func:`count_profile`."""
    values, below, at_least = profile
    i = int(np.searchsorted(values, k, side="left"))  # distinct counts below k
    return int(below[i]) + k * int(at_least[i])


def largest_k_within(profile, target: int) -> int:
    """The largest K in [0, max n_b] with S(K) <= T (S is nondecreasing)."""
    values = profile[0]
    lo, hi = 0, int(values[-1]) if len(values) else 0
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if capped_total(profile, mid) <= target:
            lo = mid
        else:
            hi = mid - 1
    return lo


def bin_priorities(keys: np.ndarray, seed: int) -> np.ndarray:
    """bin_priority(key, seed) of SPEC 3: orders the bins that get an extra point (numpy for up to a
    million bins, so a small run never loads the numba loops)."""
    twin = len(keys) <= SMALL_ARRAY
    return (kernels.priorities_of_np if twin else kernels.priorities_of)(keys.astype(np.uint64),
                                                                          kernels.bin_seed_mix(seed))


def _give_extras(keys: np.ndarray, counts: np.ndarray, quotas: np.ndarray, k: int, extra: int, seed: int,
                 block: int = SMALL_ARRAY) -> None:
    """One more point (``quotas`` in place) for the ``extra`` bins of smallest bin priority among those
    holding more than ``k`` points (SPEC 4), ``block`` bins at a time: the priorities of the eligible bins
    (8 bytes each) are all it holds, partitioned in place for the extra-th smallest, which the bins at or
    under then get (priorities are distinct: splitmix64 is a bijection). Over 15.9M bins an index of the
    eligible bins, their keys, priorities and an argpartition at once took 590 MB."""
    n = len(counts)
    eligible = int(np.count_nonzero(counts > k))
    if extra < eligible:
        prio = np.empty(eligible, dtype=np.uint64)
        at = 0
        for a in range(0, n, block):
            p = bin_priorities(keys[a:a + block][counts[a:a + block] > k], seed)
            prio[at:at + len(p)] = p
            at += len(p)
        prio.partition(extra - 1)
        theta = prio[extra - 1]
        del prio
    else:
        theta = np.uint64(np.iinfo(np.uint64).max)  # every eligible bin gets one
    for a in range(0, n, block):
        over = np.flatnonzero(counts[a:a + block] > k)
        p = bin_priorities(keys[a:a + block][over], seed)
        quotas[a + over[p <= theta]] += 1


def solve(histogram: Histogram, options: Options, sources: tuple = ()) -> Plan:
    """Per-bin quotas for the histogram under the options (SPEC 4)."""
    counts = histogram.counts.astype(np.int64, copy=False)  # no copies: 128 MiB each over 2^24 bins
    keys = histogram.keys.astype(np.uint32, copy=False)
    n = int(counts.sum())
    target = options.target(n)
    profile = count_profile(counts)
    extra = 0
    if options.k is not None:
        k = int(options.k)
        quotas = np.minimum(counts, k)
    elif options.mode == "paper":
        if n == 0:
            k = 1
        else:
            low = largest_k_within(profile, target)
            candidates = [c for c in (low, low + 1) if 1 <= c <= max(1, int(profile[0][-1]))]
            # ties go to the smaller k: min over (distance, k)
            k = min(candidates, key=lambda c: (abs(capped_total(profile, c) - target), c))
        quotas = np.minimum(counts, k)
    else:
        k = largest_k_within(profile, target) if n else 0
        quotas = np.minimum(counts, k)
        extra = target - int(quotas.sum())
        if extra:
            _give_extras(keys, counts, quotas, k, extra, options.seed)
    del profile
    return Plan(options, n, target, int(k), int(extra), keys, counts, quotas.astype(np.int64, copy=False),
                tuple(sources))
