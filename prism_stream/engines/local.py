"""The local engine: a run over whole sources on this machine.

:func:`sample` opens the inputs, refuses what the outputs' writers would
refuse before a point is decoded, and hands :func:`execute` the sources;
:func:`execute` picks how the input is read (held in memory, once with a
candidate spill, or twice with a key cache: :mod:`.reads`) and runs the
pipeline (:mod:`.pipeline`). The SQL engine runs :func:`execute` too, over a
query's result.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import time
import warnings

from ..core.warm import warm_up
from ..errors import Interrupted, UsageError
from ..formats import check_sink, extension
from ..formats.conversion import color_fields
from ..formats.columns import check_selection_apart, own_selection, read_only_kept
from ..run import remote, staging
from ..run.inputs import open_sources, warn_read_again
from ..run.outputs import Layout
from ..run.progress import notice_compiling
from ..run.request import Request
from ..run.spill import SpillFull, spill_refusal
from ..run.tempspace import TempForecast, forecast
from ..run.summary import Summary, peak_rss_bytes
from . import cleaned, spatial
from .pipeline import NO_POINTS, Run, run_pipeline, write_options
from .reads import Held, Reread, Spilled

MEMORY_POINTS = 1 << 20  # inputs of at most this many points are held in memory (no numba loop loads)


def one_read_refusal(sources, request: Request) -> str | None:
    """Why a run of these options reads its input twice (None: once, with a candidate spill)."""
    if request.reads == "two":
        return "--reads two"
    if request.flag is not None:
        return "--flag writes every point"
    if request.options.space is not None:
        return "--space: pass one, the spatial order and pass two each read the input"
    return spill_refusal(sources)


def sample(inputs, output: str | None = None, request: Request | None = None, **options) -> Summary:
    """Sample ``inputs`` into ``output`` with PRISM; return the run's summary.

    Parameters
    ----------
    inputs : str or list of str
        Files, globs or folders; together they are one cloud.
    output : str or None
        ``.parquet``, ``.las``, ``.laz``, ``.copc.laz``, ``.ply`` or ``.xyz``; a folder for directory
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
    _refuse_by_name(layout, request)
    warn_read_again(inputs, output)
    if request.per_file:
        if not layout.directory:
            raise UsageError("--per-file needs directory mode (an output folder)")
        with _opened(layout, request) as sources:  # every file's refusals before the first file is sampled
            refuse_outputs(layout, sources, request)
            cleaned.refuse(request, sources, per_file=True)
            spatial.check_coordinates(request.options, sources)
            selections = [_per_file_selection(request.selection, s) for s in sources]  # each the names it has
        return _per_file(layout, request, selections)
    t0 = time.perf_counter()
    sources = open_sources(layout.files, **request.open_options(), copies_to=request.temp_dir)
    try:
        refuse_outputs(layout, sources, request)
        cleaned.refuse(request, sources)
        spatial.check_coordinates(request.options, sources)
        read_only_kept(sources, request.selection)
        if request.options.denoise is not None:
            cleaned.load()  # scipy's KD-tree, before the kernels' warm-up holds scipy.linalg back (core/warm.py)
        if not held_in_memory(sources, request):
            for s in sources:
                s.prestart()  # decoder processes (a large LAZ file) start beside the numba loading
            notice_compiling(request.progress)  # before the loading thread imports numba: never two at once
            warm_up()  # the numba loops load while the first chunk is decoded
        inputs = [remote.absolute(f) for f in layout.files]
        with staging.work_dir(request.temp_dir) as tmp:
            if request.options.denoise is None:
                return execute(sources, layout, request, tmp, inputs, t0=t0)
            kept, removal = cleaned.clean(sources, request, tmp, layout.files)
            every = removal["points_before"] and removal["removed"] == removal["points_before"]
            empty = (f"--denoise {removal['method']} removed every point of the input; the output is empty"
                     if every else NO_POINTS)
            summary = execute(kept, layout, request, tmp, inputs, t0=t0, no_points=empty, denoise=removal)
            summary.plan["denoise"] = removal
            return summary
    finally:
        for s in sources:
            s.close()


