"""The rasterizer benchmark's reference workload: pixel-aligned Gaussians from two context views.

A plausible indoor depth map (a slanted back wall, a floor and two boxes) is unprojected from two context
cameras, one Gaussian per pixel, sized to about one pixel footprint, and rendered into a target camera
between them. Built from a seed, no files.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from aesplat.geometry import intrinsics_from_fov, make_pose, matrix_to_quat, quat_to_matrix, unproject_depth
from aesplat.types import Gaussians


def _yaw_pose(yaw: float, x: float) -> Tensor:
    half = torch.tensor(yaw / 2)
    q = torch.stack([torch.cos(half), torch.zeros(()), torch.sin(half), torch.zeros(())])
    return make_pose(quat_to_matrix(q), torch.tensor([x, 0.0, 0.0]))


def room_depth(height: int, width: int, shift: float) -> Tensor:
    """z-depth [H, W] of a room seen from the front: wall at 4-5 m, floor below, two boxes."""
    v, u = torch.meshgrid(torch.linspace(-1, 1, height), torch.linspace(-1, 1, width), indexing="ij")
    wall = 4.5 + 0.5 * (u + shift) + 0.1 * torch.sin(6 * v)
    floor = torch.where(v > 0.05, 1.2 / (v - 0.05 + 1e-3).clamp_min(0.25), torch.full_like(v, 1e9))
    depth = torch.minimum(wall, floor)
    box1 = ((u + shift - 0.4).abs() < 0.25) & ((v - 0.2).abs() < 0.3)
    box2 = ((u + shift + 0.5).abs() < 0.15) & ((v + 0.1).abs() < 0.2)
    depth = torch.where(box1, torch.full_like(depth, 2.5) + 0.3 * u, depth)
    return torch.where(box2, torch.full_like(depth, 3.2), depth)


def reference_workload(
    size: int = 224, sh_degree: int = 4, views: int = 2, scale_factor: float = 1.0, seed: int = 0
) -> tuple[Gaussians, Tensor, Tensor]:
    """Gaussians ([1, views * size^2]) plus target extrinsics [1, 1, 4, 4] and intrinsics [1, 1, 3, 3]."""
    gen = torch.Generator().manual_seed(seed)
    fov = math.radians(60.0)
    ctx_poses = torch.stack([_yaw_pose(0.08 * (i - 0.5), 0.3 * (i - 0.5)) for i in range(views)])[None]
    intr = intrinsics_from_fov(torch.full((1, views), fov))
    depth = torch.stack([room_depth(size, size, 0.1 * (i - 0.5)) for i in range(views)])[None]
    means = unproject_depth(depth, intr, ctx_poses).reshape(1, -1, 3)
    n = means.shape[1]
    footprint = (depth / (intr[..., 0, 0, None, None] * size)).reshape(1, n, 1)  # metres per pixel
    scales = footprint * scale_factor * (0.6 + 0.8 * torch.rand(1, n, 3, generator=gen))
    quats = matrix_to_quat(quat_to_matrix(torch.randn(1, n, 4, generator=gen)))
    opacities = 0.2 + 0.79 * torch.rand(1, n, generator=gen)
    k = (sh_degree + 1) ** 2
    sh = torch.randn(1, n, k, 3, generator=gen) * 0.05
    sh[:, :, 0] = torch.randn(1, n, 3, generator=gen) * 0.8
    target = _yaw_pose(0.02, 0.05)[None, None]
    return Gaussians(means, quats, scales, opacities, sh), target, intrinsics_from_fov(torch.full((1, 1), fov))
