"""The exact render mode: the viewer's current viewpoint rendered on the server by this project's rasterizer,
with view-dependent SH up to the chosen degree, the way ``aesplat predict`` renders."""

from __future__ import annotations

import torch
from torch import Tensor

from ..export import drop_transparent
from ..render import render
from .camera import Viewpoint
from .scene import ViewScene


@torch.no_grad()
def render_viewpoint(
    scene: ViewScene,
    viewpoint: Viewpoint,
    height: int,
    *,
    sh_degree: int | None = None,
    min_opacity: float = 0.0,
    backend: str = "auto",
    device: torch.device | str = "cpu",
) -> Tensor:
    """Render ``viewpoint`` ``height`` pixels tall -> colour [3, height, round(height * aspect)] in [0, 1].

    sh_degree: SH bands evaluated (default: all the Gaussians carry); min_opacity: Gaussians below it are left
    out. The background and renderer options are the scene's (those of its prediction).
    """
    h, w = viewpoint.size(height)
    ext = viewpoint.extrinsics().to(device)[None, None]  # [1, 1, 4, 4]
    intr = viewpoint.intrinsics(height).to(device)[None, None]  # [1, 1, 3, 3]
    gaussians = drop_transparent(scene.gaussians, min_opacity).to(device)
    out = render(gaussians, ext, intr, h, w, background=scene.background.to(device), sh_degree=sh_degree,
                 backend=backend, **scene.render_options)  # fmt: skip
    return out.color[0, 0].clamp(0, 1).cpu()