def _refuse_by_name(layout: Layout, request: Request) -> None:
    if request.order == "rank":
        for path in layout.outputs():
            if extension(path) == ".copc.laz":
                raise UsageError("--order rank cannot apply to COPC output: COPC orders its points by octree "
                                 "node (write .laz, .las, .parquet or .ply for a progressive file"
                                 + ("; in directory mode, --format laz" if layout.directory else "") + ")", path)


def refuse_outputs(layout: Layout, sources, request: Request) -> None:
    """What a writer would refuse of each output, from the options and the inputs' headers: before a point
    is decoded, naming the output as the user gave it."""
    if layout.directory:
        check_selection_apart(request.selection, sources)
    for path, members in layout.planned(sources):
        check_sink(path, members, write_options(layout, request, members))


@contextlib.contextmanager
def _opened(layout: Layout, request: Request):
    sources = open_sources(layout.files, **request.open_options(), copies_to=request.temp_dir)
    try:
        yield sources
    finally:
        for s in sources:
            s.close()


def check_run(inputs, output: str, request: Request) -> Layout:
    """Refuse what a run of ``request`` from ``inputs`` into ``output`` would refuse before pass one, writing
    nothing (``--plan`` given the run's OUTPUT); return its layout."""
    layout = Layout.of(inputs, output, request.output_format, request.overwrite)
    _refuse_by_name(layout, request)
    if request.per_file and not layout.directory:
        raise UsageError("--per-file needs directory mode (an output folder)")
    with _opened(layout, request) as sources:
        refuse_outputs(layout, sources, request)
        cleaned.refuse(request, sources, per_file=request.per_file)
    return layout


def rank(inputs, output: str, request: Request | None = None, column: str = "prism_rank", **options) -> Summary:
    """Write the points of ``inputs`` with their PRISM rank in ``column``: the points of rank < T are the exact
    sample for T (:mod:`..core.ranks`).

    Every point by default; ``ratio=R`` or ``count=T`` keeps only the points
    of rank < T (the sample for that target, ranked); ``order="rank"`` writes
    them in rank order (a progressive file). Exact mode only.
    """
    return sample(inputs, output, request, rank=column, **options)


def plan(inputs, request: Request | None = None, **options) -> Summary:
    """Pass one and the solve only: what a run would keep, writing nothing."""
    return sample(inputs, None, request, **options)


def execute(sources, layout: Layout, request: Request, tmp: str, inputs: list, *, t0: float,
            no_points: str = NO_POINTS, **more_provenance) -> Summary:
    """Both passes over ``sources`` into the layout's outputs, the temporary files in ``tmp``: the pipeline,
    handed the way this run reads its input (:mod:`.reads`).

    ``inputs`` are what the summary names as the inputs; ``layout.output``
    None stops after the solve. A source whose count is unknown (a query's
    result) learns it in pass one.
    """
    run = Run(request, layout, tmp, inputs, t0, no_points, more_provenance)
    if held_in_memory(sources, request):
        return run_pipeline(run, Held(sources, memory_points()))
    notice_compiling(request.progress)
    refusal = one_read_refusal(sources, request)  # a plan says how a run would read
    temp = temp_forecast(sources, layout, request, tmp)  # None only where refusal says why (a query's result)
    if layout.output is not None and temp is not None:
        if refusal is None and not temp.one_read_fits:
            refusal = temp.too_big_for_one_read()
        if refusal is not None:
            temp.refuse_two_reads()  # before pass one: the key cache would not fit either
    if refusal is None and layout.output is None:  # the run's own candidate filter: the spill it reports is the run's
        return run_pipeline(run, Spilled(sources, temp, tmp, dry=True))
    if refusal is None:
        try:
            return run_pipeline(run, Spilled(sources, temp, tmp, dry=False))
        except SpillFull as full:
            refusal = str(full) or "the spill ran out of temporary space"
            temp = temp_forecast(sources, layout, request, tmp)  # the spill's room is free again
            temp.refuse_two_reads()
            run = Run(request, layout, tmp, inputs, time.perf_counter(), no_points, more_provenance)
    return run_pipeline(run, Reread(sources, tmp, refusal, temp))


