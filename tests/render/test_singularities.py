"""Both renderers' view directions at their singular point: a Gaussian exactly at a camera centre.

The torch backend culls such a Gaussian (z = 0 <= near) before it evaluates any direction; the gsplat
backend evaluates the SH colour of every Gaussian for every camera before gsplat culls, so its direction
mean - camera centre can be exactly zero. Both must give finite, bounded gradients there.
"""

from __future__ import annotations

import pytest
import torch

from aesplat.render import fold_cameras, render
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
def test_gsplat_fold_at_a_camera_centre_has_zero_direction_and_bounded_gradients(sh_degree):
    g, ext, intr = _at_camera_centres(sh_degree)
    leaves = _leaves(g, ext)
    folded = fold_cameras(Gaussians(*leaves[:5]), leaves[5], intr, sh_degree)
    colors = folded.colors.reshape(2, 12, 3)  # [V, N, 3]
    # Direction 0: only the DC band contributes, as if the higher bands were absent.
    dc_only = fold_cameras(g, ext, intr, 0).colors.reshape(2, 12, 3)
    torch.testing.assert_close(colors[0, 0], dc_only[0, 0])
    torch.testing.assert_close(colors[1, 1], dc_only[1, 1])
    wrt = {"means": leaves[0], "sh": leaves[4], "extrinsics": leaves[5]}  # what the colours depend on
    grads = torch.autograd.grad((colors * torch.randn_like(colors)).sum(), list(wrt.values()))
    for name, grad in zip(wrt, grads):
        assert torch.isfinite(grad).all(), name
        assert grad.abs().max() < 1e4, f"{name}: {grad.abs().max():.3g}"  # the old clamp gave ~1e19


@pytest.mark.parametrize("sh_degree", [1, 3])
def test_torch_render_at_a_camera_centre_has_finite_gradients(sh_degree):
    g, ext, intr = _at_camera_centres(sh_degree)
    leaves = _leaves(g, ext)
    out = render(Gaussians(*leaves[:5]), leaves[5], intr, 16, 20, backend="torch")
    grads = torch.autograd.grad((out.color * torch.rand_like(out.color)).sum(), leaves)
    assert all(torch.isfinite(grad).all() for grad in grads)
    assert grads[0][0, :2].abs().max() < 1e4
