"""A run of PRISM, written once: scan -> solve -> cutoffs -> select -> write -> summary.

:func:`run_pipeline` is the sequence every engine runs. What differs between
runs is handed to it as a :class:`Reads` strategy, which says how pass one
reads the input and how pass two gets its points back:

- :class:`.reads.Held`: a small input held in memory (numpy alone);
- :class:`.reads.Spilled`: read once, the candidates spilled to a temporary file;
- :class:`.reads.Reread`: read twice, each point's bin key cached in between;
- :class:`.dask.driver.OnCluster`: the units of a Dask cluster, each doing one of the above.

The state of a run (request, output layout, temporary folder, timings, the
inputs the summary names, provenance) travels as one :class:`Run`.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field

import numpy as np

from ..core.cutoffs import Rules
from ..core.quotas import Plan, solve
from ..formats import WriteOptions, open_sink
from ..formats.columns import own_selection
from ..formats.reorder import reorder_by
from ..run.outputs import Layout
from ..run.progress import Progress, say
from ..run.request import Request
from ..run.summary import Summary, provenance, summarize, warn_about
from . import spatial
from .ranking import Ranks, rank_points

NO_POINTS = "the input has no points; the output is empty"


@dataclass
class Run:
    """One run's context: everything its steps need besides the plan."""

    request: Request
    layout: Layout  # where the outputs go, and their commit (None output: a plan, writing nothing)
    tmp: str  # the run's temporary folder
    inputs: list  # what the summary names as the inputs
    t0: float = field(default_factory=time.perf_counter)
    no_points: str = NO_POINTS  # the warning for an empty input
    provenance: dict = field(default_factory=dict)  # more for every output's provenance (a query's text)
    seconds: dict = field(default_factory=dict)  # each step's wall time

    @property
    def options(self):
        return self.request.options

    @property
    def dry(self) -> bool:
        """A plan: pass one and the solve only."""
        return self.layout.output is None

    @contextlib.contextmanager
    def timed(self, step: str | None):
        """Time the block as ``step`` (None: not a step of the summary)."""
        t = time.perf_counter()
        yield
        if step is not None:
            self.seconds[step] = self.seconds.get(step, 0.0) + time.perf_counter() - t

    def since_start(self, step: str) -> None:
        """``step`` took from the run's start until now (pass one: opening the inputs counts)."""
        self.seconds[step] = time.perf_counter() - self.t0


class Reads:
    """How a run reads its input: pass one, the cutoffs, and where pass two gets its points.

    A strategy is a context manager (its temporary files live inside it) and
    implements :meth:`scan`, :meth:`histogram`, :meth:`facts`, :meth:`select`
    and :meth:`masked` (or :meth:`write`); the rest has defaults the local
    strategies share. ``sources`` are the run's open sources.
    """

    label = "pass 2/2 select"  # pass two's progress bar
    cutoff_step: str | None = "cutoffs"  # the summary's name for the cutoff step's time
    commit_step: str | None = None  # and for the publishing of the outputs (None: part of "select")

    files = None  # the strategy's temporary files (a context manager), closed when the run ends
    space_reads = 1  # the reads of the input a spatial share adds (--space: its spatial order)

    def __enter__(self):
        if self.files is not None:
            self.files.__enter__()
        return self

    def __exit__(self, *exc):
        return self.files.__exit__(*exc) if self.files is not None else False

    def scan(self, run: Run) -> tuple:
        """Pass one: each source's facts (as dicts, in order)."""
        raise NotImplementedError

    def histogram(self):
        """Pass one's histogram (the memory pass one held for it is let go)."""
        raise NotImplementedError

    def solved(self, run: Run, plan: Plan) -> None:
        """What the strategy learns from the plan before the cutoffs (or a plan's summary)."""

    def facts(self, run: Run, plan: Plan) -> dict:
        """What the summary says of how the input was read (under ``plan``)."""
        raise NotImplementedError

    def rules(self, plan: Plan) -> "Rules | None":
        """The per-key rules the cutoff scan and pass two read (None: this strategy reads the plan itself). Made
        before :meth:`select`, so that the run may let the plan's per-bin arrays go first."""
        return None

    def select(self, run: Run, plan: Plan, rules: "Rules | None") -> None:
        """The cutoffs: after this, :meth:`masked` and :meth:`kept` know which points the plan keeps. ``plan``
        has no per-bin arrays when ``rules`` were made and the run does not rank (:meth:`.Plan.without_bins`)."""
        raise NotImplementedError

    def masked(self, src, bar):
        """Pass two over one source: (points, keep mask) pairs, moving ``bar``."""
        raise NotImplementedError

    def kept(self):
        """The kept points as (bin keys, ids), in input order (what the ranks are computed from)."""
        raise NotImplementedError

    def total(self) -> int | None:
        """How many points pass two goes over (its progress bar's end): what the temporary files hold."""
        return None if self.files is None else self.files.size

    def ranks(self, run: Run, plan: Plan) -> "Ranks | None":
        return rank_points(plan, run, self.kept)

    def every_point(self):
        """Every point as (path, xyz, bin keys, ids) chunks, in input order: the spatial share's read."""
        raise NotImplementedError(f"{type(self).__name__} does not read the points for --space")

    def keep_ids(self, ids) -> None:
        """From here on keep exactly these ids (ascending): the spatial share's sample."""
        raise NotImplementedError

    def respace(self, run: Run, plan: Plan, rarity: "spatial.Rarity") -> "spatial.Spaced":
        """The spatial share (SPEC 9): PRISM's sample merged with the spatial order; pass two keeps its ids."""
        spaced = spatial.respace(plan, run, self.kept, self.every_point, sum(s.count or 0 for s in self.sources),
                                 rarity)
        self.keep_ids(spaced.ids)
        return spaced

    def published(self, run: Run) -> None:
        """After the outputs are published (what is said only of an output that exists)."""

    def write(self, run: Run, plan: Plan, ranks: "Ranks | None") -> list[str]:
        """Pass two: every output written (staged, published by the pipeline); what the writers noted, said
        once every output is written, before they are published (a warning made an error leaves none)."""
        import warnings

        from ..errors import PrismWarning

        noted = write_outputs(plan, run, self.sources, self.label, self.total(), self.masked, ranks)
        for text in noted:
            warnings.warn(text, PrismWarning, stacklevel=2)
        return noted


