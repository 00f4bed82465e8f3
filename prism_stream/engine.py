"""The local streaming engine: source -> scan -> plan -> cutoffs -> select -> sink.

Two passes over the inputs in chunks. Pass one builds the global histogram
and caches each point's bin key in a temporary file (4 bytes a point), so
that the cutoff scan and pass two never decode colors again. Memory holds
the dense per-key tables (at most 2^24 keys), one chunk and the cutoff
heaps (one 8-byte word per point kept in a capped bin); it does not grow
with the input.
"""

from __future__ import annotations

import os
import resource
import sys
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass, field

import numpy as np

from . import __version__
from .bins import ColorDepth
from .cutoff import Rules, find_cutoffs
from .errors import CorruptInput, Interrupted, UsageError
from .formats import open_sink, open_source
from .layout import Layout
from .kernels import ID_SHIFT, MAX_RECORDS_PER_SOURCE
from .plan import Options, Plan, solve
from .prefetch import prefetched
from .progress import Progress
from .scan import HistogramAccumulator, SourceScan, source_scan
from .select import Selector

DEFAULT_CHUNK = 1 << 20


class PrismWarning(UserWarning):
    """Something the user should know that does not stop the run (one bin, no points)."""


@dataclass
class Summary:
    """What a run did: the plan's totals, the decisions, the timings."""

    inputs: list
    output: str | None
    points: int
    bins: int
    target: int | None
    kept: int
    ratio_achieved: float
    rule: str
    k: int
    extra: int
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


class KeyCache:
    """Every point's bin key, in input order, in a temporary file."""

    def __init__(self, folder: str):
        self.path = os.path.join(folder, "keys.u32")
        self.file = open(self.path, "w+b")
        self.size = 0

    def append(self, keys: np.ndarray) -> None:
        self.file.write(np.ascontiguousarray(keys, dtype=np.uint32).tobytes())
        self.size += len(keys)

    def read(self, offset: int, n: int) -> np.ndarray:
        self.file.flush()
        self.file.seek(offset * 4)
        data = self.file.read(n * 4)
        return np.frombuffer(data, dtype=np.uint32)

    def overwrite_zero(self, offset: int, n: int) -> None:
        self.file.flush()
        self.file.seek(offset * 4)
        self.file.write(bytes(n * 4))
        self.file.seek(0, os.SEEK_END)

    def close(self) -> None:
        self.file.close()


def provenance(plan: Plan, files: list[str]) -> dict:
    """What goes into the output's own metadata (SPEC 6)."""
    s = plan.summary()
    s.pop("bin_size", None)
    return {
        "software": f"prism-stream {__version__}",
        "method": "PRISM color-stratified sampling (Lim, Im, Choi 2026)",
        "options": plan.options.as_dict(),
        "inputs": [os.path.abspath(f) for f in files],
        **s,
    }


