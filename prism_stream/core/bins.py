"""The stratum of a point: its bin key from quantized color (SPEC 1 and 2)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import CorruptInput, UsageError
from . import kernels
from .names import COLOR_DEPTHS, COLOR_SPACES
from .sparse import mark, marks_for


@dataclass(frozen=True)
class BinSpec:
    """How colors become bin keys: the color space, and quantization as bits dropped or a float step.

    ``step`` q (the authors' script's ``-q``): each channel c, the 8-bit value
    or in chroma 255 * v / (r + g + b), becomes floor(c / q + 0.5), computed
    in float64 as ``floor((255.0 * v) / (s * q) + 0.5)`` (chroma) or
    ``floor(v / q + 0.5)`` (rgb), so every engine gets the same bits. q = 1
    gives the unquantized keys exactly.
    """

    color_space: str = "rgb"
    quant_bits: int = 0
    step: float | None = None

    def __post_init__(self):
        if self.color_space not in COLOR_SPACES:
            raise UsageError(f"color space must be one of {', '.join(COLOR_SPACES)}, not {self.color_space!r}")
        if not (0 <= int(self.quant_bits) <= 7):
            raise UsageError(f"quantization bits must be in 0..7, not {self.quant_bits}")
        if self.step is not None:
            if not (float(self.step) >= 1.0 and np.isfinite(float(self.step))):
                raise UsageError(f"--quant-step must be a number >= 1, not {self.step}")
            if int(self.quant_bits):
                raise UsageError("give --quant-bits or --quant-step, not both")

    @property
    def width(self) -> int:
        if self.step is not None:
            return max(1, int(np.floor(255.0 / float(self.step) + 0.5)).bit_length())
        return 8 - self.quant_bits

    @property
    def key_space(self) -> int:
        """Number of possible keys; dense per-key arrays have this length."""
        return 1 << (3 * self.width)

    def keys(self, r, g, b, shift: int = 0, compiled: bool = True) -> np.ndarray:
        """Bin keys (uint32) of integer channels holding 8-bit values after ``>> shift``. ``compiled=False``:
        numpy alone (the same keys), for a run that does not load the numba loops."""
        if self.step is not None:
            return step_keys(r, g, b, shift, self.color_space == "chroma", float(self.step), self.width)
        chroma = self.color_space == "chroma"
        if not compiled:
            return kernels.bin_keys_np(r, g, b, shift, chroma, self.quant_bits)
        r, g, b = kernels.loop_channels(r, g, b)
        return kernels.bin_keys(r, g, b, shift, chroma, self.quant_bits)

    def counted_keys(self, r, g, b, shift: int, counts: np.ndarray, marks: np.ndarray | None = None) -> np.ndarray:
        """:meth:`keys`, each also counted in ``counts`` (a dense histogram over the key space), the block of
        each key counted for the first time marked in ``marks`` (:func:`.sparse.marks_for` of the table: the
        blocks a scan of it must read; none given: made and dropped)."""
        if marks is None:
            marks = marks_for(len(counts))
        if self.step is not None:
            keys = self.keys(r, g, b, shift)
            np.add.at(counts, keys, 1)
            mark(marks, keys)
            return keys
        r, g, b = kernels.loop_channels(r, g, b)
        return kernels.bin_keys_counted(r, g, b, shift, self.color_space == "chroma", self.quant_bits, (counts, marks))

    def channels(self, keys: np.ndarray):
        """The quantized (r, g, b) of each key: the inverse of the key packing."""
        w = self.width
        mask = (1 << w) - 1
        keys = np.asarray(keys, dtype=np.uint32)
        return (keys >> (2 * w)) & mask, (keys >> w) & mask, keys & mask


def step_keys(r, g, b, shift: int, chroma: bool, step: float, width: int) -> np.ndarray:
    """Bin keys with a float quantization step (see :class:`BinSpec`)."""
    r, g, b = (np.asarray(c).astype(np.int64) >> shift for c in (r, g, b))
    if chroma:
        s = (r + g + b).astype(np.float64)
        den = np.where(s > 0, s, 1.0) * step
        lv = [np.where(s > 0, np.floor((255.0 * c) / den + 0.5), 0.0).astype(np.int64) for c in (r, g, b)]
    else:
        lv = [np.floor(c / step + 0.5).astype(np.int64) for c in (r, g, b)]
    return ((lv[0] << (2 * width)) | (lv[1] << width) | lv[2]).astype(np.uint32)


class ColorDepth:
    """The color-depth decision of one source file, made as its colors stream by.

    ``auto`` calls a file 8-bit while every value seen is <= 255. Once a value
    above 255 shows up the file is 16-bit for good; the records seen before
    then all had channels <= 255, so under ``v >> 8`` every one of them falls
    in the bin of (0, 0, 0), whose key is 0 in both color spaces. After the
    chunk that proves it, ``refile`` says how many records pass one must move
    to key 0 instead of re-reading them (:func:`.passes.scan` does it).
    """

    def __init__(self, option: str, path: str, compiled: bool = True):
        if option not in COLOR_DEPTHS:
            raise UsageError(f"color depth must be one of {', '.join(COLOR_DEPTHS)}, not {option!r}")
        self.option = option
        self.path = path
        self.kind = None  # "int" or "float", set by the first chunk
        self.is16 = option == "16"
        self.switched_at = None  # records seen as 8-bit before the switch to 16-bit
        self.refile = 0  # set by the chunk that proved the file 16-bit: the records before it go to key 0
        self.max_value = 0
        self.seen = 0
        self.narrow = False  # 8-bit channel types: no value can exceed 255, the file is 8-bit from the start
        self.channel_range = kernels.channel_range if compiled else kernels.channel_range_np

    @property
    def undecided(self) -> bool:
        """Whether the file may still prove 16-bit: ``auto``, integer colors wider than 8 bits, no value
        above 255 so far."""
        return self.option == "auto" and self.kind == "int" and not self.is16 and not self.narrow

    @property
    def decision(self) -> str:
        """What the file was read as: ``8``, ``16``, ``float`` (or ``8`` for a file with no points)."""
        if self.kind == "float":
            return "float"
        return "16" if self.is16 else "8"

    def prepare(self, r, g, b):
        """Channels ready for :meth:`BinSpec.keys`, and the shift to apply to them."""
        n = len(r)
        self.refile = 0
        kinds = {np.asarray(c).dtype.kind for c in (r, g, b)}
        if "f" in kinds and kinds != {"f"} and kinds <= {"f", "u", "i"}:
            raise CorruptInput("color channels mix floats and integers (" + ", ".join(
                f"{name} {np.asarray(c).dtype}" for name, c in zip(("red", "green", "blue"), (r, g, b))) +
                "): all three as floats in [0, 1] or all as integers", self.path)
        if kinds & {"f"}:
            kind = "float"
            r, g, b = (float_to_8bit(np.asarray(c), self.path) for c in (r, g, b))
        elif kinds <= {"u", "i"}:
            kind = "int"
        else:
            raise CorruptInput(f"color channels have unsupported type {sorted(kinds)}", self.path)
        if self.kind is None:
            self.kind = kind
            self.narrow = all(np.asarray(c).dtype.itemsize == 1 for c in (r, g, b))
        elif self.kind != kind or (self.narrow and any(np.asarray(c).dtype.itemsize != 1 for c in (r, g, b))):
            raise CorruptInput("color channels change type between chunks", self.path)
        r, g, b = kernels.loop_channels(r, g, b)  # after the type checks above, which read the input's own types
        if kind == "float":
            self.seen += n
            return r, g, b, 0
        if n:
            lo, hi = (int(v) for v in self.channel_range(r, g, b))
            if lo < 0:
                raise CorruptInput(f"negative color value {lo}", self.path)
            if hi > 65535:
                raise CorruptInput(f"color value {hi} does not fit in 16 bits", self.path)
            self.max_value = max(self.max_value, hi)
            if hi > 255 and not self.is16:
                if self.option == "8":
                    raise UsageError(
                        f"--color-depth 8 but the file holds color values up to {hi}; use auto or 16", self.path
                    )
                self.is16 = True
                self.switched_at = self.seen
                self.refile = self.seen
        self.seen += n
        return r, g, b, (8 if self.is16 else 0)


def float_to_8bit(c: np.ndarray, path: str) -> np.ndarray:
    """floor(255 * c) for float colors in [0, 1]; anything else is an input error."""
    c = np.asarray(c)
    if c.size:
        bad = ~((c >= 0.0) & (c <= 1.0))
        if bad.any():
            v = c[bad][0].item()
            raise CorruptInput(f"float color {v!r} outside [0, 1]", path)
    return np.floor(c.astype(np.float64) * 255.0).astype(np.uint8)


def decided_keys(spec: BinSpec, rgb, decision: str, path: str) -> np.ndarray:
    """Bin keys of a chunk whose source's color depth is already decided (pass two, any engine)."""
    r, g, b = rgb
    if decision == "float" or any(np.asarray(c).dtype.kind == "f" for c in rgb):
        r, g, b = (float_to_8bit(np.asarray(c), path) for c in rgb)
        return spec.keys(r, g, b, 0)
    return spec.keys(r, g, b, 8 if decision == "16" else 0)
