"""Whether predicted Gaussians form a 3D scene or a screen-space point lattice (docs/evaluation.md).

A feed-forward model can reproduce its training views with Gaussians far below a pixel, all opaque, each
visible only through the rasterizer's 0.3-pixel low-pass: the renders at the trained size look right, while
any other size, another viewer or another tool shows dots. Four figures per scene tell the two apart:

    opaque_share       Gaussians with opacity above ``NEAR_OPAQUE`` (0.99)
    subpixel_share     Gaussians whose largest axis projects below ``SUBPIXEL`` (0.1 px) in their own view
    fusion_gain_db     target PSNR from all context views' Gaussians minus the best single view's alone
    transfer_gain_db   target PSNR rendered at s x the size against ground truth at s x, minus the 1x render
                       upsampled (bilinear) against the same ground truth (``--data.eval_transfer_scale s``)

A lattice has a negative transfer gain: upsampling its own render beats rendering it larger.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from aesplat.model.gaussian_head import pixel_footprint
from aesplat.types import Gaussians, RenderOutput

from .metrics import psnr

NEAR_OPAQUE = 0.99
SUBPIXEL = 0.1  # pixels

# Renders Gaussians into cameras: (gaussians, extrinsics [B, V, 4, 4], intrinsics [B, V, 3, 3], height, width)
Renderer = Callable[[Gaussians, Tensor, Tensor, int, int], RenderOutput]


def projected_size(scales: Tensor, depth: Tensor, intrinsics: Tensor) -> Tensor:
    """Pixels spanned by one standard deviation of each Gaussian's largest axis in its own view [B, V·H·W]:
    scales [B, V·H·W, 3] scene units, depth [B, V, H, W] each pixel's z-depth, intrinsics [B, V, 3, 3]
    normalised. (The axis seen side-on; seen at a slant it spans less.)"""
    h, w = depth.shape[-2:]
    unit = pixel_footprint(intrinsics, h, w)[..., None]  # [B, V, 1] scene units per pixel at depth 1
    return scales.amax(-1) / (depth.flatten(2) * unit).clamp_min(1e-12).flatten(1)


def gaussian_shares(gaussians: Gaussians, depth: Tensor, intrinsics: Tensor) -> dict[str, Tensor]:
    """``opaque_share`` and ``subpixel_share`` per scene [B] of Gaussians predicted one per context pixel
    (depth [B, Vc, H, W], the context views' intrinsics [B, Vc, 3, 3])."""
    size = projected_size(gaussians.scales, depth, intrinsics)
    return {
        "opaque_share": (gaussians.opacities > NEAR_OPAQUE).float().mean(-1),
        "subpixel_share": (size < SUBPIXEL).float().mean(-1),
    }


def view_gaussians(gaussians: Gaussians, view: int, num_views: int) -> Gaussians:
    """The Gaussians of one context view (they are stored view by view, one per pixel)."""
    per_view = gaussians.num_gaussians // num_views
    return gaussians.apply(lambda t: t[:, view * per_view : (view + 1) * per_view])


def fusion_gain(
    render: Renderer,
    gaussians: Gaussians,
    num_views: int,
    extrinsics: Tensor,  # [B, Vt, 4, 4] the target cameras
    intrinsics: Tensor,  # [B, Vt, 3, 3]
    target: Tensor,  # [B, Vt, 3, H, W] in [0, 1]
    fused_psnr: Tensor,  # [B] the targets' mean PSNR rendered from all Gaussians
) -> Tensor:
    """``fusion_gain_db`` [B]: ``fused_psnr`` minus the best mean target PSNR from one context view's
    Gaussians alone."""
    b, vt, _, h, w = target.shape
    single = []
    for view in range(num_views):
        color = render(view_gaussians(gaussians, view, num_views), extrinsics, intrinsics, h, w).color
        single.append(psnr(color.flatten(0, 1), target.flatten(0, 1)).reshape(b, vt).mean(1))
    return fused_psnr - torch.stack(single).amax(0)


def transfer_gain(
    render: Renderer,
    gaussians: Gaussians,
    extrinsics: Tensor,  # [B, Vt, 4, 4] the target cameras
    intrinsics: Tensor,  # [B, Vt, 3, 3] normalised: the same at every size
    rendered: Tensor,  # [B, Vt, 3, H, W] the targets rendered at the model's size
    target_large: Tensor,  # [B, Vt, 3, sH, sW] the targets at s times the size, in [0, 1]
) -> dict[str, Tensor]:
    """``psnr_transfer`` (rendered at s x), ``psnr_upsampled`` (the 1x render upsampled bilinearly) and
    ``transfer_gain_db`` (their difference), each the mean over a scene's targets [B]."""
    b, vt, _, sh, sw = target_large.shape
    large = render(gaussians, extrinsics, intrinsics, sh, sw).color.flatten(0, 1)
    upsampled = F.interpolate(rendered.flatten(0, 1), size=(sh, sw), mode="bilinear", align_corners=False)
    truth = target_large.flatten(0, 1)
    direct = psnr(large, truth).reshape(b, vt).mean(1)
    baseline = psnr(upsampled, truth).reshape(b, vt).mean(1)
    return {"psnr_transfer": direct, "psnr_upsampled": baseline, "transfer_gain_db": direct - baseline}
