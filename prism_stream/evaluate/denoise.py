"""Statistical outlier removal, as the authors' script runs it before sampling.

The authors' released PRISM.py calls Open3D's
``remove_statistical_outlier(nb_neighbors=100, std_ratio=2.0)`` on every
cloud before PRISM. Open3D's rule, reproduced here point for point:

- d_i = the mean distance from point i to its ``k`` nearest neighbours, the
  point itself included (its distance 0 counts, so the mean is over k).
- mu = the sum of the positive d_i over N (all points, including those with
  d_i = 0); sigma = sqrt(sum over positive d_i of (d_i - mu)^2 / (N - 1)).
- keep i when 0 < d_i < mu + std_ratio * sigma. A point whose k neighbours
  all sit on it (d_i = 0: k or more duplicates) is removed.

In memory: the cloud's coordinates and one KD-tree (about 60 bytes a point
plus k distances a point in blocks). ``tests/test_denoise.py`` checks it
against Open3D on the real clouds when open3d is installed.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..errors import UsageError

_SOR = re.compile(r"^sor:(\d+),([0-9.eE+-]+)$")


@dataclass(frozen=True)
class Denoise:
    """``--denoise sor:K,STD``: statistical outlier removal with K neighbours and a STD-sigma cut."""

    neighbours: int = 100
    std_ratio: float = 2.0

    @staticmethod
    def parse(text: str) -> "Denoise":
        m = _SOR.match(str(text).strip().lower())
        if not m:
            raise UsageError(f"--denoise takes sor:K,STD (e.g. sor:100,2.0), not {text!r}")
        k, std = int(m.group(1)), float(m.group(2))
        if k < 1 or not (std > 0 and math.isfinite(std)):
            raise UsageError(f"--denoise sor:K,STD needs K >= 1 and STD > 0, not {text!r}")
        return Denoise(k, std)

    @property
    def label(self) -> str:
        return f"sor:{self.neighbours},{self.std_ratio:g}"


def mean_neighbour_distances(xyz: np.ndarray, k: int, block: int = 1 << 16) -> np.ndarray:
    """d_i: mean distance to the k nearest points, the point itself included (Open3D's SearchKNN)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    n = len(xyz)
    k = min(k, n)
    out = np.empty(n)
    if n == 0:
        return out
    tree = cKDTree(xyz)
    for a in range(0, n, block):
        d, _ = tree.query(xyz[a:a + block], k=k, workers=-1)
        out[a:a + block] = np.asarray(d).reshape(len(d), -1).mean(axis=1)
    return out


def sor_keep(xyz: np.ndarray, neighbours: int = 100, std_ratio: float = 2.0) -> np.ndarray:
    """Boolean mask of the points Open3D's ``remove_statistical_outlier`` keeps."""
    d = mean_neighbour_distances(xyz, neighbours)
    n = len(d)
    if n == 0:
        return np.zeros(0, dtype=bool)
    pos = d > 0
    mu = d[pos].sum() / n
    sigma = math.sqrt(((d[pos] - mu) ** 2).sum() / (n - 1)) if n > 1 else 0.0
    return pos & (d < mu + std_ratio * sigma)
