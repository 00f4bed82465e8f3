"""Every command's options, made from the Request's fields (prism_stream/run/request.py), so each is declared once.

``request_options(...)`` adds the click options of Request fields to a
command; the command gets them back as keyword arguments and builds the
Request with :func:`request_of`. The options of the report (``--json``,
``--summary``, ``--quiet``) are declared here once too.
"""

from __future__ import annotations

import dataclasses
import os
import sys

import click

from prism_stream.run.request import Request

_TYPES = {"ratio": float, "count": int, "k": int, "quant_bits": click.IntRange(0, 7), "quant_step": float, "seed": int,
          "chunk_size": click.IntRange(1), "threads": click.IntRange(1),
          # eval's (prism_stream/evaluate/options.py)
          "ablation_k": click.IntRange(1), "nss_per_bin": click.IntRange(1), "voxel_size": float,
          "nss_k": click.IntRange(3), "tile_points": click.IntRange(1000)}
FIELDS = {f.name: f for f in dataclasses.fields(Request)}


def request_options(*, only=(), exclude=(), unset=(), helps=None):
    """A decorator adding the options of the Request's fields (``only`` these, or all but ``exclude``).

    The fields named in ``unset`` default to None instead of the Request's default, so a command can
    tell "not given" (``eval --preset`` fills those in). ``helps`` maps a field to the help text of
    this command, where an option does more here than the Request's text says (``sql --threads``).
    """
    return dataclass_options(Request, only=only, exclude=exclude, unset=unset, helps=helps)


def dataclass_options(cls, *, only=(), exclude=(), unset=(), helps=None):
    """:func:`request_options` for any dataclass whose fields are declared with ``run.request.option``
    (``eval``'s EvalOptions). A tuple default is offered as comma-separated text, which the dataclass parses."""
    helps = helps or {}
    chosen = [f for f in dataclasses.fields(cls) if f.metadata.get("cli") and (not only or f.name in only)
              and f.name not in exclude]

    unknown = set(helps) - {f.name for f in chosen}
    assert not unknown, f"help for options the command lacks: {unknown}"

    def decorate(fn):
        for f in reversed(chosen):
            m = f.metadata
            default = ",".join(map(str, f.default)) if isinstance(f.default, tuple) else f.default
            kw = {"help": helps.get(f.name, m["help"]), "default": None if f.name in unset else default}
            if isinstance(f.default, bool) and f.name not in unset:
                kw["is_flag"] = True
            elif m["choices"]:
                kw["type"] = click.Choice(m["choices"])
                kw["show_default"] = True
            elif f.name in _TYPES:
                kw["type"] = _TYPES[f.name]
            if default not in (None, "") and not isinstance(f.default, bool) and f.name not in unset:
                kw["show_default"] = True
            if m["metavar"]:
                kw["metavar"] = m["metavar"]
            fn = click.option(*m["flags"], f.name, **kw)(fn)
        return fn

    return decorate


def engine(dask: str | None):
    """``prism_stream.sample``'s call shape on the engine the command line names: the Dask cluster at
    ``dask`` (``--dask``), or this machine."""
    if dask:
        from prism_stream.engines.dask import on_cluster

        return on_cluster(dask)
    return local_engine()


def local_engine():
    """The local engine's ``sample``, in a process that runs no numba linear algebra: numba's first kernel
    skips its search for a BLAS (an import of scipy.linalg, 0.2-0.3 s; ``core/warm.py``)."""
    from prism_stream.core.warm import without_blas
    from prism_stream.engines.local import sample

    without_blas()
    return sample


COMMAND = "prism_stream.command"  # where the command line is, in the click context's meta (cli/main.py)


def small_pages() -> None:
    """Before pyarrow loads (a command calls this, through :func:`request_of` or itself, before it imports
    anything that loads pyarrow): Arrow's allocator (mimalloc) is asked for no transparent huge pages.
    mimalloc hands a freed batch's pages back to the OS and takes them again for the next one; as huge pages
    each comes back zeroed 2 MiB at a time, and on a machine whose memory is fragmented the kernel compacts it
    first: up to 0.4 s of a 10M-point Parquet run on one thread (the decode waits on it), and on two threads
    0.65-1.3 s of system time where small pages took 0.3-0.45 (bench/PROFILE.md, "Huge pages at every thread
    count"). mimalloc then turns them off for the whole process and the processes it starts (``prctl``: numpy's
    and numba's large arrays too, DuckDB's in ``sql``). A value the user set is kept."""
    if "pyarrow" not in sys.modules:
        os.environ.setdefault("MIMALLOC_ALLOW_THP", "0")


def request_of(values: dict, **more) -> Request:
    """The Request of a command's parsed options (the Request fields among them), plus ``more``, with the
    command line that gave them."""
    ctx = click.get_current_context(silent=True)
    command = ctx.meta.get(COMMAND) if ctx is not None else None
    given = {k: v for k, v in values.items() if k in FIELDS}
    small_pages()
    if given.get("preset") is not None and ctx is not None:  # the preset fills what the command line left unsaid
        given = {k: v for k, v in given.items() if ctx.get_parameter_source(k) != click.core.ParameterSource.DEFAULT}
        return Request.of(**given, command=command, **more)
    return Request(**given, command=command, **more)


as_json = click.option("--json", "as_json", is_flag=True, help="Print the run summary as JSON on stdout.")
summary_file = click.option("--summary", "summary_file", metavar="FILE",
                            help="Also write the JSON summary to this file (a new file; --overwrite replaces one).")
quiet = click.option("--quiet", "-q", is_flag=True,
                     help="No progress bars, no summary text (errors and warnings still print).")


def _verbose(ctx, param, value):
    from prism_stream.run.progress import set_verbose

    set_verbose(bool(value) and not ctx.resilient_parsing)  # every command line sets it, on or off


verbose = click.option("--verbose", "-v", is_flag=True, expose_value=False, callback=_verbose,
                       help="Each step on stderr as it starts and ends (points, seconds), terminal or not.")


def report_options(fn):
    """--json, --summary, --quiet and --verbose."""
    return as_json(summary_file(quiet(verbose(fn))))
