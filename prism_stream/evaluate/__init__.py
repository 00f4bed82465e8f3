"""Evaluation: the paper's baselines and measures, on clouds of any size.

:mod:`.baselines` (Random, Voxel grid, Normal space sampling, streamed like
the sampler), :mod:`.metrics` (Chamfer and Hausdorff distance, color
entropy gain), :mod:`.run` (the paper's Table 1, ablation and k sweep),
:mod:`.report` (tables as text, CSV and JSON), :mod:`.plots` (matplotlib).
"""

from .baselines import BaselineResult, nss_sample, random_sample, voxel_sample
from .cloud import Cloud, coordinates
from .metrics import (Distances, chamfer_distance, color_entropy_gain, entropy_bits, hausdorff_distance,
                      read_sample, sample_distances)

__all__ = [
    "BaselineResult",
    "Cloud",
    "Distances",
    "chamfer_distance",
    "color_entropy_gain",
    "coordinates",
    "entropy_bits",
    "hausdorff_distance",
    "nss_sample",
    "random_sample",
    "read_sample",
    "sample_distances",
    "voxel_sample",
]
