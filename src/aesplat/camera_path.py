"""Cameras between cameras: a path through the predicted input cameras (``interpolate_cameras``, rotations
slerped), and a camera as the JSON record ``cameras.json`` holds (``camera_record``)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .geometry import (
    denormalize_intrinsics,
    focal_to_fov,
    invert_pose,
    make_pose,
    matrix_to_quat,
    quat_to_matrix,
)


def slerp(q0: Tensor, q1: Tensor, t: Tensor) -> Tensor:
    """Spherical interpolation of unit quaternions (w, x, y, z): q0, q1 [F, 4] at times t [F] -> [F, 4]."""
    dot = (q0 * q1).sum(-1, keepdim=True)  # [F, 1]
    q1 = torch.where(dot < 0, -q1, q1)  # the shorter way round
    theta = torch.acos(dot.abs().clamp(max=1.0))
    t = t[:, None]
    near = theta < 1e-4  # nearly equal rotations: linear interpolation, no 0 / 0
    sin = torch.where(near, torch.ones_like(theta), torch.sin(theta))
    w0 = torch.where(near, 1 - t, torch.sin((1 - t) * theta) / sin)
    w1 = torch.where(near, t, torch.sin(t * theta) / sin)
    q = w0 * q0 + w1 * q1
    return q / q.norm(dim=-1, keepdim=True)


def interpolate_cameras(extrinsics: Tensor, intrinsics: Tensor, frames: int) -> tuple[Tensor, Tensor]:
    """A path through V cameras in order: extrinsics [V, 4, 4] (camera-to-world), intrinsics [V, 3, 3].

    Rotations are slerped, centres and intrinsics interpolated linearly, ``frames`` poses in all (the first
    and last are the first and last input cameras). Returns extrinsics [F, 4, 4] and intrinsics [F, 3, 3].
    """
    v = extrinsics.shape[0]
    if v < 2:
        raise ValueError("a camera path needs at least two cameras")
    if frames < 2:
        raise ValueError(f"a camera path needs at least two frames, got {frames}")
    s = torch.linspace(0, v - 1, frames, dtype=extrinsics.dtype, device=extrinsics.device)  # [F]
    seg = s.floor().long().clamp(max=v - 2)
    t = s - seg  # [F] position within the segment
    quats = matrix_to_quat(extrinsics[:, :3, :3])  # [V, 4]
    rots = quat_to_matrix(slerp(quats[seg], quats[seg + 1], t))  # [F, 3, 3]
    centres = extrinsics[:, :3, 3]
    tt = t[:, None]
    trans = (1 - tt) * centres[seg] + tt * centres[seg + 1]  # [F, 3]
    tk = t[:, None, None]
    intr = (1 - tk) * intrinsics[seg] + tk * intrinsics[seg + 1]  # [F, 3, 3]
    return make_pose(rots, trans), intr


def camera_record(extrinsics: Tensor, intrinsics: Tensor, height: int, width: int) -> dict:
    """A JSON-able description of one camera: c2w / w2c 4x4, normalised and pixel 3x3 intrinsics, FOVs."""
    k_pix = denormalize_intrinsics(intrinsics, height, width)
    fov_x = focal_to_fov(intrinsics[0, 0]).item()
    fov_y = focal_to_fov(intrinsics[1, 1]).item()
    return {
        "camera_to_world": extrinsics.tolist(),
        "world_to_camera": invert_pose(extrinsics).tolist(),
        "intrinsics_normalized": intrinsics.tolist(),
        "intrinsics_pixels": k_pix.tolist(),
        "width": width,
        "height": height,
        "fov_x_deg": math.degrees(fov_x),
        "fov_y_deg": math.degrees(fov_y),
    }
