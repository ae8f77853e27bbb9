"""Getting predictions out: 3DGS PLY files and Gaussian pruning."""

from .ply import VIEWER_MAX_SH_DEGREE, gaussians_to_ply_array, ply_property_names, write_ply
from .prune import drop_transparent, keep_most_opaque

__all__ = [
    "VIEWER_MAX_SH_DEGREE",
    "drop_transparent",
    "gaussians_to_ply_array",
    "keep_most_opaque",
    "ply_property_names",
    "write_ply",
]
