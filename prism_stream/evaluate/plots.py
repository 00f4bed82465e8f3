"""Figures of an evaluation (PNG, matplotlib): polar chroma histograms and the k-sweep curve.

matplotlib is imported only when a figure is drawn; ``pip install
'.[eval]'`` in the clone brings it. The histogram itself (:func:`chroma_histogram`)
needs numpy only, so evaluations record it without matplotlib.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import UsageError
from ..core.histogram import Histogram
from .cloud import RGB8
from .entropy import HUE_BINS, SAT_BINS, hue_sat_cells



def _save(fig, path: str, title: str = "", dpi: int = 110) -> str:
    """Title, tighten, write and close a figure; return its path."""
    plt = _pyplot()
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path

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
        raise UsageError("--plots needs matplotlib: pip install matplotlib, or pip install '.[eval]' in the clone") from None
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
        # radius = sqrt(saturation): LiDAR colors are mostly below 0.3, which linear rings squeeze to the center
        radius = np.sqrt(np.linspace(0, 1, c.shape[1] + 1))
        mesh = ax.pcolormesh(theta, radius, np.ma.masked_less_equal(c.T, 0), norm=norm, cmap="viridis",
                             shading="flat")
        ax.set_title(f"{label}\n{int(c.sum()):,} points", fontsize=9)
        rings = [0.1, 0.2, 0.4, 0.7, 1.0]
        ax.set_yticks(np.sqrt(rings))
        ax.set_yticklabels([f"s={v:g}" for v in rings], fontsize=7, color="0.3")
        ax.set_xticks(np.deg2rad([0, 60, 120, 180, 240, 300]))
        ax.set_xticklabels(["R", "Y", "G", "C", "B", "M"], fontsize=8)
    if mesh is not None:
        fig.colorbar(mesh, ax=fig.axes, shrink=0.8, label="points per (hue, saturation) cell")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _cell_colors(hue_bins: int, sat_bins: int) -> np.ndarray:
    """The color at the center of each (hue, saturation) cell, at full value: (hue_bins, sat_bins, 3)."""
    from matplotlib.colors import hsv_to_rgb

    h = (np.arange(hue_bins) + 0.5) / hue_bins
    sat = (np.arange(sat_bins) + 0.5) / sat_bins
    hh, ss = np.meshgrid(h, sat, indexing="ij")
    return hsv_to_rgb(np.stack([hh, ss, np.ones_like(hh)], axis=-1))


def chroma_bars(panels: list[tuple[str, np.ndarray]], path: str, title: str = "") -> str:
    """The paper's color-distribution figure: one 3D bar per (hue, saturation) cell on the polar
    chromaticity grid, height log10(1 + count) on one z range shared by every panel, bar colored as its cell."""
    plt = _pyplot()
    counts = [np.asarray(c, dtype=np.float64) for _, c in panels]
    zmax = max([float(np.log10(1 + c.max())) for c in counts if c.size] + [1.0])
    n = len(panels)
    cols = min(n, 3)
    rows = (n + cols - 1) // cols
    fig = plt.figure(figsize=(4.8 * cols, 4.6 * rows + 0.4))
    hb, sb = counts[0].shape
    colors = _cell_colors(hb, sb)
    th = 2 * np.pi * (np.arange(hb) + 0.5) / hb
    rad = np.sqrt((np.arange(sb) + 0.5) / sb)  # sqrt(saturation), as in the polar plot
    tt, rr = np.meshgrid(th, rad, indexing="ij")
    x, y = (rr * np.cos(tt)).ravel(), (rr * np.sin(tt)).ravel()
    width = 0.045
    for i, ((label, _), c) in enumerate(zip(panels, counts)):
        ax = fig.add_subplot(rows, cols, i + 1, projection="3d")
        z = np.log10(1 + c).ravel()
        on = z > 0
        ax.bar3d(x[on] - width / 2, y[on] - width / 2, np.zeros(on.sum()), width, width, z[on],
                 color=colors.reshape(-1, 3)[on], shade=True, edgecolor="none")
        for s in (0.1, 0.4, 1.0):  # labeled saturation rings on the floor
            a = np.linspace(0, 2 * np.pi, 90)
            ax.plot(np.sqrt(s) * np.cos(a), np.sqrt(s) * np.sin(a), 0, color="0.6", lw=0.6)
            ax.text(np.sqrt(s), 0, 0, f"s={s:g}", fontsize=6, color="0.35")
        for ang, name in zip(range(0, 360, 60), "RYGCBM"):
            ax.text(1.15 * np.cos(np.deg2rad(ang)), 1.15 * np.sin(np.deg2rad(ang)), 0, name, fontsize=7)
        ax.set_zlim(0, zmax)
        ax.set_xlim(-1.1, 1.1)
        ax.set_ylim(-1.1, 1.1)
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_zlabel("log10(1 + points)", fontsize=7)
        ax.tick_params(axis="z", labelsize=7)
        ax.view_init(elev=32, azim=-60)
        ax.set_title(f"{label}: {int(c.sum()):,} points, {int((c > 0).sum())} cells", fontsize=9)
    return _save(fig, path, title, dpi=110)


def top_down(panels: list[tuple[str, np.ndarray, np.ndarray | None]], path: str, title: str = "") -> str:
    """Top-down true-color renders, input and samples side by side on the same axes limits.

    Points are drawn lowest first, so the top of the scene is what shows, as
    in a plan view. Each panel shows up to PREVIEW evenly strided points.
    """
    plt = _pyplot()
    n = len(panels)
    cols = min(n, 3)
    rows = (n + cols - 1) // cols
    ref = panels[0][1]
    lo, hi = ref[:, :2].min(axis=0), ref[:, :2].max(axis=0)
    aspect = float((hi[1] - lo[1]) / max(hi[0] - lo[0], 1e-12))
    w = 4.6
    fig, axes = plt.subplots(rows, cols, figsize=(w * cols, max(2.5, w * min(aspect, 1.6)) * rows + 0.5),
                             squeeze=False)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    for ax, (label, xyz, rgb) in zip(axes.ravel(), panels):
        order = np.argsort(xyz[:, 2], kind="stable")
        col = (rgb[order] / 255.0) if rgb is not None else "k"
        size = max(0.15, min(6.0, 2e4 / max(len(xyz), 1)))
        ax.scatter(xyz[order, 0], xyz[order, 1], c=col, s=size, marker=".", linewidths=0)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.set_facecolor("0.92")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(label, fontsize=9)
    return _save(fig, path, title, dpi=120)


def spaced_ticks(values: list, factor: float = 1.2) -> list:
    """Tick positions on a log axis, each at least ``factor`` times the one before: methods that reach 5% and
    5.01% of the points get one tick, not two labels printed over each other ("5.5.01")."""
    out: list = []
    for v in sorted(values):
        if not out or (v > 0 and out[-1] > 0 and v >= out[-1] * factor):
            out.append(v)
    return out


def metric_curves(rows, path: str, title: str = "", entropy_label: str = "entropy gain (bits)") -> str:
    """CD, HD and entropy gain against the ratio reached, one line per method (one dataset)."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2))
    series: dict[str, list] = {}
    for r in rows:
        series.setdefault(r.method, []).append(r)
    for name, rs in series.items():
        rs = sorted(rs, key=lambda r: r.ratio)
        x = [100 * r.ratio for r in rs]
        for ax, f in zip(axes, ("chamfer", "hausdorff", "entropy_gain")):
            y = [getattr(r, f) for r in rs]
            if all(v is not None for v in y):
                ax.plot(x, y, marker="o", label=name)
    ticks = spaced_ticks(sorted({round(100 * r.ratio, 2) for r in rows}))
    for ax, name in zip(axes, ("Chamfer distance (input units)", "Hausdorff distance (input units)",
                               entropy_label)):
        ax.set_xscale("log")
        ax.set_xticks(ticks)
        ax.xaxis.set_minor_formatter(plt.NullFormatter())
        ax.set_xlabel("output ratio (% of input points)")
        ax.set_ylabel(name)
        ax.grid(True, which="both", alpha=0.3)
        ax.xaxis.set_major_formatter(plt.FuncFormatter(lambda v, _: f"{v:g}"))
    axes[2].axhline(0, color="0.5", lw=0.8)
    axes[0].legend(fontsize=8)
    return _save(fig, path, title, dpi=110)


