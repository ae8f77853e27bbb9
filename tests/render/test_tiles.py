"""Tile binning: the reach test that drops unreachable (Gaussian, tile) pairs is exact and conservative."""

from __future__ import annotations

import math

import torch

from aesplat.render.composite import composite
from aesplat.render.projection import project_gaussians
from aesplat.render.tiles import _reaches_tile, bin_gaussians

from .scenes import cameras, random_scene


def _pixel_min_sigma(rows, src, tx, ty, tile_size):
    """min over the tile's pixel centres of sigma, pixel by pixel (float64)."""
    mx, my, a, b, c, _ = rows.double()[src].unbind(-1)
    u = torch.arange(tile_size, dtype=torch.float64) + 0.5
    best = torch.full_like(mx, math.inf)
    for j in range(tile_size):
        dx = (tx.double() * tile_size)[:, None] + u[None] - mx[:, None]
        dy = (ty.double() * tile_size + u[j] - my)[:, None]
        sigma = 0.5 * a[:, None] * dx * dx + b[:, None] * dx * dy + 0.5 * c[:, None] * dy * dy
        best = torch.minimum(best, sigma.amin(1))
    return best


def _rect_min_sigma(rows, src, tx, ty, tile_size):
    """min of sigma over the rectangle spanned by the pixel centres: 0 when the mean is inside, else the
    smallest of the four edges' 1D minima (float64)."""
    mx, my, a, b, c, _ = rows.double()[src].unbind(-1)
    x_lo, y_lo = tx.double() * tile_size + 0.5 - mx, ty.double() * tile_size + 0.5 - my
    x_hi, y_hi = x_lo + tile_size - 1, y_lo + tile_size - 1
    sigma = lambda dx, dy: 0.5 * a * dx * dx + b * dx * dy + 0.5 * c * dy * dy  # noqa: E731
    edges = [sigma(x, torch.clamp(-b * x / c, y_lo, y_hi)) for x in (x_lo, x_hi)]
    edges += [sigma(torch.clamp(-b * y / a, x_lo, x_hi), y) for y in (y_lo, y_hi)]
    inside = (x_lo <= 0) & (x_hi >= 0) & (y_lo <= 0) & (y_hi >= 0)
    return torch.where(inside, 0.0, torch.stack(edges).amin(0))


def test_reach_test_keeps_every_pair_that_reaches_the_threshold_and_drops_the_rest():
    gen = torch.Generator().manual_seed(0)
    n = 4000
    means = torch.rand(n, 2, generator=gen, dtype=torch.float64) * 64
    # random SPD conics, from round to very elongated (condition numbers up to 1e4)
    angle = torch.rand(n, generator=gen, dtype=torch.float64) * math.pi
    s1 = 10 ** (torch.rand(n, generator=gen, dtype=torch.float64) * 2 - 2.5)
    s2 = s1 * 10 ** (torch.rand(n, generator=gen, dtype=torch.float64) * 4)
    cos, sin = angle.cos(), angle.sin()
    a, b, c = s1 * cos**2 + s2 * sin**2, (s1 - s2) * cos * sin, s1 * sin**2 + s2 * cos**2
    opacity = torch.rand(n, generator=gen, dtype=torch.float64) * 0.99 + 0.01
    rows = torch.stack([means[:, 0], means[:, 1], a, b, c, opacity], -1)
    src = torch.arange(n).repeat_interleave(9)
    offset = torch.arange(9).repeat(n)
    tile_size = 8
    tx = (means[src, 0] // tile_size + offset % 3 - 1).to(torch.int32)
    ty = (means[src, 1] // tile_size + offset // 3 - 1).to(torch.int32)

    keep = _reaches_tile(rows, src, tx, ty, tile_size, 1 / 255)
    at_pixels = opacity[src] * torch.exp(-_pixel_min_sigma(rows, src, tx, ty, tile_size))
    assert bool(keep[at_pixels >= 1 / 255].all()), "a pair that reaches 1/255 at some pixel was dropped"
    # The test is exact for the rectangle of pixel centres, up to its 1 % margin: every pair that stays
    # clearly below the threshold there goes.
    in_rect = opacity[src] * torch.exp(-_rect_min_sigma(rows, src, tx, ty, tile_size))
    assert not bool(keep[in_rect < (1 / 255) * 0.98].any())
    assert bool(keep[in_rect >= 1 / 255].all())
    assert 0.2 < float((~keep).float().mean()) < 0.9  # the scene exercises both outcomes


def test_reach_test_keeps_pairs_with_non_finite_sigma():
    rows = torch.tensor([[4.0, 4.0, 0.0, 0.0, 0.0, 0.5], [100.0, 4.0, math.nan, 0.0, 1.0, 0.5]])
    keep = _reaches_tile(rows, torch.tensor([0, 1]), torch.tensor([3, 3]), torch.tensor([0, 0]), 8, 1 / 255)
    assert keep.tolist() == [True, True]


def test_dropping_unreachable_tiles_leaves_the_image_unchanged_and_shortens_the_lists():
    g = random_scene(n=300, sh_degree=1, seed=3, dtype=torch.float32, spread=1.2)
    ext, intr = cameras(v=2, dtype=torch.float32)
    h = w = 48
    with torch.no_grad():
        proj, _ = project_gaussians(g, ext, intr, h, w, 1)
        args = (proj.camera, proj.means2d, proj.radii, proj.depths, 2, h, w, 8)
        boxes = bin_gaussians(*args)
        reached = bin_gaussians(*args, conics=proj.conics, opacities=proj.opacities)
        assert reached.order.numel() < 0.95 * boxes.order.numel()
        colour = [
            composite(proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths, bins, h, w)
            for bins in (boxes, reached)
        ]
    for full, culled in zip(colour[0], colour[1], strict=True):
        torch.testing.assert_close(culled, full, atol=1e-6, rtol=0)
