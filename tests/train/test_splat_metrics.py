"""Point lattice or 3D scene: the opaque and sub-pixel shares, the fusion gain and the transfer gain tell a
screen-space lattice of tiny opaque Gaussians from Gaussians that cover their pixels."""

from __future__ import annotations

import math

import pytest
import torch

from aesplat.geometry import intrinsics_from_fov, rgb_to_sh_dc, unproject_depth
from aesplat.render import render
from aesplat.train.metrics import psnr
from aesplat.train.splat_metrics import (
    fusion_gain,
    gaussian_shares,
    projected_size,
    transfer_gain,
    view_gaussians,
)
from aesplat.types import Gaussians

SIZE, DEPTH = 16, 2.0


def _texture(size: int) -> torch.Tensor:
    """A smooth colour field over the image [3, size, size] (pixel centres), the same at any size."""
    v, u = torch.meshgrid((torch.arange(size) + 0.5) / size, (torch.arange(size) + 0.5) / size, indexing="ij")
    return torch.stack([0.5 + 0.4 * torch.sin(2 * math.pi * u), 0.5 + 0.4 * torch.cos(2 * math.pi * v),
                        0.3 + 0.4 * u * v])  # fmt: skip


def _plane(pixels: float, opacity: float) -> tuple[Gaussians, torch.Tensor, torch.Tensor, torch.Tensor]:
    """One Gaussian per pixel of a fronto-parallel plane at DEPTH seen by camera 0 (the identity), each
    ``pixels`` pixels wide, coloured by the texture: Gaussians, depth [1, 1, S, S], extrinsics, intrinsics."""
    k = intrinsics_from_fov(torch.tensor([[math.radians(50.0)]]))
    e = torch.eye(4)[None, None]
    depth = torch.full((1, 1, SIZE, SIZE), DEPTH)
    means = unproject_depth(depth, k, e).reshape(1, -1, 3)
    n = means.shape[1]
    scale = pixels * DEPTH / (k[0, 0, 0, 0].item() * SIZE)
    colours = rgb_to_sh_dc(_texture(SIZE).flatten(1).T)[None, :, None]
    g = Gaussians(means, torch.tensor([1.0, 0, 0, 0]).expand(1, n, 4), torch.full((1, n, 3), scale),
                  torch.full((1, n), opacity), colours)  # fmt: skip
    return g, depth, e, k


def _renderer(mode: str):
    def fn(g, e, k, h, w):
        return render(g, e, k, h, w, backend="torch", rasterize_mode=mode)

    return fn


def test_shares_count_opaque_and_sub_pixel_gaussians():
    g, depth, _, k = _plane(1.0, 0.5)
    size = projected_size(g.scales, depth, k)
    torch.testing.assert_close(size, torch.ones_like(size), rtol=1e-5, atol=0)
    scales = g.scales.clone()
    scales[0, : SIZE * SIZE // 4] *= 0.05  # a quarter at 0.05 px
    opacities = g.opacities.clone()
    opacities[0, :10] = 0.995
    shares = gaussian_shares(Gaussians(g.means, g.quats, scales, opacities, g.sh), depth, k)
    assert shares["subpixel_share"].item() == pytest.approx(0.25)
    assert shares["opaque_share"].item() == pytest.approx(10 / (SIZE * SIZE))


@pytest.mark.parametrize(("pixels", "opacity", "mode", "low", "high"), [
    (1e-4, 0.999, "classic", -math.inf, -2.0),  # a lattice: upsampling its own render beats rendering it larger
    (1.0, 0.999, "antialiased", -0.5, math.inf),  # Gaussians that cover their pixels render at 2x as well
])  # fmt: skip
def test_transfer_gain_tells_a_lattice_from_a_surface(pixels, opacity, mode, low, high):
    g, _, e, k = _plane(pixels, opacity)
    fn = _renderer(mode)
    small = fn(g, e, k, SIZE, SIZE).color
    truth = _texture(2 * SIZE)[None, None]
    out = transfer_gain(fn, g, e, k, small, truth)
    assert low < out["transfer_gain_db"].item() < high
    torch.testing.assert_close(out["transfer_gain_db"], out["psnr_transfer"] - out["psnr_upsampled"])


def test_fusion_gain_is_what_the_second_view_adds():
    """Two views' Gaussians, each the left or right half of the plane: together they render the target,
    each alone half of it; with the second view's Gaussians transparent nothing is gained."""
    g, _, e, k = _plane(1.0, 0.999)
    left = (g.means[0, :, 0] < 0).nonzero().squeeze(1)
    right = (g.means[0, :, 0] >= 0).nonzero().squeeze(1)
    g2 = g.apply(lambda t: torch.cat([t[:, left], t[:, right]], dim=1))
    fn = _renderer("antialiased")
    truth = _texture(SIZE)[None, None]
    assert torch.equal(view_gaussians(g2, 1, 2).means, g.means[:, right])
    fused = fn(g2, e, k, SIZE, SIZE).color
    fused_psnr = psnr(fused[0], truth[0])
    gain = fusion_gain(fn, g2, 2, e, k, truth, fused_psnr)
    assert gain.item() > 3.0
    opacities = g2.opacities.clone()
    opacities[:, len(left) :] = 1e-4
    g3 = Gaussians(g2.means, g2.quats, g2.scales, opacities, g2.sh)
    alone = psnr(fn(g3, e, k, SIZE, SIZE).color[0], truth[0])
    assert fusion_gain(fn, g3, 2, e, k, truth, alone).item() == pytest.approx(0.0, abs=1e-6)
