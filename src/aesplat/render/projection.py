"""EWA projection of 3D Gaussians into pinhole cameras, with gsplat's "classic" culling rules.

Pure torch and differentiable (plain autograd) with respect to the Gaussians and both camera matrices.
Cheap culls run first so the expensive work (covariances, Jacobians, SH) only sees survivors:

1. transparent: opacity < 1/255 (can never pass the alpha threshold);
2. depth: z <= near or z >= far (behind the camera, at its centre, on the near plane);
3. footprint: non-finite or degenerate 2D covariance, zero radius, or a bounding box off the image.

Every division is guarded by a ``where`` *before* it, so no culled or degenerate value can turn into a
NaN in the backward pass.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from aesplat.geometry import eval_sh, invert_pose, num_sh_coeffs, quat_to_matrix, safe_normalize
from aesplat.types import Gaussians

ALPHA_MIN = 1.0 / 255.0  # contributions below this alpha are skipped
MAX_EXTENT = 3.33  # bounding-box half-size in standard deviations (tightened by opacity below)


@dataclass(frozen=True)
class Projected:
    """The Gaussians that survived culling, one row per (camera, Gaussian) pair; M rows in total.

    camera      [M]     flat camera index b * V + v (int64)
    gaussian    [M]     flat Gaussian index b * N + n (int64)
    means2d     [M, 2]  pixel coordinates of the centre (pixel centres at +0.5)
    conics      [M, 3]  inverse 2D covariance (a, b, c) of [[a, b], [b, c]], low-pass included
    radii       [M, 2]  bounding-box half-sizes in pixels (integers stored as float)
    depths      [M]     camera-frame z
    opacities   [M]
    colors      [M, 3]  SH evaluated towards the camera, max(. + 0.5, 0)
    """

    camera: Tensor
    gaussian: Tensor
    means2d: Tensor
    conics: Tensor
    radii: Tensor
    depths: Tensor
    opacities: Tensor
    colors: Tensor


@dataclass(frozen=True)
class CullCounts:
    """How many (camera, Gaussian) pairs each cull removed, in the order they run."""

    total: int
    transparent: int
    depth: int
    footprint: int

    @property
    def visible(self) -> int:
        return self.total - self.transparent - self.depth - self.footprint


def _ewa(
    means: Tensor,  # [B * N, 3]
    shape: Callable[[Tensor, Tensor], tuple[Tensor, Tensor, Tensor]],  # (gid [M], J R [M, 2, 3]) -> 2D cov
    cameras: tuple[Tensor, Tensor, Tensor],  # rotations [C, 3, 3], translations [C, 3], intrinsics [C, 3, 3]
    cam: Tensor,  # [M] camera of each pair
    gid: Tensor,  # [M] flat Gaussian index of each pair
    height: int,
    width: int,
    eps2d: float,
) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor], Tensor, Tensor]:
    """Pixel means [M, 2], low-passed 2D covariance entries (a, b, c) [M] each, camera z [M] and the
    determinant of the 2D covariance before the low-pass [M] (from the unblurred entries: exact for tiny ones).

    Callers guarantee z > near > 0 for every pair. Small per-pair matrix products are written as broadcast
    multiply-and-sum: batched 3x3 matmuls are slow on the CPU.
    """
    rot_all, trans_all, k_all = cameras
    r = rot_all.index_select(0, cam)  # [M, 3, 3]
    mean_c = (r * means.index_select(0, gid)[:, None, :]).sum(-1) + trans_all.index_select(0, cam)  # [M, 3]
    k = k_all.index_select(0, cam)
    fx, fy = k[:, 0, 0] * width, k[:, 1, 1] * height
    cx, cy = k[:, 0, 2] * width, k[:, 1, 2] * height
    x, y, z = mean_c.unbind(-1)
    rz = 1.0 / z
    # gsplat's Jacobian clamp: the tangent point stays within [-0.15, 1.15] of the image in pixels.
    lo_x, hi_x = -(cx + 0.15 * width) / fx, (1.15 * width - cx) / fx
    lo_y, hi_y = -(cy + 0.15 * height) / fy, (1.15 * height - cy) / fy
    tx = z * torch.minimum(hi_x, torch.maximum(lo_x, x * rz))
    ty = z * torch.minimum(hi_y, torch.maximum(lo_y, y * rz))
    # J R, with J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]: rows [M, 3] each.
    jr0 = (fx * rz)[:, None] * r[:, 0] - (fx * tx * rz * rz)[:, None] * r[:, 2]
    jr1 = (fy * rz)[:, None] * r[:, 1] - (fy * ty * rz * rz)[:, None] * r[:, 2]
    ca, cb, cc = shape(gid, torch.stack([jr0, jr1], dim=1))
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)
    return means2d, (ca + eps2d, cb, cc + eps2d), z, ca * cc - cb * cb


def _radii(ca: Tensor, cc: Tensor, opac: Tensor, ok: Tensor) -> tuple[Tensor, Tensor]:
    """Bounding-box half-sizes [M] in pixels: the box of the ellipse where opacity * exp(-sigma) >= 1/255,
    capped at 3.33 standard deviations (gsplat's opacity-aware radius)."""
    ratio = torch.where(ok, opac / ALPHA_MIN, torch.ones_like(opac)).clamp_min(1.0)
    extent = torch.sqrt(2.0 * torch.log(ratio)).clamp_max(MAX_EXTENT)
    big = torch.full_like(ca, 1e12)
    rad_x = torch.ceil(extent * torch.where(ok, ca, big).clamp(0.0, 1e12).sqrt())
    rad_y = torch.ceil(extent * torch.where(ok, cc, big).clamp(0.0, 1e12).sqrt())
    return rad_x, rad_y


def project_gaussians(
    gaussians: Gaussians,
    extrinsics: Tensor,  # [B, V, 4, 4] camera-to-world
    intrinsics: Tensor,  # [B, V, 3, 3] normalised
    height: int,
    width: int,
    sh_degree: int,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    covariances: Tensor | None = None,  # [B, N, 3, 3] world covariances replacing scales / quats
    colors: Tensor | None = None,  # [B, N, 3] fixed colours replacing the SH
    antialiased: bool = False,
) -> tuple[Projected, CullCounts]:
    """Cull and project every Gaussian into every camera of its batch element.

    ``sh_degree`` is the number of SH bands evaluated (0 evaluates only the DC term, no basis at all).
    ``antialiased``: gsplat's "antialiased" mode, each pair's opacity scaled by :func:`compensation` (the
    projected opacities carry it; a pair it fades below 1/255 is culled with the footprint, as gsplat does).
    ``covariances`` and ``colors`` serve pre-transformed Gaussians (the tests' emulation of gsplat uses them).
    """
    b, n = gaussians.means.shape[:2]
    v = extrinsics.shape[1]
    w2c = invert_pose(extrinsics)  # [B, V, 4, 4]
    rot, trans = w2c[..., :3, :3], w2c[..., :3, 3]

    # 1-2. opacity and depth culls on all pairs, from one row of the view matrix only.
    opaque = gaussians.opacities >= ALPHA_MIN  # [B, N]
    z_all = torch.einsum("bvk,bnk->bvn", rot[..., 2, :], gaussians.means) + trans[..., 2, None]  # [B, V, N]
    in_range = (z_all > near) & (z_all < far)
    keep = opaque[:, None] & in_range
    total = b * v * n
    transparent = int((~opaque).sum()) * v
    depth_culled = int((opaque[:, None] & ~in_range).sum())

    bi, vi, ni = keep.nonzero(as_tuple=True)
    cam, gid = bi * v + vi, bi * n + ni
    cameras = (rot.reshape(b * v, 3, 3), trans.reshape(b * v, 3), intrinsics.reshape(b * v, 3, 3))
    flat_means = gaussians.means.reshape(b * n, 3)
    if covariances is not None:
        flat_cov = covariances.reshape(b * n, 3, 3)

        def shape(idx: Tensor, jr: Tensor) -> tuple[Tensor, Tensor, Tensor]:
            x = (jr[:, :, :, None] * flat_cov.index_select(0, idx)[:, None]).sum(2)  # J R Sigma [M, 2, 3]
            return (x[:, 0] * jr[:, 0]).sum(-1), (x[:, 0] * jr[:, 1]).sum(-1), (x[:, 1] * jr[:, 1]).sum(-1)
    else:
        scales, quats = gaussians.scales.reshape(b * n, 3), gaussians.quats.reshape(b * n, 4)

        def shape(idx: Tensor, jr: Tensor) -> tuple[Tensor, Tensor, Tensor]:
            rs = (
                quat_to_matrix(quats.index_select(0, idx)) * scales.index_select(0, idx)[:, None, :]
            )  # R_q S [M, 3, 3]
            t = (jr[:, :, :, None] * rs[:, None]).sum(2)  # J R R_q S [M, 2, 3]; 2D cov = t t^T
            return (t[:, 0] * t[:, 0]).sum(-1), (t[:, 0] * t[:, 1]).sum(-1), (t[:, 1] * t[:, 1]).sum(-1)

    # 3. footprint cull. Selecting rows is safe for the backward only if no row holds a non-finite value
    # (0 * inf = NaN); otherwise the survivors are projected again on their own.
    ewa = _ewa(flat_means, shape, cameras, cam, gid, height, width, eps2d)
    with torch.no_grad():
        m2, (ca, cb, cc), _, det_raw = ewa
        det = ca * cc - cb * cb
        opac = gaussians.opacities.reshape(b * n).index_select(0, gid)
        ok = torch.isfinite(ca) & torch.isfinite(cb) & torch.isfinite(cc) & torch.isfinite(m2).all(-1)
        all_finite = bool(ok.all())
        ok &= det > 0
        if antialiased:
            opac = opac * compensation(det_raw, torch.where(ok, det, torch.ones_like(det)))
            ok &= opac >= ALPHA_MIN
        rad_x, rad_y = _radii(ca, cc, opac, ok)
        on_screen = (m2[:, 0] + rad_x > 0) & (m2[:, 0] - rad_x < width)
        on_screen &= (m2[:, 1] + rad_y > 0) & (m2[:, 1] - rad_y < height)
        visible = ok & ((rad_x > 0) | (rad_y > 0)) & on_screen
        sel = visible.nonzero(as_tuple=True)[0]
    footprint = int(cam.numel() - sel.numel())

    cam_v, gid_v = cam.index_select(0, sel), gid.index_select(0, sel)
    if all_finite:
        means2d, depth, det_raw = (ewa[i].index_select(0, sel) for i in (0, 2, 3))
        ca, cb, cc = (t.index_select(0, sel) for t in ewa[1])
    else:
        means2d, (ca, cb, cc), depth, det_raw = _ewa(
            flat_means, shape, cameras, cam_v, gid_v, height, width, eps2d
        )
    det = ca * cc - cb * cb  # > 0 for every survivor
    conics = torch.stack([cc / det, -cb / det, ca / det], dim=-1)
    opacities = gaussians.opacities.reshape(b * n).index_select(0, gid_v)
    if antialiased:
        opacities = opacities * compensation(det_raw, det)

    # Colours: only the SH bands in use; degree 0 never touches directions.
    ncoef = num_sh_coeffs(sh_degree)
    sh = gaussians.sh.flatten(0, 1)[:, :ncoef].index_select(0, gid_v)  # [Mv, K', 3]
    if colors is not None:
        colors = colors.reshape(b * n, 3).index_select(0, gid_v)
    elif sh_degree == 0:
        colors = eval_sh(sh, sh.new_zeros(sh.shape[0], 3), 0)
    else:
        campos = extrinsics[..., :3, 3].reshape(b * v, 3).index_select(0, cam_v)
        d = flat_means.index_select(0, gid_v) - campos
        dirs = safe_normalize(d)  # z > near, so d != 0; guarded all the same
        colors = eval_sh(sh, dirs, sh_degree)

    projected = Projected(
        camera=cam_v,
        gaussian=gid_v,
        means2d=means2d,
        conics=conics,
        radii=torch.stack([rad_x, rad_y], dim=-1).index_select(0, sel),
        depths=depth,
        opacities=opacities,
        colors=colors,
    )
    return projected, CullCounts(total, transparent, depth_culled, footprint)


def compensation(det_raw: Tensor, det_blurred: Tensor) -> Tensor:
    """The antialiasing filter's opacity factor sqrt(det Σ / det(Σ + eps2d·I)) [M], in [0, 1).

    ``det_blurred`` must be positive. The ratio is floored at 1e-12 (a factor of 1e-6, where gsplat's is 0) so
    that a flat Gaussian (det Σ = 0) has a finite gradient; its opacity is then far below 1/255 either way.
    """
    return torch.sqrt((det_raw / det_blurred).clamp_min(1e-12))


def active_sh_degree(sh: Tensor, requested: int, tol: float = 0.0) -> int:
    """Highest SH band (<= ``requested``) whose coefficients carry energy above ``tol`` (max |c|).

    Bands above it add exactly nothing to the colour, so they need not be evaluated. Bands are checked from
    the top down with one min/max reduction each, so a scene that uses its top band costs one pass over it.
    """
    for band in range(requested, 0, -1):
        lo, hi = num_sh_coeffs(band - 1), num_sh_coeffs(band)
        if sh[..., lo:hi, :].numel() == 0:
            continue
        low, high = torch.aminmax(sh[..., lo:hi, :])
        if max(-float(low), float(high)) > tol or low.isnan() or high.isnan():
            return band
    return 0
