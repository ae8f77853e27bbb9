"""gsplat backend (CUDA) and the camera folding that gives it gradients for the intrinsics.

gsplat differentiates through its ``viewmats`` but not through ``Ks``. So the cameras are folded into the
Gaussians here, in torch: each Gaussian is moved into the camera frame, and x, y are mapped by

    A = [[fx / f0, 0, (cx - c0) / f0], [0, fy / f0, (cy - c0) / f0], [0, 0, 1]]   (normalised units)

so that projecting A q with a fixed reference camera (focal f0 = 1, centre c0 = 0.5) gives exactly the
pixel that projecting q with the real camera gives. The EWA Jacobian composes the same way (J_ref A = J), and
gsplat's Jacobian clamp is a fixed pixel window ([-0.15, 1.15] of the image), so the folded render is the
unfolded render, and autograd carries gradients from gsplat's means / covariances back to both cameras.
Colours are evaluated from SH in torch towards the real camera centre.

gsplat is imported lazily: it is needed only when this backend runs.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from aesplat.geometry import covariance_from_scale_rot, eval_sh, invert_pose, num_sh_coeffs, safe_normalize
from aesplat.types import Gaussians, RenderOutput

from .projection import ALPHA_MIN
from .settings import RenderSettings, RenderStats

REFERENCE_FOCAL = 1.0  # normalised focal length of the fixed reference camera
REFERENCE_CENTER = 0.5


@dataclass(frozen=True)
class FoldedGaussians:
    """Gaussians of B * V single-camera scenes, each already in its camera's folded frame.

    means        [C, N, 3]     folded camera-frame centres (z unchanged)
    covariances  [C, N, 3, 3]  folded camera-frame covariances
    opacities    [C, N]
    colors       [C, N, 3]     SH evaluated towards the real camera centre
    intrinsics   [3, 3]        the reference camera (normalised), used with an identity view matrix
    """

    means: Tensor
    covariances: Tensor
    opacities: Tensor
    colors: Tensor
    intrinsics: Tensor


def reference_intrinsics(dtype: torch.dtype, device: torch.device) -> Tensor:
    """Normalised reference camera [3, 3] of the folded frame."""
    f, c = REFERENCE_FOCAL, REFERENCE_CENTER
    return torch.tensor([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]], dtype=dtype, device=device)


def fold_cameras(
    gaussians: Gaussians,
    extrinsics: Tensor,  # [B, V, 4, 4] camera-to-world
    intrinsics: Tensor,  # [B, V, 3, 3] normalised
    sh_degree: int,
) -> FoldedGaussians:
    """Fold each camera's pose and intrinsics into a copy of the Gaussians (pure torch, differentiable)."""
    b, n = gaussians.means.shape[:2]
    v = extrinsics.shape[1]
    w2c = invert_pose(extrinsics)  # [B, V, 4, 4]
    rot, trans = w2c[..., :3, :3], w2c[..., :3, 3]
    fx, fy = intrinsics[..., 0, 0], intrinsics[..., 1, 1]
    cx, cy = intrinsics[..., 0, 2], intrinsics[..., 1, 2]
    zero, one = torch.zeros_like(fx), torch.ones_like(fx)
    f0, c0 = REFERENCE_FOCAL, REFERENCE_CENTER
    fold = torch.stack(
        [fx / f0, zero, (cx - c0) / f0, zero, fy / f0, (cy - c0) / f0, zero, zero, one], dim=-1
    ).reshape(b, v, 3, 3)
    m = fold @ rot  # [B, V, 3, 3]: world -> folded camera frame
    means = torch.einsum("bvij,bnj->bvni", m, gaussians.means) + (fold @ trans[..., None])[..., None, :, 0]
    cov_w = covariance_from_scale_rot(gaussians.scales, gaussians.quats)  # [B, N, 3, 3]
    cov = m[:, :, None] @ cov_w[:, None] @ m[:, :, None].transpose(-1, -2)  # [B, V, N, 3, 3]

    sh = gaussians.sh[:, :, : num_sh_coeffs(sh_degree)]
    if sh_degree == 0:
        colors = eval_sh(sh, gaussians.means, 0)[:, None].expand(b, v, n, 3)
    else:
        d = gaussians.means[:, None] - extrinsics[:, :, None, :3, 3]  # [B, V, N, 3]
        dirs = safe_normalize(d)  # every Gaussian, culled ones too: one at a camera centre gets 0
        colors = eval_sh(sh[:, None].expand(b, v, *sh.shape[1:]), dirs, sh_degree)
    opac = gaussians.opacities[:, None].expand(b, v, n)
    return FoldedGaussians(
        means=means.reshape(b * v, n, 3),
        covariances=cov.reshape(b * v, n, 3, 3),
        opacities=opac.reshape(b * v, n),
        colors=colors.reshape(b * v, n, 3),
        intrinsics=reference_intrinsics(means.dtype, means.device),
    )


