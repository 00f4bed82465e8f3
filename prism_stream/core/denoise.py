"""``--denoise sor:K,STD``: the statistical outlier removal a run applies before sampling, as a spec.

Parsing only (no scipy): :class:`~prism_stream.core.quotas.Options` validates
the text at every start; the removal itself is ``evaluate/denoise.py``
(Open3D's rule, streamed), run by ``engines/cleaned.py`` for ``sample`` and
by ``eval``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from ..errors import UsageError

_SOR = re.compile(r"^sor:(\d+),([0-9.eE+-]+)$")


@dataclass(frozen=True)
class Denoise:
    """``--denoise sor:K,STD``: statistical outlier removal with K neighbours and a STD-sigma cut."""

    neighbours: int = 100
    std_ratio: float = 2.0

    @staticmethod
    def parse(text: str) -> "Denoise":
        m = _SOR.match(str(text).strip().lower())
        if not m:
            raise UsageError(f"--denoise takes sor:K,STD (e.g. sor:100,2.0), not {text!r}")
        k, std = int(m.group(1)), float(m.group(2))
        if k < 1 or not (std > 0 and math.isfinite(std)):
            raise UsageError(f"--denoise sor:K,STD needs K >= 1 and STD > 0, not {text!r}")
        return Denoise(k, std)

    @property
    def label(self) -> str:
        return f"sor:{self.neighbours},{self.std_ratio:g}"