def sample(
    inputs,
    output: str | None = None,
    *,
    ratio: float | None = None,
    count: int | None = None,
    k: int | None = None,
    mode: str = "exact",
    color_space: str = "rgb",
    quant_bits: int = 0,
    quant_step: float | None = None,
    color_depth: str = "auto",
    seed: int = 0,
    chunk_size: int = DEFAULT_CHUNK,
    threads: int | None = None,
    rgb_columns=None,
    overwrite: bool = False,
    progress: bool = False,
    temp_dir: str | None = None,
    flag: str | None = None,
    output_format: str | None = None,
    per_file: bool = False,
) -> Summary:
    """Sample ``inputs`` into ``output`` with PRISM (SPEC.md); return the run's summary.

    Parameters
    ----------
    inputs : str or list of str
        Files, globs or Parquet directories; together they are one cloud.
    output : str or None
        ``.parquet``, ``.las`` or ``.laz``; None runs pass one and the solve
        only (a plan), writing nothing.
    ratio, count, k
        Exactly one: the target ratio of N, the target count T, or a fixed
        per-bin cap k.
    mode : {"exact", "paper"}
        ``exact`` keeps exactly T points; ``paper`` uses the paper's single
        integer k* whose total is closest to T.
    color_space, quant_bits, quant_step, color_depth, seed
        Binning and hashing options, as in SPEC.md; ``quant_step`` is the
        authors' float step (see :class:`prism_stream.bins.BinSpec`).
    chunk_size : int
        Points read at a time; the output does not depend on it.
    threads : int or None
        Decoder threads (LAZ, Parquet) and read-ahead; None uses every core.
        The output does not depend on it.
    flag : str or None
        Write every point, with a keep flag, instead of dropping points: a
        column (Parquet, PLY) or extra-bytes dimension (LAS) of that name,
        or ``"withheld"`` for the LAS withheld bit on dropped points.
    output_format : str or None
        Directory mode only: the extension of each output (``parquet``,
        ``las``, ``laz``...); default: each input's own.
    per_file : bool
        Directory mode only: solve each file on its own instead of one
        global solve across all of them.

    Directory mode: when ``output`` is a directory (it exists, or ends with
    a path separator), each input file gets its own output, mirroring the
    input tree; a directory input then means every readable file under it.
    """
    options = Options(ratio=ratio, count=count, k=k, mode=mode, color_space=color_space, bits=int(quant_bits),
                      quant_step=quant_step,
                      color_depth=color_depth, seed=int(seed))
    if chunk_size < 1:
        raise UsageError(f"--chunk-size must be positive, not {chunk_size}")
    if threads is None:
        threads = os.cpu_count() or 1
    if threads < 1:
        raise UsageError(f"--threads must be positive, not {threads}")
    layout = Layout.of(inputs, output, output_format, overwrite)
    output = layout.output
    files = layout.files
    if per_file:
        if not layout.directory:
            raise UsageError("--per-file needs directory mode (an output folder)")
        return _per_file(layout, options, dict(chunk_size=chunk_size, threads=threads, rgb_columns=rgb_columns,
                                               progress=progress, temp_dir=temp_dir, flag=flag))
    spec = options.spec
    seconds = {}
    caught: list[str] = []
    t0 = time.perf_counter()
    sources = [open_source(f, i, threads=threads, rgb_columns=rgb_columns) for i, f in enumerate(files)]
    for s in sources:
        if s.count >= MAX_RECORDS_PER_SOURCE:
            raise CorruptInput(f"{s.count} points is more than one source may hold (2^{ID_SHIFT})", s.path)
    total_declared = sum(s.count for s in sources)
    sink = None
    try:
        with tempfile.TemporaryDirectory(prefix="prism-stream-", dir=temp_dir) as tmp:
            cache = KeyCache(tmp)
            try:
                acc = HistogramAccumulator(spec)
                scans = []
                offsets = []
                with Progress("pass 1/2 histogram", total_declared, progress) as bar:
                    for src in sources:
                        offsets.append(cache.size)
                        scans.append(scan_source(src, spec, options.color_depth, chunk_size, acc, cache, bar))
                seconds["scan"] = time.perf_counter() - t0
                t1 = time.perf_counter()
                plan = solve(acc.histogram(), options, tuple(s.as_dict() for s in scans))
                del acc
                seconds["solve"] = time.perf_counter() - t1
                caught += warn_about(plan)
                if output is None:
                    return summarize(plan, [os.path.abspath(f) for f in files], None, seconds, caught)
                t2 = time.perf_counter()
                rules = Rules(plan)
                with Progress("cutoffs", cache.size, progress and len(rules.caps) > 0) as bar:
                    cutoffs = find_cutoffs(rules, sources, chunk_size,
                                           lambda src, a, n: cache.read(offsets[src.ordinal] + a, n), bar)
                seconds["cutoffs"] = time.perf_counter() - t2
                t3 = time.perf_counter()
                selector = Selector(plan, cutoffs, rules)
                prov = provenance(plan, files)
                layout.begin()
                kept = 0
                with Progress("pass 2/2 select", total_declared, progress) as bar:
                    for target, members in layout.targets(sources):
                        sink = open_sink(target, members, prov, flag=flag)
                        for src in members:
                            kept += _select_source(src, offsets[src.ordinal], chunk_size, selector, cache, sink, bar)
                        sink.commit()
                        sink = None
                if kept != plan.kept:
                    raise AssertionError(f"selected {kept} points, the plan keeps {plan.kept}")
                layout.publish()
                seconds["select"] = time.perf_counter() - t3
            finally:
                cache.close()
    except KeyboardInterrupt:
        if sink is not None:
            sink.abort()
        layout.discard()
        raise Interrupted("interrupted; no output was written", output) from None
    except BaseException:
        if sink is not None:
            sink.abort()
        layout.discard()
        raise
    finally:
        for s in sources:
            s.close()
    seconds["total"] = time.perf_counter() - t0
    return summarize(plan, [os.path.abspath(f) for f in files], output, seconds, caught, layout.published)


def _chunks(iterator, src):
    """Read ahead on a thread when the source may use more than one."""
    return prefetched(iterator) if getattr(src, "threads", 1) > 1 else iterator