def _import_gsplat():
    try:
        import gsplat
    except ImportError as err:
        raise ImportError(
            "render backend 'gsplat' needs the gsplat package (CUDA): `pip install gsplat>=1.5` "
            "(or `pip install aesplat[cuda]`), or use backend='torch'"
        ) from err
    return gsplat


def render_gsplat(
    gaussians: Gaussians,
    extrinsics: Tensor,  # [B, V, 4, 4]
    intrinsics: Tensor,  # [B, V, 3, 3] normalised
    height: int,
    width: int,
    background: Tensor,  # [B, 3]
    sh_degree: int,
    settings: RenderSettings,
) -> tuple[RenderOutput, RenderStats]:
    """gsplat backend of ``render`` (float32 only, CUDA only)."""
    if not gaussians.means.is_cuda:  # checked first: the fix is the same whether or not gsplat is installed
        raise ValueError(
            f"render backend 'gsplat' needs CUDA tensors, got tensors on {gaussians.means.device}; move the "
            "inputs to the GPU, or use backend='torch' (or 'auto', which picks by the tensors' device)"
        )
    gsplat = _import_gsplat()
    b, n = gaussians.means.shape[:2]
    v = extrinsics.shape[1]
    g32 = gaussians.to(dtype=torch.float32)
    folded = fold_cameras(g32, extrinsics.float(), intrinsics.float(), sh_degree)
    scale = folded.means.new_tensor([width, height, 1.0])[:, None]
    k_pix = (folded.intrinsics * scale).expand(b * v, 1, 3, 3).contiguous()
    view = torch.eye(4, device=folded.means.device).expand(b * v, 1, 4, 4).contiguous()
    colors, alphas, _ = gsplat.rasterization(
        means=folded.means, quats=None, scales=None, covars=folded.covariances,
        opacities=folded.opacities, colors=folded.colors, viewmats=view, Ks=k_pix,
        width=width, height=height, near_plane=settings.near, far_plane=settings.far, eps2d=settings.eps2d,
        tile_size=settings.tile_size, backgrounds=background.float().repeat_interleave(v, 0)[:, None],
        render_mode="RGB+ED", rasterize_mode="classic", packed=False,
    )  # fmt: skip
    colors = colors[:, 0].permute(0, 3, 1, 2)  # [C, 4, H, W]
    alphas = alphas[:, 0].permute(0, 3, 1, 2)
    out = RenderOutput(
        color=colors[:, :3].reshape(b, v, 3, height, width),
        depth=colors[:, 3:].reshape(b, v, 1, height, width),
        alpha=alphas.reshape(b, v, 1, height, width),
    )
    transparent = int((gaussians.opacities < ALPHA_MIN).sum()) * v
    stats = RenderStats(
        backend="gsplat",
        pairs=b * v * n,
        culled_transparent=transparent,
        culled_depth=-1,
        culled_footprint=-1,
        visible=-1,
        intersections=-1,
        sh_degree_requested=sh_degree,
        sh_degree_active=sh_degree,
    )
    return out, stats
