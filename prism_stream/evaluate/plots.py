"""Figures of an evaluation (PNG, matplotlib): polar chroma histograms and the k-sweep curve.

matplotlib is imported only when a figure is drawn; ``pip install
'prism-stream[eval]'`` brings it. The histogram itself (:func:`chroma_histogram`)
needs numpy only, so evaluations record it without matplotlib.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import UsageError
from ..scan import Histogram
from .cloud import RGB8
from .entropy import HUE_BINS, SAT_BINS, hue_sat_cells


def chroma_histogram(histogram: Histogram, hue_bins: int = HUE_BINS, sat_bins: int = SAT_BINS) -> np.ndarray:
    """Points per (hue, saturation) cell, from an 8-bit RGB histogram (HSV hue and saturation)."""
    cells = hue_sat_cells(*RGB8.channels(histogram.keys), hue_bins=hue_bins, sat_bins=sat_bins)
    out = np.bincount(cells, weights=histogram.counts, minlength=hue_bins * sat_bins)
    return out.astype(np.int64).reshape(hue_bins, sat_bins)


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise UsageError("--plots needs matplotlib: pip install 'prism-stream[eval]'") from None
    return plt


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in text).strip("_")


def polar_chroma(panels: list[tuple[str, np.ndarray]], path: str, title: str = "") -> str:
    """One polar panel per (label, hue x saturation counts): hue as angle, saturation as radius,
    log10 of the count as color, one color scale shared by every panel."""
    plt = _pyplot()
    from matplotlib.colors import LogNorm

    counts = [np.asarray(c, dtype=np.float64) for _, c in panels]
    positive = [c[c > 0] for c in counts if (c > 0).any()]
    vmax = max(float(p.max()) for p in positive) if positive else 1.0
    norm = LogNorm(vmin=1.0, vmax=max(vmax, 10.0))
    n = len(panels)
    cols = min(n, 3)
    rows = (n + cols - 1) // cols
    fig = plt.figure(figsize=(4.6 * cols + 1.2, 4.4 * rows + 0.6))
    mesh = None
    for i, ((label, _), c) in enumerate(zip(panels, counts)):
        ax = fig.add_subplot(rows, cols, i + 1, projection="polar")
        theta = np.linspace(0, 2 * np.pi, c.shape[0] + 1)
        radius = np.linspace(0, 1, c.shape[1] + 1)
        mesh = ax.pcolormesh(theta, radius, np.ma.masked_less_equal(c.T, 0), norm=norm, cmap="viridis",
                             shading="flat")
        ax.set_title(f"{label}\n{int(c.sum()):,} points", fontsize=9)
        ax.set_yticklabels([])
        ax.set_xticks(np.deg2rad([0, 60, 120, 180, 240, 300]))
        ax.set_xticklabels(["R", "Y", "G", "C", "B", "M"], fontsize=8)
    if mesh is not None:
        fig.colorbar(mesh, ax=fig.axes, shrink=0.8, label="points per (hue, saturation) cell")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def k_sweep_curve(series: dict[str, list[tuple[int, float]]], path: str) -> str:
    """Output ratio against the bin capacity k, one line per dataset."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4.2))
    for name, points in series.items():
        ks, ratios = zip(*sorted(points))
        ax.plot(ks, [100 * r for r in ratios], marker="o", label=name)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("bin capacity k")
    ax.set_ylabel("output ratio (% of N)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_figures(evaluation, folder: str) -> list[str]:
    """Every figure of an evaluation into ``folder``: one polar chroma figure per dataset and
    target ratio (input and each method), and the k-sweep curve if there is one."""
    _pyplot()
    os.makedirs(folder, exist_ok=True)
    written = []
    groups: dict[tuple, list] = {}
    for row in evaluation.rows:
        groups.setdefault((row.dataset, row.target_ratio), []).append(row)
    for (dataset, ratio), rows in groups.items():
        panels = [("input", np.asarray(evaluation.inputs[dataset]["chroma"]))]
        panels += [(r.method, np.asarray(r.chroma)) for r in rows if r.chroma is not None]
        path = os.path.join(folder, f"chroma_{_slug(dataset)}_r{ratio:g}.png")
        written.append(polar_chroma(panels, path, f"{dataset}, target ratio {ratio:g}"))
    if evaluation.k_sweep:
        series: dict[str, list] = {}
        for r in evaluation.k_sweep:
            series.setdefault(r.dataset, []).append((r.k, r.ratio))
        written.append(k_sweep_curve(series, os.path.join(folder, "k_sweep.png")))
    return written
