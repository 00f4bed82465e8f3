"""The Dask engine's driver: the core's steps, mapped over work units on a dask.distributed cluster.

Every step is one of the pure per-unit functions the local engine is built
from, so the output is the local engine's, row for row:

1. pass one: ``scan_unit_spill`` maps each unit to a sparse histogram and
   spills the points it may give the sample (whole records) to a folder in
   the output's staging folder (with ``--reads two`` or
   no output, ``scan`` counts colors only); the per-file color-depth
   decision is made from each unit's largest value (a few bytes per unit
   gathered on the driver); the histograms are summed on the cluster as the
   units finish (a tree reduce, level by level: ``RunningHistogram``) and
   only the global one reaches the driver;
2. the solve runs once on the driver; the plan is sent to every worker;
3. cutoffs: each unit keeps (from its spill's index), per capped bin, its smallest priorities at or
   under a bound the cutoff almost surely lies under (so the unit sends
   about q_b/n_b of its points, not all of them); the bottom sets are
   folded as units finish (a tree reduce, level by level) in slot-range partitions; a bin whose bound proves too low
   is redone without a bound, so the cutoffs are exact whatever happens;
4. pass two: each unit writes, from its spill, its own Parquet part (or each LAS/LAZ tile its
   own file) under a temporary name, renamed on success, so a retried task
   simply overwrites its own part; the driver then renames the staging
   folder onto the output, which appears complete or not at all.

What runs on the workers is in :mod:`.tasks`, the cutoff reduce in
:mod:`.reduce`, the cluster plumbing in :mod:`.cluster`. Workers re-open
sources from a :class:`~.tasks.UnitRef` (path, ordinal, options, record
range): nothing open is ever pickled. Inputs and the output folder
must be visible to every worker under the same paths (a shared filesystem),
or be in object storage (``s3://...``): a worker then reads the URL itself,
with the store's options beside it (:func:`.tasks.unit_refs`) and its own
credentials.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import errno
import glob
import itertools
import os
import tempfile
import time
import uuid
import warnings

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ...core.cutoffs import Rules
from ...core import space
from ...core.kernels import ID_SHIFT, seed_mix
from ...core.folding import Folding
from ...core.histogram import Histogram, RunningHistogram, UnitScan, merge_units, source_scan
from ...core.quotas import Plan
from ...errors import CorruptInput, OutputError, OutputExists, PrismError, PrismWarning, UsageError
from ...formats import WriteOptions, check_sink, extension
from ...formats.las import LasSource
from ...formats.geo import common_crs
from ...formats.columns import (check_selection_apart, column_notes, common_schema, own_selection,
                                read_only_kept, select_columns)
from ...formats.parquet import output_schema
from ...run import remote, staging
from ...run.inputs import expand_inputs, open_sources, warn_read_again
from ...run.outputs import Commit, output_stem, refuse_one_more_tile
from ...run.progress import say
from ...run.request import Request
from ...run.spill import spill_refusal
from ...run.summary import Summary, provenance
from ...run.tempspace import forecast
from .. import spatial
from ..spatial_disk import DiskScan, order_in_parts
from ..pipeline import Reads, Run, run_pipeline
from ..ranking import rank_points
from .cluster import (FAN_IN, connect, gather, gather_settled, held, large_graphs, settled, wait_unstalled,
                      window, windowed)
from .reduce import BOTTOMS_PER_REDUCER, BOUND_SIGMAS, cutoffs as reduce_cutoffs
from .tasks import (PART_PREFIX, histogram_of, merge_histograms, merge_prior, part_name, scan_unit,
                    scan_unit_reread, scan_unit_spill, select_part, select_tile, sparse_histogram, unit_facts,
                    unit_kept, unit_refs, fold_scans, unit_space, worker_plan, Writing, InFile, SPACE_TASKS,
                    beside_output)

DEFAULT_UNIT = 1 << 22
PRIOR_GROWTH = 0.25  # a new prior merge once the units done since the last add this share of its points
# A one-read run whose units show more colors than this (estimated_bins, from each finished unit's points and
# bins) reads its later units twice: the priors that make one read pay over such a cloud (27-30 bytes a bin,
# two of them alive while merges run, the units' results waiting for the next) and a unit's own filter do
# not fit a worker in 1 GiB. 100M points over 15.9M bins on local:2: worker peaks 1.9-2.3 GiB one read,
# 0.9 GiB two reads (bench/RESULTS_SCALE.md, "Dask over 2^24 bins").
PRIOR_BINS = 1 << 20
SPACE_GROUP = 8  # a spatial-share task scans at least this many times the cells a scan may hold (respace)
PRIOR_EVIDENCE = 1 << 16  # bins a unit must show before its estimate is believed (a small unit's is a guess)


def _output_layout(output: str) -> tuple[str, str | None]:
    """(folder, tile extension): ``out/`` or ``out.parquet`` is a Parquet dataset, ``out/*.laz`` one LAZ a tile."""
    base = os.path.basename(output.rstrip("/"))
    if base in ("*.las", "*.laz", "*.copc.laz"):
        return os.path.dirname(output.rstrip("/")) or ".", base[1:]
    if "*" in output:
        raise UsageError("an output pattern must be FOLDER/*.las, FOLDER/*.laz or FOLDER/*.copc.laz", output)
    ext = extension(output)
    if ext in (".las", ".laz", ".copc.laz"):
        raise UsageError(f"the Dask engine writes one file per input tile: give FOLDER/*{ext}", output)
    if ext not in ("", ".parquet", ".pq"):
        raise UsageError(f"the Dask engine writes a Parquet dataset folder or FOLDER/*.laz, not {ext!r}", output)
    return output.rstrip("/") or ".", None


def check_output(files: list[str], output, overwrite: bool) -> tuple[str, str | None]:
    """(folder, tile extension) of ``output``, refused as a run refuses it: a store, a folder holding an
    input, one that exists (without ``overwrite``), one whose parent is missing."""
    if remote.is_remote(output):
        raise UsageError("the Dask engine writes its dataset to a folder every worker sees, not to a store; "
                         "give a local or shared folder", os.fspath(output))
    folder, tiles = _output_layout(os.fspath(output))
    real = os.path.realpath(folder)
    if any(os.path.realpath(f) == real or os.path.realpath(f).startswith(real + os.sep) for f in files):
        raise UsageError("the output folder would overwrite or hold an input", folder)
    refuse_one_more_tile(folder, files)  # tiles/*.parquet with no output: the last tile would become a folder
    if os.path.lexists(folder) and not overwrite:
        raise OutputExists.at_start(folder)
    if not os.path.isdir(os.path.dirname(os.path.abspath(folder))):
        raise OutputError("output folder's parent does not exist", folder)
    return folder, tiles


def _tile_names(files: list[str], ext: str) -> list[str]:
    names = [output_stem(os.path.basename(f)) + ext for f in files]
    seen = {}
    for f, n in zip(files, names):
        if n in seen:
            raise UsageError(f"two inputs would both write {n} (also {seen[n]}); rename one or write Parquet", f)
        seen[n] = f
    return names


def sample_at(address: str, inputs, output=None, request: Request | None = None, **options) -> Summary:
    """:func:`sample` on the cluster at ``address`` (``tcp://...`` or ``local:N``)."""
    with connect(address) as client:
        return sample(client, inputs, output, request, **options)


def on_cluster(address: str):
    """``prism_stream.sample``'s call shape, run on the cluster at ``address`` (what the CLI's --dask calls)."""

    def run(inputs, output=None, request: Request | None = None, **options):
        return sample_at(address, inputs, output, request, **options)

    return run


def sample(client, inputs, output: str | None = None, request: Request | None = None, *,
           unit_size: int = DEFAULT_UNIT, bound_sigmas: float = BOUND_SIGMAS,
           bottoms_per_reducer: int = BOTTOMS_PER_REDUCER, **options) -> Summary:
    """Sample ``inputs`` into ``output`` with PRISM on a Dask cluster; the rows are the local engine's.

    Parameters
    ----------
    client : dask.distributed.Client
        The cluster to run on. Inputs must be visible to every worker under
        the same paths, or be URLs (``s3://...``) every worker can read; the
        output folder must be visible to every worker.
    inputs : str or list of str
        Files, globs or Parquet directories, as for :func:`prism_stream.sample`.
    output : str or None
        ``FOLDER`` or ``FOLDER.parquet``: a Parquet dataset folder, one part
        per work unit that keeps points (``part-<source>-<first record>.parquet``,
        in input order). ``FOLDER/*.laz`` (or ``*.las``, ``*.copc.laz``): one
        file per input tile, named after it. None: pass one and the solve only.
    request, **options
        As for :func:`prism_stream.sample`; ``threads`` (default 1) are each
        task's decoder threads. ``flag``, ``output_format`` and ``per_file``
        are the local engine's only; ``progress`` is accepted and unused;
        ``temp_dir`` is where the driver ranks (``rank``); the units' spills
        are in the output's staging folder, which every worker sees.
    unit_size : int
        Points per work unit (LAZ: rounded to whole chunks; Parquet: one row
        group a unit). The output does not depend on it.
    bound_sigmas, bottoms_per_reducer
        Tuning of the cutoff reduce (see :func:`.reduce.cutoff_bounds`); the
        output does not depend on them.
    """
    request = Request.of(request, **options)
    for name, value in (("--flag", request.flag), ("--format", request.output_format),
                        ("--per-file", request.per_file or None), ("--scale", request.scale)):
        if value is not None:
            raise UsageError(f"{name} is not available with --dask (it writes a Parquet dataset or FOLDER/*.laz, "
                             "whose tiles keep their LAS inputs' own point formats and grids)")
    if request.options.denoise is not None:
        from ..cleaned import flag

        raise UsageError(f"{flag(request)} is not available with --dask: the outlier removal reads the whole cloud "
                         "on this machine (sample without --dask, or remove the outliers first)")
    if request.order != "input":
        raise UsageError("--order rank is not available with --dask: its parts are written in input order "
                         "(sort the dataset by prism_rank, or rank without --dask)")
    if unit_size < 1:
        raise UsageError(f"unit_size must be positive, not {unit_size}")
    # absolute: the workers of an existing scheduler run in folders of their own (a shared file system
    # reaches the inputs by the same absolute paths), so a path relative to this process names nothing there
    files = [remote.absolute(f) for f in expand_inputs(inputs)]
    layout = Dataset(files, output, request.overwrite)
    warn_read_again(inputs, output)
    open_options = tuple(sorted({"threads": int(request.threads or 1), "rgb_columns": request.rgb_columns}.items()))
    t0 = time.perf_counter()
    sources = open_sources(files, **dict(open_options), copies_to=None, refuse_copies="a cluster's workers "
                           "cannot share one local copy; put the file in a store (s3://, gs://, az://) or serve it "
                           "with range requests")
    try:
        temp = request.temp_dir or tempfile.gettempdir()
        if layout.output is not None and all(s.count is not None for s in sources):  # before pass one
            spatial.check_cluster_room(request.options, sum(s.count for s in sources), temp, layout.output)
        spatial.check_coordinates(request.options, sources)
        with layout.transaction(), contextlib.ExitStack() as stack:
            if layout.tiles is not None:
                refuse_tiles(sources, request.geometry)
            layout.refuse_selection(sources, request.selection, request.columns)
            read_only_kept(sources, request.selection)  # each unit carries its source's columns to decode
            cluster = OnCluster(client, sources, layout, request, open_options,
                                Tuning(unit_size, bound_sigmas, bottoms_per_reducer))
            # the driver's folder for a spatial share's scan and merge on disk (a large target's)
            tmp = stack.enter_context(staging.work_dir(temp)) if request.options.space is not None else None
            return run_pipeline(Run(request, layout, tmp, list(files), t0), cluster)
    finally:
        for s in sources:
            s.close()


def _apart(sources) -> str:
    """How a Dask run's inputs can be written apart, as a refusal suggests it: its Parquet output is one
    dataset of one schema, and its tiles (FOLDER/*.laz) take LAS/LAZ inputs alone."""
    if sources and all(isinstance(s, LasSource) for s in sources):
        return "FOLDER/*.laz: one tile per input"
    return "an output folder in a run without --dask: one output per input"


def refuse_tiles(sources, geometry: bool) -> None:
    """What a Dask run's tiles (FOLDER/*.las, *.laz, *.copc.laz) cannot hold, refused before pass one."""
    if geometry:
        raise UsageError("--geometry adds a GeoParquet geometry column: it needs Parquet output")
    for s in sources:
        if not isinstance(s, LasSource):
            raise UsageError("LAS/LAZ output needs LAS/LAZ inputs; write Parquet instead", s.path)


class Dataset(Commit):
    """The Dask engine's output: a Parquet dataset folder (one part a unit) or a folder of tiles (one a
    file), staged in a hidden folder beside it (which also holds the units' spills) and renamed onto it whole:
    the pipeline's commit, as :class:`...run.outputs.Layout` is the local engine's."""

    def __init__(self, files: list[str], output, overwrite: bool):
        self.files = files
        self.given = output  # as the user gave it
        self.overwrite = overwrite
        self.output = self.tiles = None
        if output is not None:
            self.output, self.tiles = check_output(files, output, overwrite)
        self.staging = None
        self.schema = None  # the parts' schema (an empty dataset gets one empty part of it)
        self.published: list[str] = []  # the summary's outputs: the files of the dataset or tiles, once renamed
        self.done = False  # the staging folder renamed onto the output

    @property
    def named(self):
        return self.given

    def tile_names(self) -> list[str]:
        return _tile_names(self.files, self.tiles)

    def refuse_selection(self, sources, selection, columns) -> None:
        """--columns and --keep/--drop refused before pass one, as the local run refuses them."""
        common = common_schema(sources, columns, _apart(sources))[0] if self.output is not None \
            and self.tiles is None else None
        if self.output is None or selection is None:
            return
        if self.tiles is None:
            select_columns(common, sources, selection, sources[0].path)
        else:  # each tile its own layout: the names it has, and what its writer refuses of them
            check_selection_apart(selection, sources)
            for s, name in zip(sources, self.tile_names()):
                check_sink(os.path.join(self.output, name), [s], WriteOptions(selection=own_selection(selection, s)))

    def begin(self) -> str:
        """The staging folder beside the output (created once)."""
        if self.staging is None:
            self.staging = staging.temp_folder(self.output)
        return self.staging

    def publish(self) -> None:
        """Rename the staging folder onto the output (:func:`_commit`), once."""
        if self.staging is not None:
            _commit(self.staging, self.output, self.tiles, self.schema, self.overwrite)
            self.done = True
            # the summary's outputs: every file written, the dataset's parts or the tiles
            self.published = sorted(os.path.join(self.output, n) for n in os.listdir(self.output)
                                    if not n.startswith((".", "_")))
            staging.note_published(self.named)
            self.staging = None

    def complete(self) -> bool:
        return self.done

    def tidy(self) -> None:
        self.staging = None  # renamed: nothing of it is left beside the output

    def discard(self) -> None:
        if self.staging is not None:
            staging.remove(self.staging)
            self.staging = None


@dataclasses.dataclass(frozen=True)
class Tuning:
    """How the work is cut and reduced on the cluster; the output does not depend on it."""

    unit_size: int = DEFAULT_UNIT  # points per work unit
    bound_sigmas: float = BOUND_SIGMAS  # the cutoff reduce's bounds (:func:`.reduce.cutoff_bounds`)
    bottoms_per_reducer: int = BOTTOMS_PER_REDUCER  # (slot, priority) pairs a cutoff reducer holds at most


class UnitRanks:
    """Each unit's kept points' ranks, sent with its pass-two task."""

    def __init__(self, column: str, order: str, per_unit: list):
        self.column = column
        self.order = order
        self.per_unit = per_unit

    def facts(self) -> dict:
        return {"column": self.column, "order": self.order}


class OnCluster(Reads):
    """The pipeline's steps mapped over the work units of a Dask cluster (the module docstring)."""

    commit_step = "commit"

    def __init__(self, client, sources, layout: Dataset, request: Request, open_options: tuple, tuning: Tuning):
        self.client = client
        self.sources = sources
        self.layout = layout
        self.request = request
        self.tuning = tuning
        self.key = uuid.uuid4().hex[:10]  # this run's task keys
        self.stats: dict = {"workers": len(client.scheduler_info().get("workers", {}))}
        self.refs = [r for s in sources for r in unit_refs(s, tuning.unit_size, open_options)]
        self.chunk_size = request.chunk_size
        self.stats["units"] = len(self.refs)
        self.refusal = _one_read_refusal(layout.output, request, sources)
        self.spills = None
        self.unit_spills = [None] * len(self.refs)
        self.spaced = None  # --space: the sample's ids and places (:meth:`respace`)

    def scan(self, run: Run) -> tuple:
        """Pass one: unit histograms, the depth decisions, their sum on the cluster. With an output, each
        unit also spills the points it may give the sample (its records, in the staging folder beside the
        output), so the cutoffs and pass two read the spills, not the input (:func:`.tasks.scan_unit_spill`)."""
        client, refs, options, key = self.client, self.refs, run.options, self.key
        chunk_size = run.request.chunk_size
        stage = self.layout.begin() if self.layout.output is not None else None
        if self.refusal is None:  # the units spill into the staging folder, beside the output: both on its disk
            temp = forecast(self.sources, options, stage, stage, chunk_size=chunk_size)
            self.stats["temp"] = temp.as_dict()
            if not temp.one_read_fits:
                self.refusal = temp.too_big_for_one_read()
        counter = itertools.count()

        def submit(func, *args):
            return client.submit(func, *args, key=f"prism-hsum-{key}-{next(counter)}")

        units_of = collections.Counter(r.ordinal for r in refs)
        running = RunningHistogram(submit, merge_histograms, units_of, options.color_depth)
        if self.refusal is None:
            self.spills = os.path.join(stage, ".spill")
            with _staging(self.layout.output, "the units' spills"):
                os.mkdir(self.spills)
            facts = self._scan_spilling(options, max(0, temp.budget), running)
        else:
            facts = self._scan_reading(options, running)
        stubs = [UnitScan(o, p, m, kind, Histogram.empty()) for o, p, m, kind in facts]
        _, decisions = merge_units(stubs, options.color_depth)
        seen, largest = collections.Counter(), {}  # points, largest value, by file
        for o, p, m, _ in facts:
            seen[o] += p
            largest[o] = max(largest.get(o, 0), m)
        for s in self.sources:
            if seen.get(s.ordinal, 0) != s.count:
                raise CorruptInput(f"header declares {s.count} points but {seen.get(s.ordinal, 0)} could be read",
                                   s.path)
        self.merged = running.total()
        return tuple(source_scan(s, s.count, decisions[s.ordinal], largest.get(s.ordinal, 0)).as_dict()
                     for s in self.sources)

    def histogram(self) -> Histogram:
        histogram = gather(self.client, self.client.submit(sparse_histogram, self.merged,
                                                           key=f"prism-hsparse-{self.key}"))
        self.merged = None
        self.stats["histogram_bytes"] = int(histogram.keys.nbytes + histogram.counts.nbytes)
        return histogram

    def solved(self, run: Run, plan: Plan) -> None:
        if self.spills is not None:
            self.unit_spills = _drop_partial_spills(self.refs, self.unit_spills, plan)

    def facts(self, run: Run, plan: Plan) -> dict:
        return {"dask": self.stats, **_reads(self.refusal, self.unit_spills)}

    def select(self, run: Run, plan: Plan, rules=None) -> None:
        """The plan's scalars and its rules' parts to every worker (in the graph, so the scheduler can make
        them again if a worker holding them dies), the cutoffs reduced on the cluster."""
        client, key = self.client, self.key
        rules = Rules(plan)
        parts = rules.parts()
        self.stats["plan_full_json_bytes"] = plan.json_length()  # what the plan's JSON would be (not made)
        self.stats["plan_rules_bytes"] = sum(int(a.nbytes) for a in parts)
        with large_graphs():  # the rules' parts in the graph, so that the scheduler can make the plan again
            self.plan_f = client.submit(worker_plan, plan.without_bins(), *parts, key=f"prism-plan-{key}")
        del parts
        client.replicate([self.plan_f])  # made again from the graph if every worker holding it dies
        cutoffs = reduce_cutoffs(self, plan, rules, self.plan_f)
        self.stats["cutoffs_bytes"] = int(cutoffs.keys.nbytes + cutoffs.cut.nbytes)
        self.cutoffs_f = held(client, cutoffs, f"prism-cutoffs-{key}")

    def _kept(self, run: Run, counts: list):
        """``kept()`` for the ranks and the spatial share: each unit's kept points (keys and ids, input order)
        gathered unit by unit in unit order (each let go once yielded), their counts appended to ``counts``. The
        units are submitted a window ahead of the one gathered (:func:`.cluster.window`), not
        all at once: a run of many small units holds a window of results, not one for each."""
        client, refs, spills = self.client, self.refs, self.unit_spills

        def submit(i):
            return client.submit(unit_kept, refs[i], spills[i], plan=self.plan_f, cutoffs=self.cutoffs_f,
                                 chunk_size=run.request.chunk_size, key=f"prism-kept-{self.key}-{i}")

        def kept():
            ahead: collections.deque = collections.deque()
            fed, most = 0, window(client)
            while fed < len(refs) or ahead:
                while fed < len(refs) and len(ahead) < most:
                    ahead.append(submit(fed))
                    fed += 1
                keys, ids = gather(client, ahead.popleft())
                counts.append(len(keys))
                yield keys, ids

        return kept

    def ranks(self, run: Run, plan: Plan) -> UnitRanks:
        """Each unit's kept points (keys and ids) to the driver, ranked there as the local engine ranks them
        (numpy, or DuckDB spilling to the temporary folder), sent back with pass two."""
        counts: list = []
        kept = self._kept(run, counts)
        with staging.work_dir(run.request.temp_dir) as tmp:
            ranks = rank_points(plan, dataclasses.replace(run, tmp=tmp), kept)
            return UnitRanks(ranks.column, ranks.order, [ranks.next(n).copy() for n in counts])

    def respace(self, run: Run, plan: Plan, rarity: spatial.Rarity) -> spatial.Spaced:
        """The spatial share (SPEC 9): groups of consecutive units scan their points on the cluster
        (:func:`.tasks.unit_space`), the scans are folded on the cluster as they finish (:class:`.Folding`,
        ``FAN_IN`` at a time: any grouping and order gives the same scan), a bounded number of groups in
        flight so that finished scans do not wait in the workers' memory; the driver merges the spatial order
        with PRISM's, from each unit's kept points, and pass two writes each unit's ids of the merge.

        A scan holds up to ``2 T + 1`` cells whatever its points, and a fold costs about as much per cell as
        the scan per point, so a group scans at least :data:`SPACE_GROUP` times that many points: the folds
        then take a small part of the time (100M points at T = 500,000 in units of 1M: 135 s in the spatial
        step with a scan a unit, most of it folding).

        A target whose cells do not fit in :data:`.spatial.BUDGET` (``space.on_disk``): each group's scan
        tracks at most :func:`.spatial.disk_cap` cells and writes its points to a file in the staging folder
        (``.space``, beside the output: every worker and the driver see it). The points are then sorted
        out by their cells there by tasks on the cluster, each group's file routed, each routed file visited
        and its births listed in sorted runs (:func:`.spatial_disk.order_in_parts`); the driver merges the
        runs into the order and that with PRISM's in its temporary folder (:mod:`.spatial_merge`), as the
        local engine does: the same order, bit for bit."""
        client, key, t = self.client, self.key, int(plan.target)
        on_disk = space.on_disk(t)
        cap = spatial.disk_cap(t) if on_disk else 2 * t + 1
        per = SPACE_GROUP * cap
        if on_disk:  # a group's scan is capped whatever its points: a group at least a worker thread; two with a
            # small scan (past CAP), whose folds cost little and whose points are routed below its level anyway
            n, threads = sum(r.points for r in self.refs), max(1, sum(client.nthreads().values()))
            per = min(per, -(-n // threads)) if cap == spatial.CAP else -(-n // (2 * threads))
        refs = _groups(self.refs, per)
        parts = None
        if on_disk:
            # again: the free space may have changed since pass one
            spatial.check_cluster_room(run.options, int(plan.points), os.path.dirname(run.tmp), self.layout.output)
            parts = os.path.join(self.layout.begin(), ".space")
            with _staging(self.layout.output, "the spatial share's files"):
                os.mkdir(parts)
        folds = itertools.count()
        folding = Folding(lambda *scans: client.submit(fold_scans, t, *scans, key=f"prism-sfold-{key}-{next(folds)}"),
                          FAN_IN)

        def finished(_, f) -> None:
            if f.status == "error":
                gather(client, f)  # its error now (a file's non-finite coordinates), not after every group
            folding.add(f)

        def submit(i):
            disk = None if parts is None else (os.path.join(parts, f"points-{i:06d}"), cap)
            return client.submit(unit_space, refs[i], self.plan_f, rarity, run.request.chunk_size, disk,
                                 key=f"prism-space-{key}-{i}")

        started = time.perf_counter()
        windowed(client, len(refs), submit, finished)
        result = folding.result(fold_one=True)
        folding = None  # the scans it held go once the last fold has read them
        scan = gather(client, result)
        del result
        say(f"spatial share: {len(refs):,} groups of units scanned and folded, {time.perf_counter() - started:.1f} s")
        if parts is None:
            order = scan.order(plan.seed)  # the folded scan goes with this line
            del scan
            self.spaced = spatial.spaced(plan, order, self._kept(run, []))
            return self.spaced
        paths = [os.path.join(parts, f"points-{i:06d}") for i in range(len(refs))]
        disk = DiskScan.of_parts(scan, paths, run.tmp, rarity, seed_mix(plan.seed), cap)
        del scan
        steps = itertools.count()

        def run_tasks(fn, jobs: list) -> list:  # the files' work on the cluster, each step's tasks all at once
            step = next(steps)  # a failed task's others end before the driver removes their folder
            return gather_settled(client, [client.submit(SPACE_TASKS[fn.__name__], *args,
                                                         key=f"prism-sdisk-{key}-{step}-{i}")
                                           for i, args in enumerate(jobs)])

        order = staging.ArrayFile(run.tmp, "space.order", np.uint64)
        try:
            order_in_parts(disk, plan.seed, t, order, run_tasks)
        except BaseException:
            order.discard()
            raise
        finally:
            staging.remove(parts)
        written, routed = disk.written, disk.routed
        del disk
        started = time.perf_counter()
        self.spaced = spatial.spaced(plan, order, self._kept(run, []))
        self.spaced.on_disk, self.spaced.routed = written, routed
        say(f"spatial share: merged with PRISM's order, {time.perf_counter() - started:.1f} s")
        return self.spaced

    def _unit_ranges(self) -> list[tuple[int, int]]:
        """Where each unit's ids lie in the spatial share's (ascending) ids: an array, or a file read a block
        at a time (the units' ids are ascending and apart)."""
        ids = self.spaced.ids
        bounds = np.array([(r.ordinal << ID_SHIFT) | r.start for r in self.refs]
                          + [((r.ordinal << ID_SHIFT) | r.start) + r.points for r in self.refs], np.uint64)
        if isinstance(ids, staging.ArrayFile):
            at = np.zeros(len(bounds), np.int64)
            for a in range(0, ids.size, spatial.IdSelector.BLOCK):
                at += np.searchsorted(ids.read(a, min(spatial.IdSelector.BLOCK, ids.size - a)), bounds)
        else:
            at = np.searchsorted(ids, bounds)
        n = len(self.refs)
        return [(int(at[i]), int(at[n + i])) for i in range(n)]

    def _tile_files(self, stage: str, tile: int, a: int, b: int, ranked: bool) -> tuple:
        """A tile's sample (the spatial share's ids ``a`` to ``b``, and their places with ``ranked``) copied a
        block at a time from the driver's temporary files to ``.keep`` in the staging folder, which its task
        reads: (the ids' :class:`.tasks.InFile`, the ranks' or None)."""
        out = []
        for values, dtype, suffix in ((self.spaced.ids, "<u8", "ids"), (self.spaced.places, "<i8", "ranks")):
            if suffix == "ranks" and not ranked:
                out.append(None)
                continue
            path = os.path.join(stage, ".keep", f"tile-{tile:06d}.{suffix}")
            with open(path, "wb") as f:
                step = spatial.IdSelector.BLOCK
                for at in range(a, b, step):
                    f.write(np.ascontiguousarray(values.read(at, min(step, b - at)), dtype).tobytes())
            out.append(InFile(path, dtype))
        return tuple(out)

    def write(self, run: Run, plan: Plan, ranks: UnitRanks | None) -> list[str]:
        """Pass two: parts or tiles in the staging folder, then the folder renamed onto the output. Each
        tile's notes are warned once it is published, and returned for the summary's warnings (as the local
        run's outputs' notes are)."""
        client, refs, request, key = self.client, self.refs, run.request, self.key
        layout, sources = self.layout, self.sources
        folder, stage, chunk_size = layout.output, layout.staging, request.chunk_size
        # what each unit keeps: the plan's cutoffs, or the spatial share's ids (its ranks: their places)
        keep, unit_ranks = (lambda i: self.cutoffs_f), (lambda i: None)
        if self.spaced is not None:  # read for a unit as its task is sent (a file's: a window of units held)
            at = self._unit_ranges()
            keep = lambda i: spatial.IdSelector(_between(self.spaced.ids, *at[i]))  # noqa: E731
            if ranks is not None:
                unit_ranks = lambda i: _between(self.spaced.places, *at[i])  # noqa: E731
        elif ranks is not None:
            unit_ranks = ranks.per_unit.__getitem__
        more = {} if ranks is None else {"rank": {"column": ranks.column, "order": ranks.order}}  # the local runs'
        prov = provenance(plan, layout.files, request.command, **more)
        schema = None
        if layout.tiles is None:
            # the local Parquet sink's, provenance included
            schema = output_schema(sources, prov, geometry=request.geometry, columns=request.columns,
                                   selection=request.selection)
            for text in column_notes(sources, request.columns, schema):
                warnings.warn(f"{folder}: {text}", PrismWarning, stacklevel=2)
            _, why = common_crs(sources)  # the parts' schema holds no CRS then: said, as the local engine says it
            if why:
                warnings.warn(f"{folder}: {why}", PrismWarning, stacklevel=2)
            if request.rank is not None:
                schema = schema.append(pa.field(request.rank, pa.int64()))
            writing = Writing(stage, prov, chunk_size, request.rank, schema)
            count = len(refs)

            def job(i):
                return client.submit(select_part, refs[i], self.plan_f, keep(i), writing, unit_ranks(i),
                                     self.unit_spills[i], key=f"prism-select-{key}-{i}")
        else:
            refuse_tiles(sources, request.geometry)
            names = layout.tile_names()
            by_tile = [[i for i, r in enumerate(refs) if r.ordinal == s.ordinal] for s in sources]
            writing = Writing(stage, prov, chunk_size, request.rank)
            count = len(by_tile)

            on_disk = self.spaced is not None and isinstance(self.spaced.ids, staging.ArrayFile)
            if on_disk:  # a tile's sample may be most of a large target: its ids (and ranks) go in files beside
                with _staging(folder, "a tile's sample"):  # the output, which its task reads a block at a time
                    os.mkdir(os.path.join(stage, ".keep"))

            def job(i):
                group = by_tile[i]
                if on_disk:
                    with _staging(folder, "a tile's sample"):
                        tile_keep, tile_ranks = self._tile_files(stage, i, at[group[0]][0], at[group[-1]][1],
                                                                 ranks is not None)
                else:
                    tile_keep = _tile_keep([keep(u) for u in group])
                    tile_ranks = _joined([unit_ranks(u) for u in group])
                return client.submit(select_tile, [refs[u] for u in group], self.plan_f, tile_keep, writing,
                                     (names[i], own_selection(request.selection, sources[i])), tile_ranks,
                                     [self.unit_spills[u] for u in group], key=f"prism-select-{key}-{i}")
        # a window of jobs at a time (as pass one's scans): a cluster of many units (341,989 of a COPC file at
        # --unit-size 1) is not handed every task, its ids and ranks at once; each result is read as it comes
        results: list = [None] * count

        def finished(i, f):
            results[i] = gather(client, f)  # a failed part's error now, not after every part

        try:
            windowed(client, count, job, finished)
        except PrismError as error:
            _named_in_output(error, stage, folder, layout.files)
            raise
        noted = []  # each tile's notes (attributes its writer changed or left out), said once it is published
        if layout.tiles is not None:
            noted = [f"{os.path.join(folder, name)}: {text}" for name, (_, texts) in zip(names, results)
                     for text in texts]
            results = [w for w, _ in results]
        written = sum(results)
        self.plan_f = self.cutoffs_f = None
        if written != plan.kept:
            raise AssertionError(f"wrote {written} points, the plan keeps {plan.kept}")
        if self.spills is not None:
            staging.remove(self.spills)  # what a straggling attempt holds open goes with the stage
        staging.remove(os.path.join(stage, ".keep"))  # the tiles' ids, if a spatial share's past the budget
        layout.schema = schema
        self.noted = noted
        return list(noted)  # in the summary's warnings, as the local run's outputs' notes are

    def _unit_done(self, i: int, future, running: RunningHistogram, facts: list, report):
        """A unit finished: its facts to the driver, its histogram to the running sum (on the worker that
        holds it); returns what ``report`` (a task: (something, the unit's facts)) gave beside the facts."""
        extra, facts[i] = gather(self.client, self.client.submit(report, future, key=f"prism-facts-{self.key}-{i}"))
        running.unit_done(*facts[i], self.client.submit(histogram_of, future, key=f"prism-hist-{self.key}-{i}"))
        return extra

    def _scan_reading(self, options, running: RunningHistogram) -> list:
        """Pass one without a spill (two reads): each unit's histogram to the running sum as it finishes, its
        scan let go once its facts are gathered (a unit's scan is a histogram alone: the workers hold those
        of the units finished and not yet reached by the driver's loop, not every unit's until the end).
        Returns each unit's facts (ordinal, points, max, kind). The units are fed a window at a time
        (:func:`.cluster.windowed`): a run of many small units never holds a task for each on the driver."""
        client, refs, key = self.client, self.refs, self.key
        facts = [None] * len(refs)

        def submit(i):
            return client.submit(scan_unit, refs[i], spec=options.spec, color_depth=options.color_depth,
                                 chunk_size=self.chunk_size, key=f"prism-scan-{key}-{i}")

        windowed(client, len(refs), submit,
                 lambda i, f: self._unit_done(i, f, running, facts, report=_facts_of_scan))
        return facts

    def _scan_spilling(self, options, budget: int, running: RunningHistogram) -> list:
        """Pass one of the one-read path: each unit's facts (ordinal, points, max, kind) returned, its
        :class:`.tasks.UnitSpill` in ``self.unit_spills``, its histogram summed into ``running``.

        A unit's bound comes from the counts it sees, so each unit also gets the counts of the units
        finished before it starts (its prior): the first wave spills with its own counts alone, the later
        ones with much of the cloud's (the newest merge that is done: a unit waits only for the first). Units are
        fed as threads free up, one in flight per worker thread of the cluster at that moment (an adaptive
        cluster that grows gets more). Only final counts go in a prior: a unit that saw no value above 255 in
        16-bit channels (``auto``) may yet move to key 0, so its counts wait until every unit of its file is
        done and none saw one. The output does not depend on the priors, only the spill's size does.

        The units' spills together never take more than ``budget`` (the staging disk's free space at the start,
        less the output and a reserve): a unit starts with an equal part of what is not yet spoken for (the
        spills of the units done, and the parts of the units in flight) among the threads free to start one.
        A part by points (budget x its points / N) was too small for the first wave, which has no prior and
        spills most of its points: at a billion points and 30 GB free, 32 of 255 units ran out of room and
        were read again while the spills took 3.5 GB.

        What the cluster holds stays bounded whatever the number of units: a unit's result (its histogram,
        bounds and evidence: megabytes) is let go once its counts are in a prior's merge, or once no unit is
        left to start. Until then the results waiting for a prior (the units done since the last merge, and
        the units of a file not yet decided) are folded ``FAN_IN`` at a time, level by level, with no loss
        (``merge_prior(..., fold=True)``: the prior made of the folds is the one made of the results), so
        what waits is a few folds however many units a merge waits for.
        """
        client, refs, chunk_size, spills, run, stats = self.client, self.refs, self.chunk_size, self.spills, self.key, \
            self.stats
        declared = sum(s.count for s in self.sources)
        facts = [None] * len(refs)
        unit_spills = [None] * len(refs)
        left = collections.Counter(r.ordinal for r in refs)  # ordinal -> units of the file not done yet
        undecided: dict = {}  # ordinal -> [a Folding of the results of done units of the file that looked 8-bit,
        #                                   their points]
        sixteen = set()  # files a unit proved 16-bit
        prior = None  # the newest merge of the priors (it may still be running)
        merges = []  # the merges not yet known to be done, oldest first (each holds the ones before it)
        pending_points = 0  # the points of the results waiting for a prior (``pending``, below)
        in_prior = 0  # points of the units in the merges submitted
        ready = None  # the newest merge known to be done: what a unit starts with, never waiting for a merge
        given = 0  # units that started with a prior
        flying: dict = {}  # future key -> (unit, future), the units in flight
        fed = 0
        merged = itertools.count()
        stats["prior_merges"] = 0
        allotted: dict = {}  # unit in flight -> the bytes it may spill
        spoken = 0  # bytes the finished units' spills hold, and the parts of the units in flight

        def fold(*handles):
            return client.submit(merge_prior, *handles, fold=True, key=f"prism-fold-{run}-{next(merged)}")

        pending = Folding(fold, FAN_IN)  # results of units done with final counts, not yet in a merge

        switched = None  # the estimated bins once a unit showed more than PRIOR_BINS: later units read twice

        def top_up():
            nonlocal fed, given, ready, spoken
            done = [i for i, m in enumerate(merges) if m.done()]
            if done:
                ready = merges[done[-1]]
                del merges[:done[-1] + 1]
            threads = max(1, sum(client.nthreads().values()))
            while switched is not None and fed < len(refs) and len(flying) < threads:
                allotted[fed] = 0
                f = client.submit(scan_unit_reread, refs[fed], options, chunk_size, key=f"prism-scans-{run}-{fed}")
                flying[f.key] = (fed, f)
                fed += 1
            while fed < len(refs) and len(flying) < threads:
                start = ready if ready is not None else prior  # until a first merge is done, wait for it
                given += start is not None
                allotted[fed] = share = max(0, budget - spoken) // (threads - len(flying))
                spoken += share
                f = client.submit(scan_unit_spill, refs[fed], options, declared, chunk_size, spills, start, share,
                                  key=f"prism-scans-{run}-{fed}")
                flying[f.key] = (fed, f)
                fed += 1

        with settled(client, lambda: [f for _, f in flying.values()]):  # no unit spills after the stage goes
            top_up()
            while flying:
                done, _ = wait_unstalled(client, [f for _, f in flying.values()], "FIRST_COMPLETED")
                for f in done:
                    i, _ = flying.pop(f.key)
                    unit_spills[i] = self._unit_done(i, f, running, facts, report=_report_of_spill)
                    spoken += (unit_spills[i].bytes if unit_spills[i].folder is not None else 0) - allotted.pop(i)
                    ordinal = refs[i].ordinal
                    left[ordinal] -= 1
                    if switched is None and unit_spills[i].bins >= PRIOR_EVIDENCE:
                        estimate = min(estimated_bins(facts[i][1], unit_spills[i].bins), options.spec.key_space)
                        if estimate > PRIOR_BINS:
                            switched = estimate
                            stats["bins_estimated"] = int(estimate)
                    if switched is not None:
                        continue  # no prior will be made: the waiting results are let go below
                    if not unit_spills[i].final:  # 8-bit-looking so far: another unit may move it to key 0
                        if ordinal not in sixteen:
                            waiting = undecided.setdefault(ordinal, [Folding(fold, FAN_IN), 0])
                            waiting[0].add(f)
                            waiting[1] += facts[i][1]
                    else:
                        pending.add(f)
                        pending_points += facts[i][1]
                        if unit_spills[i].decision == "16":
                            sixteen.add(ordinal)
                            undecided.pop(ordinal, None)  # its 8-bit-looking units go to key 0: no prior takes them
                    if not left[ordinal] and ordinal in undecided and ordinal not in sixteen:
                        parts, points = undecided.pop(ordinal)  # the file is 8-bit: its units' counts are final
                        pending.add(parts.result())
                        pending_points += points
                if fed == len(refs) or switched is not None:  # no unit left to start with a prior: none is needed
                    pending, prior, ready, merges = Folding(fold, FAN_IN), None, None, []
                    undecided.clear()
                elif len(pending) and all(m.done() for m in merges) and pending_points >= PRIOR_GROWTH * in_prior:
                    # one merge in flight at a time, and only once the units done since the last one add a share
                    # of what the prior holds: a merge re-sorts the whole prior's evidence (a fraction of a second
                    # a merge), so merging at every unit cost a fifth of pass one
                    prior = client.submit(merge_prior, prior, *pending.held(), key=f"prism-prior-{run}-{next(merged)}")
                    merges.append(prior)
                    in_prior += pending_points
                    pending, pending_points = Folding(fold, FAN_IN), 0
                    stats["prior_merges"] += 1
                done = f = None  # the finished units are held only where their results are still wanted
                top_up()
        stats["units_with_prior"] = given
        self.unit_spills = unit_spills
        return facts

    def spilled_units(self) -> list | None:
        """Each unit's candidate spill, or None when the units read twice."""
        return self.unit_spills if self.spills is not None else None

    def published(self, run: Run) -> None:
        """Each tile's notes, warned once it is published (as the local run warns its outputs')."""
        for text in self.noted:  # as the local run warns its outputs' notes, once they are published
            warnings.warn(text, PrismWarning, stacklevel=2)


def estimated_bins(points: int, bins: int) -> float:
    """The distinct bins a cloud has, estimated from a unit of ``points`` points that showed ``bins`` of them:
    the B for which B equal bins would show ``bins`` in ``points`` draws, B (1 - exp(-points / B)) = bins
    (at least ``bins``; infinite when every point had a bin of its own). Only how a run reads depends on
    it, never its output."""
    if bins <= 0 or points <= 0:
        return float(max(bins, 0))
    if bins >= points:
        return float("inf")
    lo, hi = float(bins), float(bins)
    while hi * -np.expm1(-points / hi) < bins:  # the shown bins grow with B: bracket, then bisect
        hi *= 2
    for _ in range(60):
        mid = (lo + hi) / 2
        if mid * -np.expm1(-points / mid) < bins:
            lo = mid
        else:
            hi = mid
    return hi


def _facts_of_scan(scan) -> tuple:
    """A :func:`.tasks.scan_unit` result's unit facts (nothing beside them)."""
    return None, unit_facts(scan)


def _report_of_spill(spilled: tuple) -> tuple:
    """A :func:`.tasks.scan_unit_spill` result's spill facts and unit facts (what the driver needs of it)."""
    return spilled[1], unit_facts(spilled[0])


def _one_read_refusal(output, request: Request, sources) -> str | None:
    """Why this run reads its input twice (None: once, each unit spilling its candidates)."""
    if output is None:
        return "a plan only: pass one reads the colors alone"
    if request.reads == "two":
        return "--reads two"
    if request.options.space is not None:
        return "--space: pass one, the spatial order and pass two each read the input"
    refusal = spill_refusal(sources)
    if refusal is None and request.reads == "auto" and all(
            s.format == "parquet" and not remote.is_remote(s.path) for s in sources):
        return PARQUET_TWICE
    return refusal


# On a cluster a unit's pass one costs more than the local engine's (its own filter tables, the prior's
# evidence, every column decoded and the candidates written), while a Parquet unit's two-read passes decode
# only its three color columns twice and every column once: at a billion points (17 tiles, 129k bins, 1%)
# one read took 194.7 s and two reads 124.6 s on `local:2`; at 240M points 70.6 / 35.8 s (1%) and
# 47.8 / 27.6 s (0.1%) (bench/RESULTS_SCALE.md). LAZ decodes whole chunks, so LAZ units still read once.
PARQUET_TWICE = ("Parquet on Dask: each unit reads its color columns in pass one and the cutoffs, every column "
                 "once in pass two, faster than spilling every column (--reads one reads once)")


def _drop_partial_spills(refs, unit_spills: list, plan) -> list:
    """The units whose spill lacks points their file's decision needs lose it: they are read again
    (:meth:`.tasks.UnitSpill.needs_reread`)."""
    out = []
    for ref, u in zip(refs, unit_spills):
        if u.needs_reread(plan.sources[ref.ordinal]["color_depth"]):
            staging.remove(u.folder)
            u = dataclasses.replace(u, folder=None, why="16-bit")
        out.append(u)
    return out


def _reads(refusal: str | None, unit_spills: list) -> dict:
    """What the summary says about how the input was read (as the local engine's), and the units read twice."""
    if refusal is not None:
        return {"reads": 2, "why": refusal}
    again = sum(1 for u in unit_spills if u.folder is None)
    n = len(unit_spills)
    space = sum(1 for u in unit_spills if u.folder is None and u.why == "space")
    many = sum(1 for u in unit_spills if u.folder is None and u.why == "bins")
    why = [f"{space} of {n} units ran out of temporary space for their spill"] if space else []
    if many:
        why.append(f"{many} of {n} units were read twice: the cloud has more colors than the priors of one read "
                   f"fit in a worker's memory (over {PRIOR_BINS:,} bins, estimated from a finished unit)")
    if again - space - many:
        why.append(f"{again - space - many} of {n} units saw no color value above 255 (or saw one only after their "
                   "first points) in a file proved 16-bit: those points move to bin 0, and the units are read again")
    return {"reads": 2 if again else 1,
            "why": "; ".join(why) if again else "the input's size is known up front",
            "spill_points": int(sum(u.points for u in unit_spills)),
            "spill_bytes": int(sum(u.bytes for u in unit_spills)),
            "spill_points_written": int(sum(u.written for u in unit_spills)),
            "spill_compactions": int(sum(u.compactions for u in unit_spills)),
            "units_read_again": again}


def _named_in_output(error: PrismError, stage: str, folder: str, inputs=()) -> None:
    """A part or tile a worker failed to write, named where it would have been published: in the output
    folder (the staging folder is renamed onto it), not beside it, as the sink's own public name has it. An
    input (a file beside the output that a task failed to read) keeps its own name."""
    path = os.fspath(error.path) if error.path is not None else None
    if path and os.path.abspath(path) in {os.path.abspath(os.fspath(f)) for f in inputs}:
        return
    if path and os.path.dirname(path) in (stage, os.path.dirname(stage)) and not staging.is_temporary(
            os.path.basename(path)) and os.path.basename(path) != os.path.basename(folder.rstrip(os.sep)):
        error.path = os.path.join(folder, os.path.basename(path))


def _staging(output: str, what: str):
    """:func:`.tasks.beside_output` for the driver's own writes to the staging folder beside ``output``."""
    return beside_output(what, os.path.dirname(os.path.abspath(output)))


def _between(values, a: int, b: int) -> np.ndarray:
    """``values[a:b]``, of an array or a temporary file."""
    return values.read(a, b - a) if isinstance(values, staging.ArrayFile) else values[a:b]


def _groups(refs: list, points: int) -> list[list]:
    """Consecutive units in groups of at least ``points`` points (the last group whatever is left)."""
    groups, group, n = [], [], 0
    for ref in refs:
        group.append(ref)
        n += ref.points
        if n >= points:
            groups.append(group)
            group, n = [], 0
    if group:
        groups.append(group)
    return groups


def _tile_keep(keep: list):
    """What a tile's units keep, as one: the plan's cutoffs (one for all), or their ids of the spatial share
    joined (a tile's units are consecutive in input order)."""
    if not isinstance(keep[0], spatial.IdSelector):
        return keep[0]
    return spatial.IdSelector(np.concatenate([k.ids for k in keep]))


def _joined(parts: list):
    return None if parts[0] is None else np.concatenate(parts)


def _commit(stage: str, folder: str, tiles, schema, overwrite: bool = False) -> None:
    """Drop what killed tasks left behind, then rename the staging folder onto the output.

    Without ``overwrite`` an output that appeared since the start (another run's) is never replaced.
    """
    for name in os.listdir(stage):
        if name.startswith(".") and name.endswith(staging.SUFFIX):
            os.unlink(os.path.join(stage, name))
    if tiles is None and not any(n.startswith(PART_PREFIX) for n in os.listdir(stage)):
        pq.ParquetWriter(os.path.join(stage, part_name(0, 0)), schema, compression="zstd").close()
    old = None
    if os.path.lexists(folder) and not overwrite:
        raise OutputExists.meanwhile(folder)
    if os.path.lexists(folder):
        old = staging.temp_folder(folder)
        os.rename(folder, os.path.join(old, "old"))
    try:
        os.rename(stage, folder)
    except OSError as exc:
        if old is not None:
            os.rename(os.path.join(old, "old"), folder)
            staging.remove(old)
        if exc.errno in (errno.EEXIST, errno.ENOTEMPTY) and not overwrite:
            raise OutputExists.meanwhile(folder) from None
        raise OutputError(f"cannot commit the output: {exc.strerror or exc}", folder) from None
    if old is not None:
        staging.remove(old)


def read_dataset(folder: str) -> pa.Table:
    """The rows of a Parquet dataset folder this engine wrote, in input order."""
    parts = sorted(glob.glob(os.path.join(folder, PART_PREFIX + "*.parquet")))
    return pa.concat_tables([pq.read_table(p) for p in parts])
