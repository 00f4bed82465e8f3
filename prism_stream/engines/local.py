"""The local engine: the core's passes over whole sources on this machine, with a key cache.

Pass one (:func:`..core.passes.scan`) counts every source into one dense
histogram and appends each point's bin key to a temporary file (4 bytes a
point), so that the cutoff scan and pass two never decode colors again.
Memory holds the dense per-key tables (at most 2^24 keys), one chunk and the
cutoff heaps (one 8-byte word per point kept in a capped bin); it does not
grow with the input.

The SQL engine runs :func:`execute` too, over a query's result.
"""

from __future__ import annotations

import dataclasses
import os
import time

import numpy as np

from ..core.cutoffs import Rules, find_cutoffs
from ..core.histogram import Histogram, SourceScan, Tally, source_scan
from ..core.passes import scan, select
from ..core.quotas import solve
from ..core.selection import Selector
from ..errors import UsageError
from ..formats import open_sink
from ..run import staging
from ..run.inputs import open_sources
from ..run.outputs import Layout
from ..run.progress import Progress
from ..run.request import Request
from ..run.summary import Summary, peak_rss_bytes, provenance, summarize, warn_about


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

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class CachedTally(Tally):
    """One source's keys, counted into the run's shared dense histogram and appended to the key cache."""

    def __init__(self, dense: np.ndarray, cache: KeyCache):
        self.dense = dense
        self.cache = cache
        self.base = cache.size  # where this source's keys start in the cache

    def count(self, spec, r, g, b, shift):
        keys = spec.keys(r, g, b, shift, counts=self.dense)
        self.cache.append(keys)
        return keys

    def refile(self, n):
        moved = self.cache.read(self.base, n).copy()
        np.subtract.at(self.dense, moved, 1)
        self.dense[0] += n
        self.cache.overwrite_zero(self.base, n)

    def histogram(self):
        return None  # the run's histogram is the shared dense one


def sample(inputs, output: str | None = None, request: Request | None = None, **options) -> Summary:
    """Sample ``inputs`` into ``output`` with PRISM; return the run's summary.

    Parameters
    ----------
    inputs : str or list of str
        Files, globs or folders; together they are one cloud.
    output : str or None
        ``.parquet``, ``.las``, ``.laz`` or ``.ply``; a folder for directory
        mode (one output per input); None runs pass one and the solve only
        (a plan), writing nothing.
    request : Request, optional
        Every option at once; ``**options`` are :class:`Request` fields
        (``ratio=0.01``, ``seed=3``, ``quant_bits=2``, ...) and override it.

    Directory mode: when ``output`` is a directory (it exists, or ends with
    a path separator), each input file gets its own output, mirroring the
    input tree; a directory input then means every readable file under it.
    """
    request = Request.of(request, **options)
    layout = Layout.of(inputs, output, request.output_format, request.overwrite)
    if request.per_file:
        if not layout.directory:
            raise UsageError("--per-file needs directory mode (an output folder)")
        return _per_file(layout, request)
    t0 = time.perf_counter()
    sources = open_sources(layout.files, **request.open_options())
    try:
        with staging.work_dir(request.temp_dir) as tmp:
            return execute(sources, layout, request, tmp, [os.path.abspath(f) for f in layout.files], t0=t0)
    finally:
        for s in sources:
            s.close()


def plan(inputs, request: Request | None = None, **options) -> Summary:
    """Pass one and the solve only: what a run would keep, writing nothing."""
    return sample(inputs, None, request, **options)


def execute(sources, layout: Layout, request: Request, tmp: str, inputs: list, *, t0: float,
            no_points: str = "the input has no points; the output is empty", **more_provenance) -> Summary:
    """Both passes over ``sources`` into the layout's outputs, the key cache in ``tmp``.

    ``inputs`` are what the summary names as the inputs; ``layout.output``
    None stops after the solve. A source whose count is unknown (a query's
    result) learns it in pass one.
    """
    options = request.options
    spec = options.spec
    seconds: dict = {}
    chunk = request.chunk_size
    with layout.transaction(), KeyCache(tmp) as cache:
        dense = np.zeros(spec.key_space, dtype=np.int64)
        scans: list[SourceScan] = []
        offsets = []
        declared = None if any(s.count is None for s in sources) else sum(s.count for s in sources)
        with Progress("pass 1/2 histogram", declared, request.progress) as bar:
            for src in sources:
                offsets.append(cache.size)
                unit_scan = scan(src.whole(), spec, options.color_depth, chunk, CachedTally(dense, cache), bar)
                if src.count is None:
                    src.count = unit_scan.points
                scans.append(source_scan(src, unit_scan.points, unit_scan.decision, unit_scan.max_value))
        seconds["scan"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        plan = solve(Histogram.from_dense(dense), options, tuple(s.as_dict() for s in scans))
        del dense
        seconds["solve"] = time.perf_counter() - t1
        caught = warn_about(plan, no_points)
        if layout.output is None:
            return summarize(plan, inputs, None, seconds, caught)

        t2 = time.perf_counter()
        rules = Rules(plan)
        with Progress("cutoffs", cache.size, request.progress and len(rules.caps) > 0) as bar:
            cutoffs = find_cutoffs(rules, sources, chunk, lambda src, a, n: cache.read(offsets[src.ordinal] + a, n),
                                   bar)
        seconds["cutoffs"] = time.perf_counter() - t2

        t3 = time.perf_counter()
        selector = Selector(plan, cutoffs, rules)
        prov = provenance(plan, layout.files, **more_provenance)
        layout.begin()
        kept = 0
        with Progress("pass 2/2 select", cache.size, request.progress) as bar:
            for target, members in layout.targets(sources):
                with open_sink(target, members, prov, flag=request.flag) as sink:
                    for src in members:
                        base = offsets[src.ordinal]
                        for pts, mask in select(src.whole(), plan, selector=selector, chunk_size=chunk, bar=bar,
                                                keys_of=lambda a, n, base=base: cache.read(base + a, n)):
                            sink.write(pts, mask)
                            kept += int(np.count_nonzero(mask))
        if kept != plan.kept:
            raise AssertionError(f"selected {kept} points, the plan keeps {plan.kept}")
        layout.publish()
        seconds["select"] = time.perf_counter() - t3
    seconds["total"] = time.perf_counter() - t0
    return summarize(plan, inputs, layout.output, seconds, caught, layout.published)


def _per_file(layout: Layout, request: Request) -> Summary:
    """Directory mode with an independent solve per file; all outputs published together."""
    t0 = time.perf_counter()
    runs = []
    one = dataclasses.replace(request, overwrite=True, per_file=False, output_format=None)
    with layout.transaction():
        layout.begin()
        for i, f in enumerate(layout.files):
            runs.append(sample(f, layout.stage(i), one))
        layout.publish()
    options = request.options
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
