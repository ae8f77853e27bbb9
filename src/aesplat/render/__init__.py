"""The rasterizer: one interface (``render``), a registry of backends (torch, gsplat), render statistics."""

from .gsplat_backend import FoldedGaussians, fold_cameras
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
    "FoldedGaussians",
    "RenderSettings",
    "RenderStats",
    "active_sh_degree",
    "fold_cameras",
    "get_backend",
    "gsplat_available",
    "render",
    "render_with_stats",
]
