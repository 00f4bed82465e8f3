"""XY tiles with an overlap: the evaluation's out-of-core neighbour searches (NSS normals, outlier removal).

A :class:`Tiling` cuts the cloud's bounding box into a grid of about
``tile_points`` points a tile; :func:`spill_tiles` writes every point to the
file of its own tile ("core") and of every tile whose overlap it lies in,
so each tile can be loaded alone with the neighbours of its border points.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from .cloud import Cloud


@dataclass(frozen=True)
class Tiling:
    """An XY grid of tiles, each read with an overlap so border normals see their neighbours."""

    lo: np.ndarray
    width: np.ndarray  # tile width in x and y
    shape: tuple  # (gx, gy)
    margin: np.ndarray  # overlap in x and y

    @staticmethod
    def plan(lo, hi, points: int, tile_points: int, overlap: float) -> "Tiling":
        ext = np.maximum(np.asarray(hi[:2]) - np.asarray(lo[:2]), 1e-12)
        tiles = max(1, math.ceil(points / max(1, tile_points)))
        gx = max(1, round(math.sqrt(tiles * ext[0] / ext[1])))
        gy = max(1, math.ceil(tiles / gx))
        width = ext / np.array([gx, gy])
        return Tiling(np.asarray(lo[:2], np.float64), width, (gx, gy), width * overlap)

    @property
    def count(self) -> int:
        return self.shape[0] * self.shape[1]

    def cell(self, xy: np.ndarray) -> np.ndarray:
        ij = np.floor((xy - self.lo) / self.width).astype(np.int64)
        np.clip(ij, 0, np.array(self.shape) - 1, out=ij)
        return ij

    def members(self, xy: np.ndarray):
        """(tile, point index, is core) for every tile whose core or overlap holds each point."""
        core = self.cell(xy)
        out = []
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                t = core + np.array([dx, dy])
                ok = (t[:, 0] >= 0) & (t[:, 0] < self.shape[0]) & (t[:, 1] >= 0) & (t[:, 1] < self.shape[1])
                if dx or dy:
                    tlo = self.lo + t * self.width - self.margin
                    thi = self.lo + (t + 1) * self.width + self.margin
                    ok &= np.all((xy >= tlo) & (xy <= thi), axis=1)
                idx = np.flatnonzero(ok)
                out.append((t[idx, 0] * self.shape[1] + t[idx, 1], idx, np.full(len(idx), not (dx or dy))))
        return out


SPILL = np.dtype([("xyz", "<f8", 3), ("gid", "<i8"), ("core", "?")])


def spill_tiles(cloud: Cloud, tiling: Tiling, folder: str) -> tuple[list[str], int]:
    """One pass writing each point (33 bytes) to the file of every tile whose core or overlap holds it.

    Returns the tile files' paths (a tile with no point has no file) and the records written.
    """
    paths = [os.path.join(folder, f"tile-{t}.bin") for t in range(tiling.count)]
    spilled = 0
    for c in cloud.chunks():
        gid = c.offset + np.arange(len(c), dtype=np.int64)
        groups = tiling.members(c.xyz[:, :2])
        tiles = np.concatenate([g[0] for g in groups])
        rows = np.concatenate([g[1] for g in groups])
        core = np.concatenate([g[2] for g in groups])
        order = np.argsort(tiles, kind="stable")
        tiles, rows, core = tiles[order], rows[order], core[order]
        rec = np.empty(len(rows), SPILL)
        rec["xyz"], rec["gid"], rec["core"] = c.xyz[rows], gid[rows], core
        spilled += len(rows)
        cuts = np.flatnonzero(np.diff(tiles)) + 1
        for part in np.split(np.arange(len(tiles)), cuts):
            if len(part):
                with open(paths[int(tiles[part[0]])], "ab") as f:
                    f.write(rec[part].tobytes())  # a full disk raises ENOSPC (numpy's tofile: a short write, no errno)
    return paths, spilled
