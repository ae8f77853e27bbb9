"""Small random scenes and cameras shared by the render tests, and renders of them with their gradients, by the
torch backend and by the reference."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from aesplat.geometry import intrinsics_from_fov, make_pose, quat_to_matrix
from aesplat.render import render
from aesplat.types import Gaussians

from .reference import reference_render

H, W = 20, 28  # the image size of the comparisons


def random_scene(
    n: int = 24,
    b: int = 1,
    sh_degree: int = 1,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
    spread: float = 0.6,
) -> Gaussians:
    """Gaussians in front of a camera at the origin looking down +z (centres around z = 3)."""
    gen = torch.Generator().manual_seed(seed)
    means = (torch.rand(b, n, 3, generator=gen, dtype=dtype) - 0.5) * 2 * spread
    means[..., 2] += 3.0
    return Gaussians(
        means=means,
        quats=torch.randn(b, n, 4, generator=gen, dtype=dtype),
        scales=torch.rand(b, n, 3, generator=gen, dtype=dtype) * 0.12 + 0.03,
        opacities=torch.rand(b, n, generator=gen, dtype=dtype) * 0.9 + 0.05,
        sh=torch.randn(b, n, (sh_degree + 1) ** 2, 3, generator=gen, dtype=dtype) * 0.4,
    )


def cameras(
    b: int = 1, v: int = 2, dtype: torch.dtype = torch.float64, fov_deg: float = 60.0
) -> tuple[Tensor, Tensor]:
    """Camera-to-world poses [B, V, 4, 4] (view 0 the identity, the others shifted and slightly turned) and
    normalised intrinsics [B, V, 3, 3] with a slightly off-centre principal point for the later views."""
    poses, ks = [], []
    for i in range(v):
        axis_angle = torch.tensor([0.02 * i, -0.05 * i, 0.01 * i], dtype=dtype)
        half = axis_angle.norm() / 2
        q = torch.cat([torch.cos(half)[None], axis_angle / max(axis_angle.norm(), 1e-12) * torch.sin(half)])
        poses.append(make_pose(quat_to_matrix(q), torch.tensor([0.15 * i, -0.05 * i, 0.02 * i], dtype=dtype)))
        k = intrinsics_from_fov(torch.tensor(math.radians(fov_deg + 5 * i), dtype=dtype))
        k[0, 2] += 0.02 * i
        k[1, 1] *= 1 + 0.05 * i
        ks.append(k)
    ext = torch.stack(poses)[None].expand(b, v, 4, 4).clone()
    intr = torch.stack(ks)[None].expand(b, v, 3, 3).clone()
    return ext, intr


def leaf_tensors(g: Gaussians, ext: Tensor, intr: Tensor, bg: Tensor, dtype: torch.dtype) -> list[Tensor]:
    """The scene's tensors, cameras and background as fresh ``dtype`` leaves that require gradients."""
    tensors = [g.means, g.quats, g.scales, g.opacities, g.sh, ext, intr, bg]
    return [t.detach().clone().to(dtype).requires_grad_() for t in tensors]


def outputs_and_grads(fn, leaves: list[Tensor], weights: list[Tensor]) -> tuple[list[Tensor], list[Tensor]]:
    """``fn``'s (colour, depth, alpha) on ``leaves`` and the gradients of their ``weights``-weighted sum,
    both float64."""
    g = Gaussians(*leaves[:5])
    outs = fn(g, *leaves[5:])
    loss = sum((o * w.to(o.dtype)).sum() for o, w in zip(outs, weights))
    grads = torch.autograd.grad(loss, leaves)
    return [o.detach().double() for o in outs], [x.double() for x in grads]


def torch_fn(**options):
    """A render of H x W by the torch backend with ``options`` -> (colour, depth, alpha)."""

    def fn(g, ext, intr, bg):
        out = render(g, ext, intr, H, W, background=bg, backend="torch", **options)
        return out.color, out.depth, out.alpha

    return fn


def reference_fn(g, ext, intr, bg):
    return reference_render(g, ext, intr, H, W, bg)
