"""The rasterizer: one interface (``render``), a registry of backends (torch, gsplat), render statistics."""

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

__all__ = [
    "BACKENDS",
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
