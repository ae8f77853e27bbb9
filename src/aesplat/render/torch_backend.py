"""Pure-PyTorch tile rasterizer: project + cull, bin into tiles, composite with a hand-written backward."""

from __future__ import annotations

from torch import Tensor

from aesplat.types import Gaussians, RenderOutput

from .composite import composite
from .projection import project_gaussians
from .settings import RenderSettings, RenderStats
from .tiles import bin_gaussians

DEPTH_EPS = 1e-10  # gsplat's clamp of alpha when normalising the expected depth


def render_torch(
    gaussians: Gaussians,
    extrinsics: Tensor,  # [B, V, 4, 4]
    intrinsics: Tensor,  # [B, V, 3, 3] normalised
    height: int,
    width: int,
    background: Tensor,  # [B, 3]
    sh_degree: int,
    settings: RenderSettings,
    covariances: Tensor | None = None,  # [B, N, 3, 3] instead of scales / quats
    colors: Tensor | None = None,  # [B, N, 3] instead of SH
) -> tuple[RenderOutput, RenderStats]:
    """Torch backend of ``render``; inputs are already in the working dtype."""
    b, v = extrinsics.shape[:2]
    proj, counts = project_gaussians(
        gaussians, extrinsics, intrinsics, height, width, sh_degree,
        near=settings.near, far=settings.far, eps2d=settings.eps2d, covariances=covariances, colors=colors,
        antialiased=settings.rasterize_mode == "antialiased",
    )  # fmt: skip
    bins = bin_gaussians(
        proj.camera,
        proj.means2d.detach(),
        proj.radii,
        proj.depths.detach(),
        b * v,
        height,
        width,
        settings.tile_size,
        conics=proj.conics.detach(),
        opacities=proj.opacities.detach(),
    )
    rgb, depth_sum, trans = composite(
        proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths, bins, height, width,
        chunk=settings.chunk, max_elements=settings.max_elements, compiled=settings.compile,
        step_elements=settings.step_elements,
    )  # fmt: skip
    alpha = 1.0 - trans  # [C, 1, H, W]
    color = rgb + trans * background.repeat_interleave(v, dim=0)[:, :, None, None]
    depth = depth_sum / alpha.clamp_min(DEPTH_EPS)
    out = RenderOutput(
        color=color.reshape(b, v, 3, height, width),
        depth=depth.reshape(b, v, 1, height, width),
        alpha=alpha.reshape(b, v, 1, height, width),
    )
    stats = RenderStats(
        backend="torch",
        pairs=counts.total,
        culled_transparent=counts.transparent,
        culled_depth=counts.depth,
        culled_footprint=counts.footprint,
        visible=counts.visible,
        intersections=int(bins.order.numel()),
        sh_degree_requested=sh_degree,
        sh_degree_active=sh_degree,
    )
    return out, stats
