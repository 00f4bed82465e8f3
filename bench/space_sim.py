"""Color and space (issue 29): candidate mechanisms between PRISM and a voxel grid, in memory, on the real clouds.

    python bench/space_sim.py [--ratios 0.01,0.1] [--seeds 0,1,2] [--json bench/out/space_sim.json]

Every method keeps exactly T = floor(r N + 0.5) points of a cloud. Measured against an equal-T voxel grid V
(Chamfer and Hausdorff distance, CD / CD_V and HD / HD_V) and against PRISM P (the rgb-grid color entropy gain,
512 cells, gain / gain_P), as issue 29 states its target: some setting with CD <= 1.15 V, HD <= 1.3 V and
gain >= 0.75 P on average over the clouds.

Methods (priorities are a seeded random permutation; bin and cell priorities a seeded random draw):

- ``P``: PRISM, exact mode over the 8-bit RGB bins; ``R``: uniform random; ``V``: the voxel grid: the largest
  cell size with at least T occupied cells (bisection), T of those cells by cell priority, the point nearest its
  cell's centroid in each.
- ``mix a``: the issue's baseline: round(a T) points as V takes them (its own size), then PRISM over the
  other points for the rest.
- ``mixr a``: the mixture, its voxel share taking in each cell the point of the rarest color (its count
  in the whole cloud, ties by priority) instead of the one nearest the centroid.
- ``mixq<b> a``: as ``mixr``, the rarity of the color with b low bits dropped a channel (coarse colors:
  more ties), ties by distance to the cell's centroid.
- ``nest s``: cells of size s x V's; each cell's quota by PRISM's exact rule over the cells (cells as bins,
  target T), and inside each cell its quota by PRISM's exact rule over the cell's color bins (K_c or K_c + 1
  a bin, the extra ones by bin priority). One cell (s large) is PRISM itself; cells of V's size with one
  point each are a voxel grid whose point in each cell is a random color of the cell, not a random point.
- ``rare s``: as ``nest s``, but inside a cell the bins are taken rarest first (by their count in the whole
  cloud), not by bin priority: each cell gives its rarest colors.

The engine implements none of these yet: this is where the mechanism is chosen (and the oracle written)
before it is built into every engine.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from prism_stream.evaluate import Cloud

REAL = Path(__file__).resolve().parent.parent / "tests" / "data" / "real"
CLOUDS = ("laspy__fullwave.laz", "open3d__frag_115.ply", "pcl__office1.pcd", "potree__lion_takanawa.copc.laz",
          "pdal__las_with_several_extra_byte_bloc.laz", "pdal__autzen_trim.las")


def load(name: str):
    with Cloud(str(REAL / name)) as cloud:
        xyz, keys = [], []
        for c in cloud.chunks():
            xyz.append(c.xyz)
            keys.append(cloud.keys_of(c.ordinal, c.raw.rgb))
        return np.concatenate(xyz), np.concatenate(keys).astype(np.int64)


def places(sorted_groups: np.ndarray) -> np.ndarray:
    """Each element's place (0, 1, ...) in its run of equal values of ``sorted_groups``."""
    g = sorted_groups
    start = np.concatenate([[0], np.flatnonzero(g[1:] != g[:-1]) + 1])
    return np.arange(len(g)) - np.repeat(start, np.diff(np.concatenate([start, [len(g)]])))


def rounds(group: np.ndarray, prio: np.ndarray) -> np.ndarray:
    """Each point's round: its place in its group by priority."""
    by = np.lexsort((prio, group))
    j = np.empty(len(group), np.int64)
    j[by] = places(group[by])
    return j


def ranked_order(group: np.ndarray, prio: np.ndarray, group_prio: np.ndarray) -> np.ndarray:
    """PRISM's exact selection order over groups (bins or cells): points are taken round by round
    (:func:`rounds`), each round's groups by group priority. The first q points of this order are PRISM's
    exact sample of q points over these groups (K full rounds, the extra ones by group priority among the
    groups with more than K points)."""
    return np.lexsort((prio, group_prio[group], rounds(group, prio)))


def prism(keys, t, prio, bin_prio) -> np.ndarray:
    _, inv = np.unique(keys, return_inverse=True)
    return ranked_order(inv, prio, bin_prio[np.unique(keys)])[:t] if t else np.zeros(0, np.int64)


