"""Real spherical harmonics up to degree 4, in the reference-3DGS / gsplat basis order and constants.

Within degree l the order is m = -l .. l. Each basis function is the textbook real SH times (-1)^m,
which is what 3DGS and gsplat evaluate (e.g. degree 1 is -C1 y, C1 z, -C1 x).
colour = max(sum_k c_k Y_k(d) + 0.5, 0) with d the unit direction from the camera centre to the Gaussian.
"""

from __future__ import annotations

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
C4 = (
    2.5033429417967046,
    -1.7701307697799304,
    0.9461746957575601,
    -0.6690465435572892,
    0.10578554691520431,
    -0.6690465435572892,
    0.47308734787878004,
    -1.7701307697799304,
    0.6258357354491761,
)
MAX_SH_DEGREE = 4


def num_sh_coeffs(degree: int) -> int:
    """Number of coefficients K = (L + 1)^2 for SH degree L."""
    return (degree + 1) ** 2


def sh_degree_from_coeffs(k: int) -> int:
    """Inverse of :func:`num_sh_coeffs`; raises for a K that is not a square."""
    degree = round(k**0.5) - 1
    if num_sh_coeffs(degree) != k or not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"{k} SH coefficients is not (L+1)^2 for an SH degree L in 0..{MAX_SH_DEGREE}")
    return degree


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """Basis values [..., (degree+1)^2] at unit directions [..., 3]."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            C2[0] * xy,
            C2[1] * yz,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * xz,
            C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    if degree >= 4:
        out += [
            C4[0] * xy * (xx - yy),
            C4[1] * yz * (3.0 * xx - yy),
            C4[2] * xy * (7.0 * zz - 1.0),
            C4[3] * yz * (7.0 * zz - 3.0),
            C4[4] * (zz * (35.0 * zz - 30.0) + 3.0),
            C4[5] * xz * (7.0 * zz - 3.0),
            C4[6] * (xx - yy) * (7.0 * zz - 1.0),
            C4[7] * xz * (xx - 3.0 * yy),
            C4[8] * (xx * (xx - 3.0 * yy) - yy * (3.0 * xx - yy)),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(coeffs: Tensor, dirs: Tensor, degree: int | None = None) -> Tensor:
    """Colour from SH coefficients [..., K, 3] along unit directions [..., 3] -> [..., 3].

    Uses bands 0..degree (default: all of ``coeffs``); degree 0 never evaluates the direction-dependent
    basis. Returns max(sum + 0.5, 0) as 3DGS does.
    """
    if degree is None:
        degree = sh_degree_from_coeffs(coeffs.shape[-2])
    if degree == 0:
        return (C0 * coeffs[..., 0, :] + 0.5).clamp_min(0.0)
    basis = sh_basis(dirs, degree)  # [..., K']
    k = num_sh_coeffs(degree)
    rgb = (basis[..., None] * coeffs[..., :k, :]).sum(-2)
    return (rgb + 0.5).clamp_min(0.0)


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:
    """I2DC: pixel colour [..., 3] in [0, 1] -> zeroth-order SH coefficient (rgb - 0.5) / C0."""
    return (rgb - 0.5) / C0


def sh_dc_to_rgb(dc: Tensor) -> Tensor:
    """Inverse of :func:`rgb_to_sh_dc`: C0 * dc + 0.5 (no clamping)."""
    return dc * C0 + 0.5
