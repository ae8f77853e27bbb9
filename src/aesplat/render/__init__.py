"""The rasterizer: one interface (``render``), a registry of backends (torch, gsplat), its config section and
settings, render statistics."""

from .gsplat_backend import fold_intrinsics, reference_intrinsics
from .interface import (
    BACKENDS,
    RenderSettings,
    RenderStats,
    get_backend,
    gsplat_available,
    render,
    render_with_stats,
)
from .projection import active_sh_degree
from .settings import RasterizerConfig

__all__ = [
    "BACKENDS",
    "RasterizerConfig",
    "RenderSettings",
    "RenderStats",
    "active_sh_degree",
    "fold_intrinsics",
    "get_backend",
    "gsplat_available",
    "render",
    "reference_intrinsics",
    "render_with_stats",
]
