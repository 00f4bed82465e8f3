"""prism-stream: out-of-core PRISM color-stratified point cloud sampling.

The layout (docs/DESIGN.md draws it):

- :mod:`.core`: the pure steps (bins, histogram, quotas, cutoffs, selection,
  and the two passes over a work unit);
- :mod:`.formats`: sources and sinks, one module a format;
- :mod:`.run`: the request (every option), inputs, outputs, the summary;
- :mod:`.engines`: where the steps run: ``local``, ``sql`` (a DuckDB query's
  result), ``dask`` (a cluster);
- :mod:`.sql`: DuckDB functions and macros, batch jobs;
- :mod:`.evaluate`: baselines and metrics for ``prism-stream eval``.

The names below load on first use, so ``import prism_stream`` stays cheap.
"""

__version__ = "0.1.0"

_EXPORTS = {
    "sample": ("engines.local", "sample"),
    "plan": ("engines.local", "plan"),
    "rank": ("engines.local", "rank"),
    "Request": ("run.request", "Request"),
    "Summary": ("run.summary", "Summary"),
    "Options": ("core.quotas", "Options"),
    "Plan": ("core.quotas", "Plan"),
    "solve": ("core.quotas", "solve"),
    "BinSpec": ("core.bins", "BinSpec"),
    "Histogram": ("core.histogram", "Histogram"),
    "merge_units": ("core.histogram", "merge_units"),
    "scan": ("core.passes", "scan"),
    "select": ("core.passes", "select"),
    "Cutoffs": ("core.cutoffs", "Cutoffs"),
    "PrismError": ("errors", "PrismError"),
    "PrismWarning": ("errors", "PrismWarning"),
}

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name):
    try:
        module, attr = _EXPORTS[name]
    except KeyError:
        raise AttributeError(f"module 'prism_stream' has no attribute {name!r}") from None
    import importlib

    value = getattr(importlib.import_module(f".{module}", __name__), attr)
    globals()[name] = value
    return value


def __dir__():
    return sorted(list(globals()) + list(_EXPORTS))
