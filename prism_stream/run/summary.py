"""What a run reports: the summary (text and JSON), the warnings, and the provenance in every output."""

from __future__ import annotations

import os
import resource
import sys
import warnings
from dataclasses import asdict, dataclass, field

from .. import __version__
from ..core.quotas import Plan
from ..errors import PrismWarning
from .remote import absolute


@dataclass
class Summary:
    """What a run did: the plan's totals, the decisions, the timings."""

    inputs: list
    output: str | None
    points: int
    bins: int | None
    target: int | None
    kept: int
    ratio_achieved: float
    rule: str
    k: int | None
    extra: int | None
    seed: int
    options: dict
    sources: list
    seconds: dict = field(default_factory=dict)
    peak_rss_bytes: int = 0
    plan: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    outputs: list = field(default_factory=list)  # every file written (directory mode: one per input)
    version: str = __version__

    def as_dict(self) -> dict:
        return asdict(self)


def peak_rss_bytes() -> int:
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(kb if sys.platform == "darwin" else kb * 1024)


def created() -> str:
    """The run's UTC time (ISO 8601, seconds); ``SOURCE_DATE_EPOCH`` fixes it (byte-reproducible outputs)."""
    import datetime as dt

    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    when = dt.datetime.fromtimestamp(int(epoch), dt.timezone.utc) if epoch and epoch.strip().isdigit() \
        else dt.datetime.now(dt.timezone.utc)
    return when.isoformat(timespec="seconds").replace("+00:00", "Z")


def provenance(plan: Plan, files: list[str], command: tuple | None = None, **more) -> dict:
    """What goes into the output's own metadata: the software, the time and command line, the options, the
    inputs and the plan's totals."""
    s = plan.summary()
    s.pop("bin_size", None)
    return {
        "software": f"prism-stream {__version__}",
        "created": created(),
        **({"command": list(command)} if command else {}),
        "method": "PRISM color-stratified sampling (Lim, Im, Choi 2026)",
        "options": plan.options.as_dict(),
        "inputs": [absolute(f) for f in files],
        **s,
        **more,
    }


def warn_about(plan: Plan, no_points: str = "the input has no points; the output is empty") -> list[str]:
    """Warn (and return the messages) about plans the user should hear of: no points, one bin, T = 0."""
    out = []
    if plan.points == 0:
        out.append(no_points)
    elif plan.bins == 1:
        out.append("every point has the same color: one bin, so the sample is a plain random one")
    elif plan.counts.max() * 2 > plan.points:
        big = int(plan.counts.max())
        out.append(f"one bin holds {100 * big / plan.points:.0f}% of the points ({big} of {plan.points}): the "
                   "colors hardly vary; if the inputs mix 8-bit and 16-bit colors, sample the files apart, give "
                   "--color-depth, or (sql) keep read_parquet's filename column so the depth is decided per file")
    if plan.target == 0 and plan.points:
        out.append(f"the target rounds to 0 points of {plan.points}; the output is empty")
    for msg in out:
        warnings.warn(msg, PrismWarning, stacklevel=3)
    return out


def summarize(plan: Plan, inputs: list, output, seconds, caught, outputs=(), **plan_extra) -> Summary:
    """The Summary of a run of ``plan`` (every engine's); ``plan_extra`` goes under ``plan``."""
    return Summary(
        inputs=list(inputs),
        output=absolute(output) if output else None,
        points=plan.points,
        bins=plan.bins,
        target=plan.target,
        kept=plan.kept,
        ratio_achieved=(plan.kept / plan.points) if plan.points else 0.0,
        rule=plan.options.rule,
        k=plan.k,
        extra=plan.extra,
        seed=plan.seed,
        options=plan.options.as_dict(),
        sources=list(plan.sources),
        seconds={k: round(v, 4) for k, v in seconds.items()},
        peak_rss_bytes=peak_rss_bytes(),
        plan={**plan.summary(), **plan_extra},
        warnings=list(caught),
        outputs=list(outputs),
    )