def run_pipeline(run: Run, reads: Reads) -> Summary:
    """One run of PRISM over ``reads``: pass one, the solve, then (with an output) the cutoffs, the ranks and
    pass two; the outputs appear whole or not at all."""
    with reads:
        with run.layout.transaction():
            sources = reads.scan(run)
            run.since_start("scan")
            with run.timed("solve"):
                plan = solve(reads.histogram(), run.options, sources)
                plan.totals  # noqa: B018 - the summary's totals, once, before the rules take room beside the plan
                say_plan(plan)
            caught = warn_about(plan, run.no_points)
            reads.solved(run, plan)
            if run.dry:
                run.since_start("total")
                return summarize(plan, run.inputs, None, run.seconds, caught, **reads.facts(run, plan))
            spaced = None
            # the spatial share's rarities, from the histogram, before the plan lets its per-bin arrays go
            rarity = spatial.Rarity(plan) if run.options.space is not None else None
            # a ranked run's ranks read the plan's keys and quotas (a spatial share's are its merge's places)
            light = run.request.rank is None or run.options.space is not None
            with run.timed(reads.cutoff_step):
                rules = reads.rules(plan)
                if rules is not None and light:
                    plan = plan.without_bins()  # the per-bin arrays go before the cutoff scan: only the rules
                    # are read from here on (320 MiB over 2^24 bins; docs/DESIGN.md, "Memory")
                reads.select(run, plan, rules)
            if run.options.space is not None:
                with run.timed("space"):
                    spaced = reads.respace(run, plan, rarity)
            if light:
                plan = plan.without_bins()  # and, where the cutoffs read them (the Dask driver), before pass two
            with run.timed("select"):
                if run.request.rank is None:
                    ranks = None
                elif spaced is not None:  # the ranks are the places of the merged order
                    ranks = Ranks(run.request.rank, run.request.order, spaced.rank_values(), "merge")
                else:
                    ranks = reads.ranks(run, plan)
                caught += reads.write(run, plan, ranks)
            with run.timed(reads.commit_step or "select"):
                run.layout.publish()  # here, to time it; the transaction would publish it otherwise
            reads.published(run)
        run.since_start("total")
        facts = reads.facts(run, plan)
    temp = facts.pop("temp", None)
    if spaced is not None:
        facts["space"] = spaced.facts(run.options)
        facts["reads"] = facts.get("reads", 0) + reads.space_reads
    return summarize(plan, run.inputs, run.layout.output, run.seconds, caught, run.layout.published, **facts,
                     **({} if ranks is None else {"rank": ranks.facts()}), **({} if temp is None else {"temp": temp}))


def say_plan(plan) -> None:
    """The solve, under --verbose."""
    k = f", K = {plan.k}" if plan.k is not None else ""
    target = f"{plan.target:,}" if plan.target is not None else "-"
    say(f"solve: N = {plan.points:,}, {plan.bins:,} bins, T = {target}{k}; keeps {plan.kept:,}")


def write_options(layout: Layout, request: Request, members) -> WriteOptions:
    """What the writer of one output is asked (--keep/--drop: as given, or in directory mode the names its
    input has)."""
    selection = own_selection(request.selection, members[0]) if layout.directory else request.selection
    return WriteOptions(flag=request.flag, geometry=request.geometry, rank=request.rank, columns=request.columns,
                        grid=request.las_grid, selection=selection)


def write_outputs(plan, run: Run, sources, label: str, total: int | None, masked, ranks: Ranks | None = None
                  ) -> list[str]:
    """Pass two's writing: each output's sink fed with ``masked(source, bar)``'s (chunk, keep mask) pairs of
    its sources, and their ranks when the run ranks (then reordered by rank with ``--order rank``), staged
    and checked against the plan (the pipeline publishes them). Returns what the sinks noted (attributes a
    format changed or left out), said by the caller once every output is written."""
    layout, request = run.layout, run.request
    more = run.provenance
    if ranks is not None:
        more = {**more, "rank": {"column": ranks.column, "order": ranks.order}}
    prov = provenance(plan, layout.files, request.command, **more)
    kept = 0
    notes: list[str] = []
    with Progress(label, total, request.progress) as bar:
        for target, members in layout.targets(sources):
            with open_sink(target, members, prov, write_options(layout, request, members)) as sink:
                sink.quiet = True  # its notes are said once every output is written (Reads.write)
                for src in members:
                    bar.at(src.path, len(sources))
                    for pts, mask in masked(src, bar):
                        n = int(np.count_nonzero(mask))
                        if ranks is None:
                            sink.write(pts, mask)
                        else:
                            sink.write(pts, mask, ranks=ranks.next(n))
                        kept += n
            notes += sink.notes
            if ranks is not None and ranks.order == "rank":
                with Progress("rank order", sink.written, request.progress) as order_bar:
                    reorder_by(target, ranks.column, sink.written, order_bar.update)
    if kept != plan.kept:
        raise AssertionError(f"selected {kept} points, the plan keeps {plan.kept}")
    return notes
