"""Pinhole cameras in the project's one convention (docs/design.md, "Conventions").

OpenCV axes (x right, y down, z forward); extrinsics are camera-to-world 4x4; intrinsics are 3x3
*normalised* (fx, cx divided by the width, fy, cy by the height); pixel centres sit at (u + 0.5, v + 0.5).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .rotation import invert_pose


def normalize_intrinsics(k_pixels: Tensor, height: int, width: int) -> Tensor:
    """Pixel intrinsics [..., 3, 3] -> normalised intrinsics [..., 3, 3]."""
    k = k_pixels.clone()
    k[..., 0, :] = k[..., 0, :] / width
    k[..., 1, :] = k[..., 1, :] / height
    return k


def denormalize_intrinsics(k_norm: Tensor, height: int, width: int) -> Tensor:
    """Normalised intrinsics [..., 3, 3] -> pixel intrinsics [..., 3, 3]."""
    scale = k_norm.new_tensor([width, height, 1.0])[:, None]
    return k_norm * scale


def fov_to_focal(fov: Tensor) -> Tensor:
    """Field of view (radians) -> normalised focal length 0.5 / tan(fov / 2)."""
    return 0.5 / torch.tan(0.5 * fov)


def focal_to_fov(focal: Tensor) -> Tensor:
    """Normalised focal length -> field of view (radians)."""
    return 2.0 * torch.atan(0.5 / focal)


def intrinsics_from_fov(fov: Tensor, aspect: float = 1.0) -> Tensor:
    """One field of view per camera [...] -> normalised intrinsics [..., 3, 3] of an image of ``aspect`` =
    width / height with square pixels and a centred principal point.

    ``fov`` spans the image's shorter side; square pixels make the longer side's wider. A square image has
    equal horizontal and vertical FOV (fx = fy in normalised units); a 2:1 image has fx = fy / 2.
    """
    if not aspect > 0:
        raise ValueError(f"aspect (width / height) must be > 0, got {aspect}")
    f = fov_to_focal(fov)
    fx, fy = f * min(1.0, 1.0 / aspect), f * min(1.0, aspect)
    zero, one, half = torch.zeros_like(f), torch.ones_like(f), torch.full_like(f, 0.5)
    rows = [fx, zero, half, zero, fy, half, zero, zero, one]
    return torch.stack(rows, dim=-1).reshape(*f.shape, 3, 3)


DEFAULT_FOV = 2.0 * math.atan(0.5)  # normalised focal length 1: the camera head's initial FOV


def pixel_grid(height: int, width: int, device=None, dtype=torch.float32, offset: float = 0.5) -> Tensor:
    """Normalised coordinates of pixel centres, [H, W, 2] as (x, y) in [0, 1]; ``offset`` 0 gives the pixels'
    top-left corners (u / W, v / H), where NAS3R unprojects its depth maps."""
    ys = (torch.arange(height, device=device, dtype=dtype) + offset) / height
    xs = (torch.arange(width, device=device, dtype=dtype) + offset) / width
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx, gy], dim=-1)


def unproject_depth_camera(depth: Tensor, intrinsics: Tensor, offset: float = 0.5) -> Tensor:
    """z-depth [B, V, H, W] -> points in each camera's frame [B, V, H, W, 3], each pixel's point on the ray
    through (u + offset, v + offset)."""
    h, w = depth.shape[-2:]
    grid = pixel_grid(h, w, device=depth.device, dtype=depth.dtype, offset=offset)
    fx, fy = intrinsics[..., 0, 0, None, None], intrinsics[..., 1, 1, None, None]
    cx, cy = intrinsics[..., 0, 2, None, None], intrinsics[..., 1, 2, None, None]
    x = (grid[..., 0] - cx) / fx * depth
    y = (grid[..., 1] - cy) / fy * depth
    return torch.stack([x, y, depth], dim=-1)


def transform_points(pose: Tensor, points: Tensor) -> Tensor:
    """Apply 4x4 transforms [..., 4, 4] to points [..., N, 3] (leading shapes broadcast)."""
    return points @ pose[..., :3, :3].transpose(-1, -2) + pose[..., None, :3, 3]


def unproject_depth(depth: Tensor, intrinsics: Tensor, extrinsics: Tensor, offset: float = 0.5) -> Tensor:
    """z-depth [B, V, H, W] with intrinsics [B, V, 3, 3] and camera-to-world [B, V, 4, 4] -> world points
    [B, V, H, W, 3] (``offset``: as :func:`unproject_depth_camera`)."""
    b, v, h, w = depth.shape
    cam = unproject_depth_camera(depth, intrinsics, offset).reshape(b, v, h * w, 3)
    return transform_points(extrinsics, cam).reshape(b, v, h, w, 3)


def project_points(
    points: Tensor,  # [B, N, 3] world
    intrinsics: Tensor,  # [B, V, 3, 3] normalised
    extrinsics: Tensor,  # [B, V, 4, 4] camera-to-world
    height: int,
    width: int,
    eps: float = 1e-6,
) -> tuple[Tensor, Tensor, Tensor]:
    """Project world points into every camera.

    Returns uv [B, V, N, 2] in pixels (pixel centres at +0.5), z-depth [B, V, N] and valid [B, V, N]
    (z > eps and inside the image). Points at or behind the camera get a safe denominator, so uv stays
    finite (and meaningless: check ``valid``).
    """
    cam = transform_points(invert_pose(extrinsics), points[:, None])  # [B, V, N, 3]
    z = cam[..., 2]
    in_front = z > eps
    z_safe = torch.where(in_front, z, torch.full_like(z, eps))
    k = intrinsics[..., None, :, :]
    u = (k[..., 0, 0] * cam[..., 0] / z_safe + k[..., 0, 2]) * width
    v = (k[..., 1, 1] * cam[..., 1] / z_safe + k[..., 1, 2]) * height
    uv = torch.stack([u, v], dim=-1)
    inside = (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
    return uv, z, in_front & inside
