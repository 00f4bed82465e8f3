"""Evaluation: the paper's baselines and measures, on clouds of any size.

:mod:`.baselines` (Random, Voxel grid, Normal space sampling, streamed like
the sampler), :mod:`.metrics` (Chamfer and Hausdorff distance, color
entropy gain), :mod:`.run` (the paper's Table 1, ablation and k sweep),
:mod:`.options` (what ``eval`` compares), :mod:`.report` (tables as text,
CSV and JSON), :mod:`.plots` (matplotlib).

The names below load on first use: the command line reads ``eval``'s options
from :mod:`.options` at every start, without scipy.
"""

import importlib

_EXPORTS = {
    "BaselineResult": "baselines", "nss_sample": "baselines", "random_sample": "baselines",
    "voxel_sample": "baselines", "Cloud": "cloud", "coordinates": "cloud", "Distances": "metrics",
    "chamfer_distance": "metrics", "color_entropy_gain": "metrics", "entropy_bits": "metrics",
    "hausdorff_distance": "metrics", "read_sample": "metrics", "sample_distances": "metrics",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    globals()[name] = value
    return value