def temp_forecast(sources, layout: Layout, request: Request, tmp: str) -> TempForecast | None:
    """The run's temporary disk, from the headers (None when a source's size is unknown: a query's result)."""
    if any(s.count is None for s in sources):
        return None
    return forecast(sources, request.options, os.path.dirname(tmp), layout.output, chunk_size=request.chunk_size,
                    rank=request.rank is not None)


def memory_points() -> int:
    """Inputs of at most this many points are held in memory (``PRISM_STREAM_MEMORY_POINTS``; 0: never)."""
    value = os.environ.get("PRISM_STREAM_MEMORY_POINTS", "")
    try:
        return max(0, int(value)) if value.strip() else MEMORY_POINTS
    except ValueError:
        raise UsageError(f"PRISM_STREAM_MEMORY_POINTS must be a number of points, not {value!r}") from None


def held_in_memory(sources, request: Request) -> bool:
    """Whether this run holds its input in memory: a small input of known size, read once."""
    if request.reads == "two":
        return False
    if any(s.count is None for s in sources) or not all(getattr(s, "spills", False) for s in sources):
        return False
    limit = memory_points()
    return limit > 0 and sum(s.count for s in sources) <= limit


def _per_file_selection(selection: tuple | None, source) -> tuple | None:
    """:func:`.own_selection` as a request carries it: a --keep of none of the file's names keeps its color
    columns (so its coordinates and colors alone, as the output folder's writers do)."""
    own = own_selection(selection, source)
    if own is not None and own[0] == "keep" and not own[1]:
        names = source.arrow_schema().names
        own = "keep", tuple(c for c in color_fields(source) if c in names)
    return own


def _selection_fields(selection: tuple | None) -> dict:
    """The --keep/--drop fields of a request that applies ``selection`` ((how, names) or None)."""
    return {"keep": selection[1] if selection and selection[0] == "keep" else None,
            "drop": selection[1] if selection and selection[0] == "drop" else None}


def _per_file(layout: Layout, request: Request, selections: list) -> Summary:
    """Directory mode with an independent solve per file, each with its own --keep/--drop (``selections``:
    :func:`.own_selection`); all outputs published together."""
    t0 = time.perf_counter()
    runs = []
    one = dataclasses.replace(request, overwrite=True, per_file=False, output_format=None)
    said = []  # each file's warnings, said once every file is written (a later file's failure leaves none)
    with layout.transaction():
        for i, f in enumerate(layout.files):
            before = len(staging.published())
            try:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    runs.append(sample(f, layout.stage(i),
                                       dataclasses.replace(one, **_selection_fields(selections[i]))))
                said += caught
            except Interrupted:  # named as the file's staged output: the folder's transaction names the folder
                raise KeyboardInterrupt from None
            finally:
                staging.forget_published(before)  # staged, not published: an interrupt leaves no output
        for w in said:  # before the folder is published: a warning made an error leaves nothing
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    options = request.options
    points = sum(r.points for r in runs)
    kept = sum(r.kept for r in runs)
    for r, final in zip(runs, layout.published):
        r.output = final
        r.outputs = [final]
    return Summary(
        inputs=[remote.absolute(f) for f in layout.files], output=remote.absolute(layout.output), points=points,
        bins=None, target=(sum(r.target for r in runs) if options.k is None else None), kept=kept,
        ratio_achieved=(kept / points) if points else 0.0, rule=options.rule, k=None, extra=None,
        seed=int(options.seed), options=options.as_dict(), sources=[s for r in runs for s in r.sources],
        seconds={**{step: round(sum(r.seconds.get(step, 0.0) for r in runs), 4)
                    for step in sorted({step for r in runs for step in r.seconds} - {"total"})},
                 "total": round(time.perf_counter() - t0, 4)},  # each step summed over the files' runs
        peak_rss_bytes=peak_rss_bytes(),
        plan={"per_file": [r.as_dict() for r in runs]}, warnings=[w for r in runs for w in r.warnings],
        outputs=list(layout.published),
    )