def cells_of(xyz, lo, size) -> np.ndarray:
    """Each point's cell of a grid of ``size`` from ``lo``, numbered 0.. in cell order."""
    ijk = np.floor((xyz - lo) / size).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    flat = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    _, inv = np.unique(flat, return_inverse=True)
    return inv.ravel()


def voxel_size_for(xyz, t, lo) -> float:
    """The largest cell size with at least t occupied cells (bisection on a log scale)."""
    ext = float(np.max(xyz.max(axis=0) - lo)) or 1.0
    a, b = ext * 1e-6, ext * 2  # occupied(a) >= t (if the cloud has t distinct places), occupied(b) = 1
    for _ in range(30):
        mid = math.sqrt(a * b)
        if cells_of(xyz, lo, mid).max() + 1 >= t:
            a = mid
        else:
            b = mid
    return a


def voxel(xyz, t, rng, size=None, rarity=None) -> np.ndarray:
    """V: T occupied cells by cell priority, in each the point nearest its centroid (``rarity``: the point of
    the smallest rarity value, e.g. its color's count in the whole cloud)."""
    lo = xyz.min(axis=0)
    size = voxel_size_for(xyz, t, lo) if size is None else size
    cell = cells_of(xyz, lo, size)
    n = cell.max() + 1
    if rarity is None:
        cent = np.zeros((n, 3))
        np.add.at(cent, cell, xyz)
        cent /= np.bincount(cell, minlength=n)[:, None]
        d = ((xyz - cent[cell]) ** 2).sum(axis=1)
    else:
        d = rarity
    by = np.lexsort((d, cell))
    first = by[np.concatenate([[True], cell[by][1:] != cell[by][:-1]])]  # nearest its centroid, a cell
    chosen = rng.permutation(n)[:t]  # T cells by cell priority
    return np.sort(first[np.isin(cell[first], chosen)])


def coarse(keys, bits):
    """The 8-bit RGB keys with ``bits`` low bits dropped a channel."""
    r, g, b = keys >> 16 & 255, keys >> 8 & 255, keys & 255
    return ((r >> bits) << 16) | ((g >> bits) << 8) | (b >> bits)


def mixture(xyz, keys, t, a, prio, bin_prio, rng, rare=False, bits=None) -> np.ndarray:
    s = int(round(a * t))
    rarity = None
    if rare:  # the voxel share takes each cell's rarest color (its count in the cloud), ties by priority
        _, inv, counts = np.unique(keys, return_inverse=True, return_counts=True)
        rarity = counts[inv] + prio / (len(prio) + 1.0)
    if bits is not None:  # rarest coarse color (bits dropped), ties by distance to the cell's centroid
        _, inv, counts = np.unique(coarse(keys, bits), return_inverse=True, return_counts=True)
        lo = xyz.min(axis=0)
        size = voxel_size_for(xyz, s, lo) if s else 1.0
        cell = cells_of(xyz, lo, size)
        n = cell.max() + 1
        cent = np.zeros((n, 3))
        np.add.at(cent, cell, xyz)
        cent /= np.bincount(cell, minlength=n)[:, None]
        d = np.sqrt(((xyz - cent[cell]) ** 2).sum(axis=1))
        rarity = counts[inv] + d / (d.max() + 1e-300) * 0.5
    v = voxel(xyz, s, rng, rarity=rarity) if s else np.zeros(0, np.int64)
    rest = np.setdiff1d(np.arange(len(xyz)), v)
    c = rest[prism(keys[rest], t - s, prio[rest], bin_prio)] if t > s else np.zeros(0, np.int64)
    return np.concatenate([v, c])


