"""What a sink needs to write points of one format in another.

A LAS or PLY sink fed from another format must know two things per chunk:
which source it came from (the engine writes sources in order, each from
record 0) and that source's color-depth decision, so that it can store
colors by the same rule that binned them (SPEC 1).
"""

from __future__ import annotations

import numpy as np

from ..core.bins import float_to_8bit
from ..errors import CorruptInput


def as_unsigned(values: np.ndarray) -> np.ndarray:
    """A color channel declared signed, read as the unsigned word of the same width.

    A writer that puts colors in a signed ``char`` stores the byte 200 as -56;
    two's complement gives the byte back. Floats and unsigned ints pass as is.
    """
    values = np.asarray(values)
    if values.dtype.kind == "i":
        return values.view(values.dtype.str.replace("i", "u"))
    if values.dtype.kind == "b":
        return values.astype(np.uint8)
    return values


def color_fields(source) -> tuple:
    """Names of the columns of ``source.arrow_schema()`` that hold its colors."""
    names = getattr(source, "color_fields", None) or getattr(source, "rgb_names", None)
    return tuple(names) if names else ("red", "green", "blue")


def depth_decisions(sources, provenance: dict) -> list[str]:
    """Each source's color-depth decision (``8``, ``16``, ``float``), in source order."""
    by_ordinal = {s.get("ordinal"): s.get("color_depth", "8") for s in provenance.get("sources", [])}
    return [str(by_ordinal.get(s.ordinal, "8")) for s in sources]


EIGHT_BIT_RULES = {"8": "8-bit values as they are", "16": "16-bit values >> 8", "float": "floor(255 c)"}


def eight_bit_rules(decisions) -> str:
    """How the sources' colors become 8-bit, by their depth decisions, in words (a writer's note)."""
    return ", ".join(EIGHT_BIT_RULES.get(d, d) for d in sorted(set(decisions)))


def colors_8bit(rgb, decision: str, path: str) -> tuple:
    """The three 8-bit channels of a chunk under its source's depth decision."""
    out = []
    for c in rgb:
        c = as_unsigned(np.asarray(c))
        if decision == "float" or c.dtype.kind == "f":
            out.append(float_to_8bit(c, path))
        elif decision == "16":
            out.append((c.astype(np.uint32) >> 8).astype(np.uint8))
        else:
            if c.size and int(c.max()) > 255:
                raise CorruptInput(f"color value {int(c.max())} in a file read as 8-bit", path)
            out.append(c.astype(np.uint8))
    return tuple(out)


def colors_16bit(rgb, decision: str, path: str) -> tuple:
    """The three 16-bit (LAS) channels: 8-bit colors scaled by 256, 16-bit ones kept."""
    if decision == "16" and not any(np.asarray(c).dtype.kind == "f" for c in rgb):
        return tuple(as_unsigned(np.asarray(c)).astype(np.uint16) for c in rgb)
    return tuple(c.astype(np.uint16) << 8 for c in colors_8bit(rgb, decision, path))


class SourceCursor:
    """Which source each written chunk belongs to.

    The engine's pass two hands the sink every chunk of every source, in
    source order and record order; a chunk that carries ``ordinal`` says so
    itself, otherwise the cursor follows the record counts.
    """

    def __init__(self, sources):
        self.sources = list(sources)
        self.index = -1
        self.pos = 0

    def source_index(self, chunk) -> int:
        ordinal = getattr(chunk, "ordinal", None)
        if ordinal is not None:
            for i, s in enumerate(self.sources):
                if s.ordinal == ordinal:
                    self.index, self.pos = i, chunk.start + len(chunk)
                    return i
        if self.index < 0 or self.pos >= self.sources[self.index].count or chunk.start == 0 and self.pos:
            self.index += 1
            while self.index < len(self.sources) - 1 and self.sources[self.index].count == 0:
                self.index += 1
            self.pos = 0
        self.index = min(self.index, len(self.sources) - 1)
        self.pos = chunk.start + len(chunk)
        return self.index