def _per_file(layout: Layout, options: Options, run: dict) -> Summary:
    """Directory mode with an independent solve per file; all outputs published together."""
    t0 = time.perf_counter()
    runs = []
    layout.begin()
    try:
        for i, f in enumerate(layout.files):
            runs.append(sample(f, layout.stage(i), ratio=options.ratio, count=options.count, k=options.k,
                               mode=options.mode, color_space=options.color_space, quant_bits=options.bits,
                               quant_step=options.quant_step, color_depth=options.color_depth, seed=options.seed, overwrite=True, **run))
        layout.publish()
    except KeyboardInterrupt:
        layout.discard()
        raise Interrupted("interrupted; no output was written", layout.output) from None
    except BaseException:
        layout.discard()
        raise
    points = sum(r.points for r in runs)
    kept = sum(r.kept for r in runs)
    for r, final in zip(runs, layout.published):
        r.output = final
        r.outputs = [final]
    return Summary(
        inputs=[os.path.abspath(f) for f in layout.files], output=os.path.abspath(layout.output), points=points,
        bins=None, target=(sum(r.target for r in runs) if options.k is None else None), kept=kept,
        ratio_achieved=(kept / points) if points else 0.0, rule=options.rule, k=None, extra=None,
        seed=int(options.seed), options=options.as_dict(), sources=[s for r in runs for s in r.sources],
        seconds={"total": round(time.perf_counter() - t0, 4)}, peak_rss_bytes=peak_rss_bytes(),
        plan={"per_file": [r.as_dict() for r in runs]}, warnings=[w for r in runs for w in r.warnings],
        outputs=list(layout.published),
    )


def scan_source(src, spec, color_depth, chunk_size, acc, cache, bar) -> SourceScan:
    """Pass one over one source: count its keys into ``acc`` and append them to ``cache``.

    A source whose ``count`` is None (a query's result) is not checked against a declared count.
    """
    depth = ColorDepth(color_depth, src.path)
    base = cache.size
    seen = 0
    for chunk in _chunks(src.color_chunks(chunk_size), src):
        if chunk.start != seen:
            raise CorruptInput(f"reader skipped from record {seen} to {chunk.start}", src.path)
        r, g, b, shift = depth.prepare(*chunk.rgb)
        if depth.switched_at == seen and seen and shift == 8:
            # this chunk proved the file 16-bit: the points read as 8-bit so far all go to key 0
            acc.move_to_zero(cache.read(base, seen).copy())
            cache.overwrite_zero(base, seen)
        keys = spec.keys(r, g, b, shift, counts=acc.dense)
        cache.append(keys)
        seen += len(keys)
        bar.update(len(keys))
    if src.count is not None and seen != src.count:
        raise CorruptInput(f"header declares {src.count} points but {seen} could be read", src.path)
    return source_scan(src, seen, depth.decision, depth.max_value)


def _select_source(src, offset, chunk_size, selector, cache, sink, bar) -> int:
    seen = kept = 0
    for chunk in _chunks(src.point_chunks(chunk_size), src):
        n = len(chunk)
        if chunk.start != seen:
            raise CorruptInput(f"reader skipped from record {seen} to {chunk.start}", src.path)
        keys = cache.read(offset + chunk.start, n)
        if len(keys) != n:
            raise CorruptInput("the file changed between the two passes", src.path)
        mask = selector.mask(keys, src.ordinal, chunk.start)
        sink.write(chunk, mask)
        kept += int(np.count_nonzero(mask))
        seen += n
        bar.update(n)
    if seen != src.count:
        raise CorruptInput(f"pass two read {seen} points, pass one {src.count}: the file changed", src.path)
    return kept


def warn_about(plan: Plan, no_points: str = "the input has no points; the output is empty") -> list[str]:
    """Warn (and return the messages) about plans the user should hear of: no points, one bin, T = 0."""
    out = []
    if plan.points == 0:
        out.append(no_points)
    elif plan.bins == 1:
        out.append("every point has the same color: one bin, so the sample is a plain random one")
    if plan.target == 0 and plan.points:
        out.append(f"the target rounds to 0 points of {plan.points}; the output is empty")
    for msg in out:
        warnings.warn(msg, PrismWarning, stacklevel=3)
    return out


def summarize(plan: Plan, inputs: list, output, seconds, caught, outputs=()) -> Summary:
    """The Summary of a run of ``plan`` (every engine's)."""
    return Summary(
        inputs=list(inputs),
        output=os.path.abspath(output) if output else None,
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
        plan=plan.summary(),
        warnings=list(caught),
        outputs=list(outputs),
    )


def plan(inputs, **kw) -> Summary:
    """Pass one and the solve only: what a run would keep, writing nothing."""
    return sample(inputs, None, **kw)
