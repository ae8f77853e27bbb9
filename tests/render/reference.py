"""A slow, obviously-correct float64 rasterizer to check the fast backends against.

Independent of ``aesplat.render``: its own projection (rigid pose inverse written out, rotation from the
quaternion, explicit 2x2 inverse) and per-pixel sequential compositing, one Gaussian at a time in depth order
for all pixels at once. No tiles, no bounding boxes: the fast renderer's boxes hold exactly the pixels where
alpha >= 1/255, so they must not change the image.
"""

from __future__ import annotations

import torch
from torch import Tensor

from aesplat.geometry import eval_sh
from aesplat.types import Gaussians


def _rotation(q: Tensor) -> Tensor:
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def reference_render(
    g: Gaussians,
    extrinsics: Tensor,  # [B, V, 4, 4]
    intrinsics: Tensor,  # [B, V, 3, 3]
    height: int,
    width: int,
    background: Tensor | None = None,  # [B, 3]
    sh_degree: int | None = None,
    near: float = 0.01,
    antialiased: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """colour [B, V, 3, H, W], depth [B, V, 1, H, W], alpha [B, V, 1, H, W] in float64.

    ``antialiased``: gsplat's mode of that name, the opacity times sqrt(det Σ₂ / det(Σ₂ + 0.3 I)) of the
    projected covariance Σ₂ (skipped, as gsplat skips it, when that leaves it below 1/255)."""
    b, n = g.means.shape[:2]
    v = extrinsics.shape[1]
    degree = g.sh_degree if sh_degree is None else sh_degree
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=torch.float64) + 0.5,
        torch.arange(width, dtype=torch.float64) + 0.5,
        indexing="ij",
    )
    colors, depths, alphas = [], [], []
    for bi in range(b):
        for vi in range(v):
            rot_t = extrinsics[bi, vi, :3, :3].T  # poses are rigid: the inverse rotation is the transpose
            w2c = torch.cat(
                [torch.cat([rot_t, -(rot_t @ extrinsics[bi, vi, :3, 3:])], 1), extrinsics[bi, vi, 3:]]
            )
            k = intrinsics[bi, vi]
            fx, fy, cx, cy = k[0, 0] * width, k[1, 1] * height, k[0, 2] * width, k[1, 2] * height
            campos = extrinsics[bi, vi, :3, 3]
            img = torch.zeros(height, width, 3, dtype=torch.float64)
            dep = torch.zeros(height, width, dtype=torch.float64)
            trans = torch.ones(height, width, dtype=torch.float64)
            done = torch.zeros(height, width, dtype=torch.bool)
            mean_c = g.means[bi] @ w2c[:3, :3].T + w2c[:3, 3]  # [N, 3]
            order = torch.sort(mean_c[:, 2].detach(), stable=True).indices
            for i in order.tolist():
                o = g.opacities[bi, i]
                x, y, z = mean_c[i]
                if z <= near or o < 1 / 255:
                    continue
                r = _rotation(g.quats[bi, i])
                cov = r @ torch.diag(g.scales[bi, i] ** 2) @ r.T
                cov_c = w2c[:3, :3] @ cov @ w2c[:3, :3].T
                tx = z * torch.clamp(x / z, -(cx + 0.15 * width) / fx, (1.15 * width - cx) / fx)
                ty = z * torch.clamp(y / z, -(cy + 0.15 * height) / fy, (1.15 * height - cy) / fy)
                jac = torch.stack(
                    [
                        torch.stack([fx / z, torch.zeros_like(z), -fx * tx / z**2]),
                        torch.stack([torch.zeros_like(z), fy / z, -fy * ty / z**2]),
                    ]
                )
                cov2 = jac @ cov_c @ jac.T
                det_unblurred = torch.linalg.det(cov2)
                cov2 = cov2 + 0.3 * torch.eye(2, dtype=torch.float64)
                det = cov2[0, 0] * cov2[1, 1] - cov2[0, 1] ** 2
                if antialiased:
                    o = o * torch.sqrt(det_unblurred / det)
                    if o < 1 / 255:
                        continue
                a, bb, c = cov2[1, 1] / det, -cov2[0, 1] / det, cov2[0, 0] / det
                u, vv = fx * x / z + cx, fy * y / z + cy
                d = g.means[bi, i] - campos
                color = eval_sh(g.sh[bi, i], d / d.norm(), degree)
                dx, dy = u - xs, vv - ys
                sigma = 0.5 * (a * dx * dx + c * dy * dy) + bb * dx * dy
                alpha = torch.clamp(o * torch.exp(-sigma), max=0.99)
                use = (sigma >= 0) & (alpha >= 1 / 255) & ~done
                next_t = trans * (1 - alpha)
                stop = use & (next_t <= 1e-4)
                done = done | stop
                use = use & ~stop
                wgt = torch.where(use, alpha * trans, torch.zeros_like(alpha))
                img = img + wgt[..., None] * color
                dep = dep + wgt * z
                trans = torch.where(use, next_t, trans)
            bg = torch.zeros(3, dtype=torch.float64) if background is None else background[bi]
            alpha_img = 1 - trans
            colors.append((img + trans[..., None] * bg).permute(2, 0, 1))
            depths.append((dep / alpha_img.clamp_min(1e-10))[None])
            alphas.append(alpha_img[None])
    shape = (b, v, -1, height, width)
    return (
        torch.stack(colors).reshape(shape),
        torch.stack(depths).reshape(shape),
        torch.stack(alphas).reshape(shape),
    )
