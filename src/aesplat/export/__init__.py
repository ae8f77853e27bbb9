"""Getting predictions out: 3DGS PLY and ``.splat`` files, COLMAP and nerfstudio camera exports, pruning."""

from .colmap import write_colmap
from .formats import EXPORTS, export_prediction, parse_formats
from .nerfstudio import write_nerfstudio
from .ply import VIEWER_MAX_SH_DEGREE, gaussians_to_ply_array, ply_property_names, read_ply, write_ply
from .prediction import PredictedScene, read_prediction
from .prune import drop_non_finite, drop_transparent, keep_most_opaque
from .splat import SPLAT_DTYPE, gaussians_to_splat_array, write_splat

__all__ = [
    "EXPORTS",
    "SPLAT_DTYPE",
    "VIEWER_MAX_SH_DEGREE",
    "PredictedScene",
    "drop_non_finite",
    "drop_transparent",
    "export_prediction",
    "gaussians_to_ply_array",
    "gaussians_to_splat_array",
    "keep_most_opaque",
    "parse_formats",
    "ply_property_names",
    "read_ply",
    "read_prediction",
    "write_colmap",
    "write_nerfstudio",
    "write_ply",
    "write_splat",
]
