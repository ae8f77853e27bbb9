"""Cameras, poses, projection and spherical harmonics: pure functions, no nn.Module state."""

from .camera import (
    DEFAULT_FOV,
    denormalize_intrinsics,
    focal_to_fov,
    fov_to_focal,
    intrinsics_from_fov,
    normalize_intrinsics,
    pixel_grid,
    project_points,
    transform_points,
    unproject_depth,
    unproject_depth_camera,
)
from .rotation import (
    covariance_from_scale_rot,
    homogeneous_to_translation,
    invert_pose,
    make_pose,
    matrix_to_quat,
    matrix_to_rot6d,
    quat_to_matrix,
    relative_to_first,
    rot6d_to_matrix,
    safe_norm,
)
from .sh import (
    C0,
    MAX_SH_DEGREE,
    eval_sh,
    num_sh_coeffs,
    rgb_to_sh_dc,
    sh_basis,
    sh_dc_to_rgb,
    sh_degree_from_coeffs,
)

__all__ = [name for name in dir() if not name.startswith("_")]
