"""The renderer's view directions at their singular point: a Gaussian exactly at a camera centre.

The torch backend culls such a Gaussian (z = 0 <= near) before it evaluates any direction, and must give
finite, bounded gradients there. (The gsplat backend hands the SH to gsplat, which evaluates colours only
for Gaussians it has not culled; no direction is computed in torch any more.)
"""

from __future__ import annotations

import pytest
import torch

from aesplat.render import render
from aesplat.types import Gaussians

from .scenes import cameras, random_scene


def _at_camera_centres(sh_degree: int) -> tuple[Gaussians, torch.Tensor, torch.Tensor]:
    """Gaussians 0 and 1 sit exactly at the centres of cameras 0 and 1; the rest are an ordinary scene."""
    g = random_scene(12, b=1, sh_degree=sh_degree, seed=5, dtype=torch.float32)
    ext, intr = cameras(1, 2, dtype=torch.float32)
    means = g.means.clone()
    means[0, :2] = ext[0, :, :3, 3]
    return Gaussians(means, g.quats, g.scales, g.opacities, g.sh), ext, intr


def _leaves(g: Gaussians, ext: torch.Tensor) -> list[torch.Tensor]:
    return [t.detach().clone().requires_grad_() for t in (g.means, g.quats, g.scales, g.opacities, g.sh, ext)]


@pytest.mark.parametrize("sh_degree", [1, 3])
def test_torch_render_at_a_camera_centre_has_finite_gradients(sh_degree):
    g, ext, intr = _at_camera_centres(sh_degree)
    leaves = _leaves(g, ext)
    out = render(Gaussians(*leaves[:5]), leaves[5], intr, 16, 20, backend="torch")
    grads = torch.autograd.grad((out.color * torch.rand_like(out.color)).sum(), leaves)
    assert all(torch.isfinite(grad).all() for grad in grads)
    assert grads[0][0, :2].abs().max() < 1e4
