"""Tile binning: which Gaussians touch which screen tiles, in front-to-back order per tile.

Fully vectorised: one ``repeat_interleave`` expands every Gaussian into its bounding box of tiles, one
global depth sort orders the Gaussians, and one stable int32 sort by tile keeps that order inside each tile.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class TileBins:
    """Per-tile lists of projected Gaussians, concatenated.

    order        [K]  projected-Gaussian index of each intersection, grouped by tile, near to far
    starts       [T]  offset of each tile's list in ``order``
    counts       [T]  length of each tile's list
    tiles_x, tiles_y, tile_size, num_cameras
    """

    order: Tensor
    starts: Tensor
    counts: Tensor
    tiles_x: int
    tiles_y: int
    tile_size: int
    num_cameras: int

    @property
    def num_tiles(self) -> int:
        return self.num_cameras * self.tiles_y * self.tiles_x


def bin_gaussians(
    camera: Tensor,  # [M] flat camera index
    means2d: Tensor,  # [M, 2] pixels
    radii: Tensor,  # [M, 2] pixels
    depths: Tensor,  # [M]
    num_cameras: int,
    height: int,
    width: int,
    tile_size: int,
) -> TileBins:
    """Intersect every Gaussian's bounding box with the tile grid and sort the intersections."""
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    device = means2d.device
    with torch.no_grad():
        depth_order = torch.sort(depths, stable=True).indices  # global front-to-back order
        m2 = means2d[depth_order]
        rad = radii[depth_order]
        lo = torch.floor((m2 - rad) / tile_size)
        hi = torch.ceil((m2 + rad) / tile_size)
        x0 = lo[:, 0].clamp(0, tiles_x).long()
        x1 = hi[:, 0].clamp(0, tiles_x).long()
        y0 = lo[:, 1].clamp(0, tiles_y).long()
        y1 = hi[:, 1].clamp(0, tiles_y).long()
        w = x1 - x0
        n_per = w * (y1 - y0)  # [M] tiles touched
        total = int(n_per.sum())
        src = torch.repeat_interleave(torch.arange(m2.shape[0], device=device), n_per, output_size=total)
        first = torch.cumsum(n_per, 0) - n_per
        local = torch.arange(total, device=device) - first[src]
        wi = w[src]
        tx = x0[src] + local % wi.clamp_min(1)
        ty = y0[src] + local // wi.clamp_min(1)
        cam = camera[depth_order][src]
        key = ((cam * tiles_y + ty) * tiles_x + tx).to(torch.int32)
        key_sorted, perm = torch.sort(key, stable=True)
        order = depth_order[src[perm]]
        num_tiles = num_cameras * tiles_y * tiles_x
        counts = torch.bincount(key_sorted.long(), minlength=num_tiles)
        starts = torch.cumsum(counts, 0) - counts
    return TileBins(order, starts, counts, tiles_x, tiles_y, tile_size, num_cameras)