def k_sweep_curve(series: dict[str, list[tuple[int, float]]], path: str) -> str:
    """Output ratio against the bin capacity k, one line per dataset."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4.2))
    for name, points in series.items():
        ks, ratios = zip(*sorted(points))
        ax.plot(ks, [100 * r for r in ratios], marker="o", label=name)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.xaxis.set_major_formatter(plt.FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_major_formatter(plt.FuncFormatter(lambda v, _: f"{v:g}"))
    ax.set_xticks(sorted({k for pts in series.values() for k, _ in pts}))
    ax.xaxis.set_minor_formatter(plt.NullFormatter())
    ax.yaxis.set_minor_formatter(plt.NullFormatter())
    ax.set_xlabel("bin capacity k")
    ax.set_ylabel("output ratio (% of N)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def space_tradeoff(rows, path: str, title: str = "", entropy_label: str = "entropy gain (bits)") -> str:
    """``eval --space``: Chamfer and Hausdorff distance, relative to the voxel grid's, against the entropy gain,
    one line per dataset through PRISM (A = 0) and its spatial shares (labeled with A); the baselines as
    points of the dataset's color."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(13, 6))
    markers = {"Random": "x", "Voxel grid": "s", "NSS": "^"}
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    by_dataset: dict[str, list] = {}
    for r in rows:
        by_dataset.setdefault(r.dataset, []).append(r)
    for i, (dataset, rs) in enumerate(by_dataset.items()):
        color = colors[i % len(colors)]
        prism = sorted([r for r in rs if r.method.startswith("PRISM") and "k" not in r.params],
                       key=lambda r: float(r.params.get("space", 0)))
        voxel = next((r for r in rs if r.method == "Voxel grid"), None)
        if voxel is None or not prism or not voxel.chamfer or not voxel.hausdorff:
            continue
        for ax, f, ref in zip(axes, ("chamfer", "hausdorff"), (voxel.chamfer, voxel.hausdorff)):
            xs = [r.entropy_gain for r in prism]
            ys = [getattr(r, f) / ref for r in prism]
            ax.plot(xs, ys, marker="o", ms=4, color=color, label=dataset)
            for r, x, y in zip(prism, xs, ys):
                if "space" not in r.params or r.params["space"] in ("0.5", "1"):
                    ax.annotate(f"{float(r.params.get('space', 0)):g}", (x, y), fontsize=7, color=color,
                                xytext=(3, 3), textcoords="offset points")
            for r in rs:
                if r.method in markers and getattr(r, f) is not None:
                    ax.plot(r.entropy_gain, getattr(r, f) / ref, markers[r.method], color=color, ms=7,
                            mfc="none")
    for ax, name in zip(axes, ("Chamfer distance / voxel grid's", "Hausdorff distance / voxel grid's")):
        ax.set_xlabel(entropy_label)
        ax.set_ylabel(name)
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(plt.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.yaxis.set_minor_formatter(plt.FuncFormatter(lambda v, _: f"{v:g}" if str(v)[0] in "1235" else ""))
        ax.grid(True, which="both", alpha=0.3)
        ax.axhline(1, color="0.5", lw=0.8)
        ax.axvline(0, color="0.5", lw=0.8)
    handles = [plt.Line2D([], [], marker=m, ls="", color="0.3", mfc="none", label=n) for n, m in markers.items()]
    axes[1].legend(handles=handles, fontsize=8, title="baselines", loc="upper right")
    lines, names = axes[0].get_legend_handles_labels()
    fig.legend(lines, names, fontsize=7, title="PRISM, spatial share A (0, 0.5 and 1 labeled)", loc="lower center",
               ncol=4, title_fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.13, 1, 1))  # the datasets' legend below both panels
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_figures(evaluation, folder: str) -> list[str]:
    """Every figure of an evaluation into ``folder``, per dataset and table group: the chromaticity
    bar histogram and polar map (input and each method), the top-down renders, CD/HD/entropy against
    the ratio (when several ratios were run), and the k-sweep curve."""
    _pyplot()
    os.makedirs(folder, exist_ok=True)
    written = []
    groups: dict[tuple, list] = {}
    for row in evaluation.rows:
        groups.setdefault((row.dataset, row.target_ratio), []).append(row)
    schemes = evaluation.settings.get("entropy_bins") or ["rgb8"]
    for (dataset, ratio), rows in groups.items():
        tag = f"r{ratio:g}" if ratio is not None else f"k{evaluation.settings.get('k')}"
        info = evaluation.inputs[dataset]
        panels = [("input", np.asarray(info["chroma"]))]
        panels += [(r.method, np.asarray(r.chroma)) for r in rows if r.chroma is not None]
        title = f"{dataset}, " + (f"target ratio {ratio:g}" if ratio is not None else tag)
        written.append(chroma_bars(panels, os.path.join(folder, f"chroma_bars_{_slug(dataset)}_{tag}.png"), title))
        written.append(polar_chroma(panels, os.path.join(folder, f"chroma_{_slug(dataset)}_{tag}.png"), title))
        if info.get("preview") is not None and all(r.preview is not None for r in rows):
            xyz, rgb = info["preview"]
            renders = [(f"input: {info['points']:,} points", xyz, rgb)]
            renders += [(f"{r.method}: {r.count:,} ({r.ratio:.2%})", r.preview, r.preview_rgb) for r in rows]
            written.append(top_down(renders, os.path.join(folder, f"topdown_{_slug(dataset)}_{tag}.png"), title))
    by_dataset: dict[str, list] = {}
    for row in evaluation.rows:
        if row.target_ratio is not None:
            by_dataset.setdefault(row.dataset, []).append(row)
    for dataset, rows in by_dataset.items():
        if len({r.target_ratio for r in rows}) > 1:
            written.append(metric_curves(rows, os.path.join(folder, f"metrics_{_slug(dataset)}.png"), dataset,
                                         f"entropy gain, {schemes[0]} bins (bits)"))
    if evaluation.settings.get("spaces"):
        by_ratio: dict = {}
        for row in evaluation.rows:
            if row.table == "main" and row.target_ratio is not None:
                by_ratio.setdefault(row.target_ratio, []).append(row)
        for ratio, rows in by_ratio.items():
            written.append(space_tradeoff(rows, os.path.join(folder, f"space_tradeoff_r{ratio:g}.png"),
                                          f"color against space, target ratio {ratio:g}",
                                          f"entropy gain, {schemes[0]} bins (bits)"))
    if evaluation.k_sweep:
        series: dict[str, list] = {}
        for r in evaluation.k_sweep:
            series.setdefault(r.dataset, []).append((r.k, r.ratio))
        written.append(k_sweep_curve(series, os.path.join(folder, "k_sweep.png")))
    return written
