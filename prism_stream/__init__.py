"""prism-stream: out-of-core PRISM color-stratified point cloud sampling.

The pipeline, one module a step: :mod:`.formats` (sources and sinks),
:mod:`.scan` (pass one), :mod:`.plan` (the quota solve), :mod:`.cutoff`
(per-bin priority cutoffs), :mod:`.select` (pass two); :mod:`.engine`
drives them locally.
"""

__version__ = "0.1.0"

from .bins import BinSpec  # noqa: E402
from .cutoff import Cutoffs  # noqa: E402
from .engine import PrismWarning, Summary, plan, sample  # noqa: E402
from .errors import PrismError  # noqa: E402
from .plan import Options, Plan, solve  # noqa: E402
from .scan import Histogram, merge_units, scan  # noqa: E402
from .select import select  # noqa: E402

__all__ = [
    "BinSpec",
    "Cutoffs",
    "Histogram",
    "Options",
    "Plan",
    "PrismError",
    "PrismWarning",
    "Summary",
    "merge_units",
    "plan",
    "sample",
    "scan",
    "select",
    "solve",
    "__version__",
]
