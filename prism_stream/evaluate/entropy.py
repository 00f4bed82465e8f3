"""Color entropy under a named binning: the paper's "color entropy gain", made explicit.

The paper reports a color entropy gain without saying which histogram it is
taken over. Every binning here is a function of a point's 8-bit RGB color,
so the entropy of a cloud under any of them comes from its 8-bit RGB
histogram (:class:`prism_stream.core.histogram.Histogram` over ``RGB8`` keys) by
regrouping, with no further pass over the points:

- ``rgb8``: the 8-bit RGB triples (2^24 bins), the finest the sampler sees.
- ``sampler``: the strata of the PRISM run being measured (its color space
  and quantization), so PRISM with k = 1 is uniform over them.
- ``rgb-grid``: a fixed coarse grid, 8 levels a channel (``v >> 5``, 512
  bins), the same for every run.
- ``hue-sat``: HSV hue x saturation, 36 x 10 cells, the grid of the paper's
  color-distribution figure; gray points (saturation 0) share the hue-0 cells.

See docs/EVALUATION.md for which of them reproduces the paper's numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.bins import BinSpec
from ..errors import UsageError
from ..core.histogram import Histogram
from .cloud import RGB8
from .metrics import entropy_bits

SCHEMES = ("rgb8", "sampler", "rgb-grid", "hue-sat")
GRID_SHIFT = 5  # rgb-grid: 8 levels a channel
HUE_BINS = 36
SAT_BINS = 10


@dataclass(frozen=True)
class Strata:
    """The bins of a PRISM run: color space and quantization, as bits dropped or as a step.

    ``step`` is the authors' float quantization step q: a channel c (8-bit,
    or 255 * v / (r + g + b) in chroma) becomes floor(c / q + 0.5).
    ``bits`` drops low bits (SPEC 2). At most one of them is not neutral.
    """

    color_space: str = "rgb"
    bits: int = 0
    step: float | None = None

    def __post_init__(self):
        BinSpec(self.color_space, self.bits)  # validates
        if self.step is not None:
            if not (float(self.step) >= 1.0 and np.isfinite(self.step)):
                raise UsageError(f"--quant-step must be a number >= 1, not {self.step}")
            if self.bits:
                raise UsageError("give --quant-bits or --quant-step, not both")

    @property
    def label(self) -> str:
        q = f"q{self.step:g}" if self.step is not None else f"{self.bits}b"
        return f"{self.color_space} {q}"

    def levels(self, r, g, b):
        """The quantized channels of 8-bit colors, each 0..max_level."""
        r, g, b = (np.asarray(c, dtype=np.int64) for c in (r, g, b))
        if self.step is None:
            spec = BinSpec(self.color_space, self.bits)
            return spec.channels(spec.keys(r, g, b, 0))
        q = float(self.step)
        if self.color_space == "chroma":
            s = (r + g + b).astype(np.float64)
            safe = np.where(s > 0, s, 1.0) * q
            return tuple(np.where(s > 0, np.floor((255.0 * c) / safe + 0.5), 0).astype(np.int64) for c in (r, g, b))
        return tuple(np.floor(c / q + 0.5).astype(np.int64) for c in (r, g, b))

    def keys(self, r, g, b) -> np.ndarray:
        lr, lg, lb = self.levels(r, g, b)
        return ((lr << 20) | (lg << 10) | lb).astype(np.int64)


def regroup(histogram: Histogram, scheme: str, strata: Strata | None = None) -> np.ndarray:
    """Point counts per bin of ``scheme``, from an 8-bit RGB histogram (bin order unspecified)."""
    if scheme not in SCHEMES:
        raise UsageError(f"--entropy-bins takes {', '.join(SCHEMES)} or all, not {scheme!r}")
    counts = np.asarray(histogram.counts, dtype=np.int64)
    if scheme == "rgb8" or not len(counts):
        return counts
    r, g, b = (c.astype(np.int64) for c in RGB8.channels(histogram.keys))
    if scheme == "sampler":
        keys = (strata or Strata()).keys(r, g, b)
    elif scheme == "rgb-grid":
        keys = ((r >> GRID_SHIFT) << 6) | ((g >> GRID_SHIFT) << 3) | (b >> GRID_SHIFT)
    else:
        keys = hue_sat_cells(r, g, b).ravel()
    _, inverse = np.unique(keys, return_inverse=True)
    return np.bincount(inverse.ravel(), weights=counts).astype(np.int64)


def hue_sat_cells(r, g, b, hue_bins: int = HUE_BINS, sat_bins: int = SAT_BINS) -> np.ndarray:
    """Flat (hue, saturation) cell index of 8-bit colors: HSV hue and saturation, equal-width cells.

    Integer arithmetic, so a color on a cell edge (hue exactly 170 degrees)
    falls in the cell it starts, not wherever a float rounding puts it.
    ``hue_bins`` must be a multiple of 6 (one run of cells per hue sextant).
    """
    r, g, b = (np.asarray(c, dtype=np.int64) for c in (r, g, b))
    hi = np.maximum(np.maximum(r, g), b)
    span = hi - np.minimum(np.minimum(r, g), b)
    per = hue_bins // 6
    x = np.where(hi == r, per * (g - b), np.where(hi == g, per * (b - r) + 2 * per * span,
                                                 per * (r - g) + 4 * per * span))
    safe = np.where(span > 0, span, 1)
    hue = np.where(span > 0, (x // safe) % hue_bins, 0)
    sat = np.minimum((sat_bins * span) // np.where(hi > 0, hi, 1), sat_bins - 1)
    return hue * sat_bins + sat


def parse_schemes(text) -> tuple:
    """``--entropy-bins``: a comma-separated list of schemes, or ``all``; the first is the headline."""
    items = [t.strip().lower() for t in (text.split(",") if isinstance(text, str) else text) if t.strip()]
    if items == ["all"]:
        return SCHEMES
    bad = [t for t in items if t not in SCHEMES]
    if bad or not items:
        raise UsageError(f"--entropy-bins takes a comma-separated list of {', '.join(SCHEMES)}, or all; "
                         f"not {text!r}")
    return tuple(dict.fromkeys(items))


def entropies(input_hist: Histogram, output_hist: Histogram, schemes, strata: Strata | None = None) -> dict:
    """{scheme: {"input", "output", "gain", "bins_input", "bins_output"}} in bits."""
    out = {}
    for s in schemes:
        ci, co = regroup(input_hist, s, strata), regroup(output_hist, s, strata)
        hi, ho = entropy_bits(ci), entropy_bits(co)
        out[s] = {"input": hi, "output": ho, "gain": ho - hi, "bins_input": int((ci > 0).sum()),
                  "bins_output": int((co > 0).sum())}
    return out