def octree_order(xyz, rarity, prio, rng, need, kd=False, by_mass=False, by_gap=False) -> np.ndarray:
    """A nested spatial order: cells of a cube over the cloud's bounds, halved every level (an octree), or one
    axis a level (``kd``: x, then y, then z); at each level every occupied cell that no earlier winner lies in
    gives its winner (the smallest ``rarity``, ties by priority), a level's new cells by cell priority, or
    (``by_mass``) the most populous first. The first S points of the order hold one point of each occupied
    cell of the finest level reached: a voxel-like sample at every S (nested). Returned down to the first level
    with at least ``need`` occupied cells. ``kd`` with ``by_mass`` is what ``--space`` computes (SPEC 9; the
    engine anchors its cells at 0, not at the cloud's minimum). ``by_gap``: a level's new cells by the distance
    from their winner to the winner of their parent cell (the point that stood for them until this level),
    the farthest first, ties by mass: a greedy cover of the holes the last, partly listed level leaves."""
    lo = xyz.min(axis=0)
    parent_cell = parent_winner = None
    side = float(np.max(xyz.max(axis=0) - lo)) or 1.0
    taken = np.zeros(len(xyz), bool)
    distinct = len(np.unique(xyz, axis=0))
    order = []
    for level in range(66 if kd else 22):
        if kd:  # one axis halved a level, x then y then z: nested cells, at most twice as many a level
            mv = np.array([1 << ((level + 2) // 3), 1 << ((level + 1) // 3), 1 << (level // 3)])
        else:
            mv = np.array([1 << level] * 3)
        ijk = np.minimum(np.floor((xyz - lo) / side * mv).astype(np.int64), mv - 1)
        m = int(mv.max())
        cells, cell = np.unique((ijk[:, 0] * m + ijk[:, 1]) * m + ijk[:, 2], return_inverse=True)
        cell = cell.ravel()
        n = len(cells)
        by = np.lexsort((prio, rarity, cell))
        first = by[np.concatenate([[True], cell[by][1:] != cell[by][:-1]])]  # each cell's winner
        has = np.zeros(n, bool)
        has[cell[taken]] = True  # cells an earlier winner lies in
        new = first[~has[cell[first]]]
        cp = rng.random(len(new))
        if by_gap and parent_cell is not None:
            gap = np.linalg.norm(xyz[new] - xyz[parent_winner[parent_cell[new]]], axis=1)
            new = new[np.lexsort((cp, -np.bincount(cell, minlength=n)[cell[new]], -gap))]
        elif by_mass:  # the cells holding the most points first, ties by cell priority
            new = new[np.lexsort((cp, -np.bincount(cell, minlength=n)[cell[new]]))]
        else:  # by cell priority
            new = new[np.argsort(cp, kind="stable")]
        taken[new] = True
        order.append(new)
        parent_cell = cell
        parent_winner = np.empty(n, np.int64)
        parent_winner[cell[first]] = first
        if n >= need or n == distinct:
            break
    return np.concatenate(order)


def merged(first: np.ndarray, second: np.ndarray, t: int, a: float) -> np.ndarray:
    """The first ``t`` of the mixture's rank: rank i is ``first``'s next point when round(a (i + 1)) >
    round(a i), else ``second``'s, each skipping points already taken (nested at every t)."""
    out, seen, i1, i2 = [], set(), 0, 0
    for i in range(t):
        if int(math.floor(a * (i + 1) + 0.5)) > int(math.floor(a * i + 0.5)) and i1 < len(first):
            while first[i1] in seen:
                i1 += 1
            p = first[i1]
            i1 += 1
        else:
            while second[i2] in seen:
                i2 += 1
            p = second[i2]
            i2 += 1
        seen.add(p)
        out.append(p)
    return np.asarray(out, np.int64)


def octree_mixture(xyz, keys, t, a, prio, bin_prio, rng, bits=4, nested_rank=True, kd=False,
                   by_mass=False, by_gap=False) -> np.ndarray:
    s = int(math.floor(a * t + 0.5))
    _, inv, counts = np.unique(coarse(keys, bits), return_inverse=True, return_counts=True)
    sp = octree_order(xyz, counts[inv].astype(np.float64), prio, rng, t if nested_rank else max(s, 1), kd=kd,
                      by_mass=by_mass, by_gap=by_gap)
    if nested_rank:
        _, kinv = np.unique(keys, return_inverse=True)
        pr = ranked_order(kinv, prio, bin_prio[np.unique(keys)])
        return merged(sp, pr, t, a)
    v = sp[:s]
    rest = np.setdiff1d(np.arange(len(xyz)), v)
    c = rest[prism(keys[rest], t - s, prio[rest], bin_prio)] if t > s else np.zeros(0, np.int64)
    return np.concatenate([v, c])


def nested(xyz, keys, t, size, prio, bin_prio, rng, rare=False) -> np.ndarray:
    lo = xyz.min(axis=0)
    cell = cells_of(xyz, lo, size)
    ncell = cell.max() + 1
    cell_prio = rng.random(ncell)
    # each cell's quota: PRISM's exact rule over the cells (cells as bins)
    order = ranked_order(cell, prio, cell_prio)[:t]
    quota = np.bincount(cell[order], minlength=ncell)
    # inside each cell: PRISM's exact rule over its color bins (bins of a cell by bin priority, or rarest first)
    ukeys, kinv = np.unique(keys, return_inverse=True)
    if rare:
        global_count = np.bincount(kinv)
        bp = global_count + bin_prio[ukeys] * 0.5  # rarest first, ties by bin priority
    else:
        bp = bin_prio[ukeys]
    j = rounds(cell * len(ukeys) + kinv, prio)  # rounds within each (cell, bin)
    within = np.lexsort((prio, bp[kinv], j, cell))  # by cell, then round, then bin order
    return within[places(cell[within]) < quota[cell[within]]]


def grid_entropy(keys) -> float:
    g = ((keys >> 16 & 255) >> 5) * 64 + ((keys >> 8 & 255) >> 5) * 8 + ((keys & 255) >> 5)
    c = np.bincount(g, minlength=512).astype(np.float64)
    c = c[c > 0] / c.sum()
    return float(-(c * np.log2(c)).sum())


def entropy_of(cells) -> float:
    _, c = np.unique(cells, return_counts=True)
    p = c / c.sum()
    return float(-(p * np.log2(p)).sum())


def hue_sat(keys):
    from prism_stream.evaluate.entropy import hue_sat_cells

    return hue_sat_cells(keys >> 16 & 255, keys >> 8 & 255, keys & 255)


def measure(xyz, keys, tree, sel, h_in) -> dict:
    """CD and HD to the whole cloud, and the entropy gains: rgb-grid (the issue's), and as checks that a
    method does not only fit that grid, the 8-bit triples (rgb8) and hue x saturation (hue-sat)."""
    s = xyz[sel]
    d_cloud, _ = cKDTree(s).query(xyz, workers=-1)  # every point to the sample
    d_sample, _ = tree.query(s, workers=-1)  # every sampled point to the cloud: 0 (a subset)
    return {"cd": float(d_cloud.mean() + d_sample.mean()), "hd": float(max(d_cloud.max(), d_sample.max())),
            "gain": grid_entropy(keys[sel]) - h_in["grid"], "gain_rgb8": entropy_of(keys[sel]) - h_in["rgb8"],
            "gain_hue_sat": entropy_of(hue_sat(keys[sel])) - h_in["hue_sat"], "n": int(len(sel))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ratios", default="0.01,0.1")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--mix", default="0.25,0.5,0.6,0.75")
    ap.add_argument("--sizes", default="1,2,4")
    ap.add_argument("--clouds", default=",".join(CLOUDS))
    ap.add_argument("--coarse-bits", default="2,3,4,5", help="mixq: bits dropped a channel for the rarity")
    ap.add_argument("--octree", default="", help="the nested spatial orders merged with PRISM's rank at these "
                    "shares: oct4, oct4w, kd4, kd4w, kd4g (see octree_order)")
    ap.add_argument("--only-octree", action="store_true", help="P, R, V, mixq and the octree mixtures only")
    ap.add_argument("--json")
    a = ap.parse_args()
    a.coarse_bits = [int(v) for v in a.coarse_bits.split(",") if v.strip()]
    ratios = [float(v) for v in a.ratios.split(",")]
    seeds = [int(v) for v in a.seeds.split(",")]
    mixes = [float(v) for v in a.mix.split(",")]
    sizes = [float(v) for v in a.sizes.split(",")]
    rows = []
    for name in a.clouds.split(","):
        xyz, keys = load(name)
        tree = cKDTree(xyz)
        h_in = {"grid": grid_entropy(keys), "rgb8": entropy_of(keys), "hue_sat": entropy_of(hue_sat(keys))}
        for r in ratios:
            t = int(math.floor(r * len(xyz) + 0.5))
            for seed in seeds:
                t0 = time.perf_counter()
                rng = np.random.default_rng(seed)
                prio = rng.permutation(len(xyz)).astype(np.float64)
                bin_prio = rng.random(1 << 24)
                lo = xyz.min(axis=0)
                vsize = voxel_size_for(xyz, t, lo)
                methods = {"P": prism(keys, t, prio, bin_prio), "R": rng.permutation(len(xyz))[:t],
                           "V": voxel(xyz, t, np.random.default_rng(seed), vsize)}
                for m in [float(v) for v in a.octree.split(",") if v.strip()]:
                    methods[f"oct4 {m:g}"] = octree_mixture(xyz, keys, t, m, prio, bin_prio,
                                                            np.random.default_rng(seed))
                    for label, kw in (("oct4w", {"by_mass": True}), ("kd4", {"kd": True}),
                                     ("kd4w", {"kd": True, "by_mass": True}),
                                     ("kd4g", {"kd": True, "by_gap": True})):
                        methods[f"{label} {m:g}"] = octree_mixture(xyz, keys, t, m, prio, bin_prio,
                                                                 np.random.default_rng(seed), **kw)
                for m in mixes:
                    if not a.only_octree:
                        methods[f"mix {m:g}"] = mixture(xyz, keys, t, m, prio, bin_prio,
                                                        np.random.default_rng(seed))
                        methods[f"mixr {m:g}"] = mixture(xyz, keys, t, m, prio, bin_prio,
                                                         np.random.default_rng(seed), rare=True)
                    for q in a.coarse_bits:
                        methods[f"mixq{q} {m:g}"] = mixture(xyz, keys, t, m, prio, bin_prio,
                                                           np.random.default_rng(seed), bits=q)
                for s in ([] if a.only_octree else sizes):
                    methods[f"nest {s:g}"] = nested(xyz, keys, t, vsize * s, prio, bin_prio,
                                                    np.random.default_rng(seed))
                    methods[f"rare {s:g}"] = nested(xyz, keys, t, vsize * s, prio, bin_prio,
                                                    np.random.default_rng(seed), rare=True)
                got = {k: measure(xyz, keys, tree, v, h_in) for k, v in methods.items()}
                for k, v in got.items():
                    assert v["n"] == t, (name, k, v["n"], t)
                    rows.append({"cloud": name, "ratio": r, "seed": seed, "method": k, **v,
                                 "cd_v": v["cd"] / got["V"]["cd"], "hd_v": v["hd"] / got["V"]["hd"],
                                 "gain_p": v["gain"] / got["P"]["gain"] if got["P"]["gain"] else float("nan"),
                                 "rgb8_p": v["gain_rgb8"] / got["P"]["gain_rgb8"],
                                 "hue_sat_p": v["gain_hue_sat"] / got["P"]["gain_hue_sat"]})
                print(f"{name} r={r} seed={seed}: {len(xyz):,} points, T={t:,}, {time.perf_counter() - t0:.1f} s",
                      flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    table(rows, ratios)


def table(rows, ratios) -> None:
    methods = list(dict.fromkeys(r["method"] for r in rows))
    for r in ratios:
        print(f"\nratio {r}: means over clouds (each cloud's mean over the seeds): CD/V, HD/V, gain/P; the worst "
              "cloud's; and the gains summed over clouds and seeds against P's (rgb-grid, rgb8, hue-sat)")
        print(f"{'method':<10} {'CD/V':>6} {'HD/V':>6} {'gain/P':>7}   {'CD/V max':>8} {'HD/V max':>8} "
              f"{'gain/P min':>10} {'sum gain / sum gain_P':>22} {'rgb8':>8} {'hue-sat':>8}")
        for m in methods:
            sel = [x for x in rows if x["method"] == m and x["ratio"] == r]
            clouds = sorted({x["cloud"] for x in sel})
            per = {c: [x for x in sel if x["cloud"] == c] for c in clouds}
            cd = [np.mean([x["cd_v"] for x in v]) for v in per.values()]
            hd = [np.mean([x["hd_v"] for x in v]) for v in per.values()]
            gp = [np.mean([x["gain_p"] for x in v]) for v in per.values()]
            def pooled(name, ratio_name):
                return sum(x[name] for x in sel) / sum(x[name] / x[ratio_name] for x in sel if x[ratio_name])

            print(f"{m:<10} {np.mean(cd):6.3f} {np.mean(hd):6.3f} {np.mean(gp):7.3f}   {max(cd):8.3f} "
                  f"{max(hd):8.3f} {min(gp):10.3f} {pooled('gain', 'gain_p'):22.3f} "
                  f"{pooled('gain_rgb8', 'rgb8_p'):8.3f} {pooled('gain_hue_sat', 'hue_sat_p'):8.3f}")


if __name__ == "__main__":
    main()
