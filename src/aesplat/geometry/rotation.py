"""Rotations and poses: 6D rotations, quaternions (w, x, y, z), homogeneous translations, covariances.

Pure functions, any leading batch shape, safe at degenerate inputs (no NaN in values or gradients).

Square roots and divisions near zero are guarded with a ``where`` *before* the singular operation, never
with a clamp alone: the derivative of ``clamp`` at its bound, and autograd's handling of a zero gradient
times an infinite local derivative, differ between torch releases (``sqrt(clamp_min(x, 0))`` at x = 0 gives
a zero gradient on torch 2.14 and NaN on 2.11 / 2.13).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.geometry.conversions import rotation_matrix_to_quaternion
from torch import Tensor

EPS = 1e-8


def safe_norm(x: Tensor, dim: int = -1, keepdim: bool = False, eps: float = EPS) -> Tensor:
    """Euclidean norm, ``eps`` (with a zero gradient) where it would be below ``eps``; finite backward
    everywhere, the zero vector included."""
    n2 = (x * x).sum(dim=dim, keepdim=keepdim)
    ok = n2 > eps * eps
    return torch.where(ok, torch.where(ok, n2, torch.ones_like(n2)).sqrt(), torch.full_like(n2, eps))


def safe_normalize(x: Tensor, dim: int = -1) -> Tensor:
    """x / |x| along ``dim``; a zero (or subnormal) vector maps to zero with a zero gradient.

    The guard is the dtype's smallest normal number, so any vector that is not (numerically) zero is
    normalised exactly: this is for directions such as Gaussian centre minus camera centre.
    """
    n2 = (x * x).sum(dim=dim, keepdim=True)
    ok = n2 > torch.finfo(x.dtype).tiny
    return torch.where(ok, x * torch.rsqrt(torch.where(ok, n2, torch.ones_like(n2))), torch.zeros_like(x))


def _fallback_axis(v: Tensor) -> Tensor:
    """A unit axis that is far from parallel to ``v`` (the coordinate axis of its smallest component)."""
    idx = v.abs().argmin(dim=-1, keepdim=True)
    # A comparison, not F.one_hot: one_hot reads the indices' range on the host (a GPU synchronisation).
    return (idx == torch.arange(3, device=v.device)).to(v.dtype)


def rot6d_to_matrix(d6: Tensor) -> Tensor:
    """6D rotation (two rows, Zhou et al.) -> rotation matrix by Gram-Schmidt.

    d6: [..., 6] -> [..., 3, 3] with det +1. Degenerate inputs (a zero first vector, or a second vector
    parallel to the first) fall back to a valid orthonormal completion instead of producing NaN.
    """
    a1, a2 = d6[..., :3], d6[..., 3:]
    n1 = safe_norm(a1, keepdim=True)
    ex = torch.zeros_like(a1)
    ex[..., 0] = 1.0
    b1 = torch.where(n1 > 1e-6, a1 / n1, ex)
    r = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    nr = safe_norm(r, keepdim=True)
    scale = safe_norm(a2, keepdim=True).clamp_min(1.0)
    alt = _fallback_axis(b1)
    alt = alt - (b1 * alt).sum(-1, keepdim=True) * b1
    alt = alt / safe_norm(alt, keepdim=True)
    b2 = torch.where(nr > 1e-6 * scale, r / nr, alt)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-2)


def matrix_to_rot6d(rot: Tensor) -> Tensor:
    """Rotation matrix [..., 3, 3] -> 6D representation [..., 6] (its first two rows)."""
    return rot[..., :2, :].reshape(*rot.shape[:-2], 6)


def homogeneous_to_translation(t4: Tensor, eps: float = 1e-3) -> Tensor:
    """4D homogeneous translation [..., 4] -> 3D [..., 3] as xyz / w, with w = softplus(raw) + eps > 0."""
    w = F.softplus(t4[..., 3:]) + eps
    return t4[..., :3] / w


def make_pose(rot: Tensor, trans: Tensor) -> Tensor:
    """Rotation [..., 3, 3] and translation [..., 3] -> homogeneous 4x4 [..., 4, 4]."""
    top = torch.cat([rot, trans[..., None]], dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def invert_pose(pose: Tensor) -> Tensor:
    """Inverse of a rigid 4x4 transform [..., 4, 4] (transpose the rotation, no general inverse)."""
    rot_t = pose[..., :3, :3].transpose(-1, -2)
    trans = -(rot_t @ pose[..., :3, 3:])[..., 0]
    return make_pose(rot_t, trans)


def relative_to_first(extrinsics: Tensor) -> Tensor:
    """Express camera-to-world poses [B, V, 4, 4] in the frame of view 0 (view 0 becomes the identity)."""
    rel = invert_pose(extrinsics[:, :1]) @ extrinsics
    eye = torch.eye(4, dtype=rel.dtype, device=rel.device)
    return torch.cat([eye.expand_as(rel[:, :1]), rel[:, 1:]], dim=1)


def safe_unit_quat(quats: Tensor) -> Tensor:
    """Quaternions (w, x, y, z) [..., 4] normalised; a zero (or near-zero) one maps to the identity with zero
    gradient. The one rule for degenerate rotations: the torch renderer (via :func:`quat_to_matrix`) and the
    gsplat backend (which would give NaN for a zero quaternion) both use it."""
    n2 = (quats * quats).sum(-1, keepdim=True)
    ok = n2 > EPS
    ident = torch.zeros_like(quats)
    ident[..., 0] = 1.0
    return torch.where(ok, quats * torch.rsqrt(torch.where(ok, n2, torch.ones_like(n2))), ident)


def quat_to_matrix(quats: Tensor) -> Tensor:
    """Quaternions (w, x, y, z) [..., 4] -> rotation matrices [..., 3, 3].

    Normalised inside (:func:`safe_unit_quat`): a zero quaternion maps to the identity with zero gradient.
    """
    q = safe_unit_quat(quats)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat(rot: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] -> unit quaternions (w, x, y, z) [..., 4] with w >= 0.

    kornia's conversion (Shepperd's method: the best-conditioned of four formulas) guards each square root
    with a ``where`` before it, so the backward is finite at the identity and at 180° turns on every torch
    release; kornia < 0.9 clamped instead, which is why the dependency is ``kornia>=0.9``.
    """
    q = rotation_matrix_to_quaternion(rot)
    q = q / safe_norm(q, keepdim=True)  # unit even for a matrix that is not exactly orthonormal
    return torch.where(q[..., :1] < 0, -q, q)


def covariance_from_scale_rot(scales: Tensor, quats: Tensor) -> Tensor:
    """3D covariance R S S^T R^T [..., 3, 3] from scales [..., 3] and quaternions (w, x, y, z) [..., 4]."""
    m = quat_to_matrix(quats) * scales[..., None, :]
    return m @ m.transpose(-1, -2)
