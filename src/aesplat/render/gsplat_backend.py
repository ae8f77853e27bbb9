"""gsplat backend (CUDA): gsplat differentiates the Gaussians natively; only the intrinsics are folded.

gsplat gives gradients for its means, quaternions, scales, opacities, SH coefficients and view matrices, but
not for ``Ks``. It uses a view matrix as a general affine map (camera-frame means M μ + t, covariances M Σ Mᵀ,
and the vector-Jacobian products of a general matrix), so each camera's intrinsics are folded into its view
matrix, in torch, and gsplat renders with a fixed reference camera (focal f0 = 1, centre c0 = 0.5):

    viewmat = [[A R, A t], [0, 1]]   A = [[fx / f0, 0, (cx - c0) / f0], [0, fy / f0, (cy - c0) / f0], [0, 0, 1]]

with [R | t] the world-to-camera pose (normalised units). Projecting A q with the reference camera gives the
pixel that projecting q with the real camera gives, and the EWA Jacobian composes the same way (J_ref A = J);
z is unchanged, so culling and depth are too; gsplat's Jacobian clamp is a fixed pixel window ([-0.15, 1.15]
of the image). For the SH directions gsplat places the camera at inverse(viewmat)[:3, 3] = −(A R)⁻¹ A t = −Rᵀ t,
the real camera centre. So the render is the unfolded one, and autograd carries gsplat's view-matrix
gradients back to the poses and the intrinsics. Only B·V matrices are built in torch: no per-camera copy of
the Gaussians, covariances or colours.

gsplat is imported lazily: it is needed only when this backend runs.
"""

from __future__ import annotations

import torch
from torch import Tensor

from aesplat.geometry import invert_pose, num_sh_coeffs, safe_unit_quat
from aesplat.types import Gaussians, RenderOutput

from .projection import ALPHA_MIN
from .settings import DeferredCount, RenderSettings, RenderStats

REFERENCE_FOCAL = 1.0  # normalised focal length of the fixed reference camera
REFERENCE_CENTER = 0.5


def reference_intrinsics(dtype: torch.dtype, device: torch.device) -> Tensor:
    """Normalised reference camera [3, 3] that gsplat renders every folded view with."""
    f, c = REFERENCE_FOCAL, REFERENCE_CENTER
    return torch.tensor([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]], dtype=dtype, device=device)


def fold_intrinsics(
    extrinsics: Tensor,  # [B, V, 4, 4] camera-to-world
    intrinsics: Tensor,  # [B, V, 3, 3] normalised
) -> Tensor:
    """View matrices [B, V, 4, 4] that map world points into each camera's folded frame (module docstring):
    rendered with :func:`reference_intrinsics` they give the real cameras' images. Differentiable in both."""
    fx, fy = intrinsics[..., 0, 0], intrinsics[..., 1, 1]
    cx, cy = intrinsics[..., 0, 2], intrinsics[..., 1, 2]
    zero, one = torch.zeros_like(fx), torch.ones_like(fx)
    f0, c0 = REFERENCE_FOCAL, REFERENCE_CENTER
    fold = torch.stack(
        [fx / f0, zero, (cx - c0) / f0, zero,
         zero, fy / f0, (cy - c0) / f0, zero,
         zero, zero, one, zero,
         zero, zero, zero, one],
        dim=-1,
    ).unflatten(-1, (4, 4))  # fmt: skip
    return fold @ invert_pose(extrinsics)


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
    gsplat=None,  # the module that rasterizes: None = the gsplat package (CUDA only)
) -> tuple[RenderOutput, RenderStats]:
    """gsplat backend of ``render`` (float32 only). Reads no device value on the host: the one count it reports
    is read only when someone asks for it, so a render queues its kernels and returns (the CPU tests count such
    reads with a stand-in module for ``gsplat``)."""
    if gsplat is None:
        if not gaussians.means.is_cuda:  # checked first: the fix is the same whether or not gsplat is installed
            raise ValueError(
                f"render backend 'gsplat' needs CUDA tensors, got tensors on {gaussians.means.device}; move "
                "the inputs to the GPU, or use backend='torch' (or 'auto', which picks by the tensors' device)"
            )
        gsplat = _import_gsplat()
    b, n = gaussians.means.shape[:2]
    v = extrinsics.shape[1]
    g = gaussians.to(dtype=torch.float32)
    viewmats = fold_intrinsics(extrinsics.float(), intrinsics.float())  # [B, V, 4, 4]
    pixels = g.means.new_tensor([width, height, 1.0])[:, None]
    k_ref = (reference_intrinsics(torch.float32, g.means.device) * pixels).expand(b, v, 3, 3).contiguous()
    colors, alphas, _ = gsplat.rasterization(
        means=g.means, quats=safe_unit_quat(g.quats), scales=g.scales, opacities=g.opacities,
        colors=g.sh[:, :, : num_sh_coeffs(sh_degree)], sh_degree=sh_degree, viewmats=viewmats, Ks=k_ref,
        width=width, height=height, near_plane=settings.near, far_plane=settings.far, eps2d=settings.eps2d,
        tile_size=settings.tile_size, backgrounds=background.float()[:, None].expand(b, v, 3).contiguous(),
        render_mode="RGB+ED", rasterize_mode=settings.rasterize_mode, packed=False,
    )  # fmt: skip
    rgbd = colors.permute(0, 1, 4, 2, 3).contiguous()  # [B, V, 4, H, W]: colour and expected depth
    alpha = alphas.permute(0, 1, 4, 2, 3).contiguous()  # [B, V, 1, H, W]
    out = RenderOutput(color=rgbd[:, :, :3], depth=rgbd[:, :, 3:], alpha=alpha)
    opacities = gaussians.opacities.detach()
    stats = RenderStats(
        backend="gsplat",
        pairs=b * v * n,
        culled_transparent=DeferredCount(lambda: int((opacities < ALPHA_MIN).sum()) * v),
        culled_depth=-1,
        culled_footprint=-1,
        visible=-1,
        intersections=-1,
        sh_degree_requested=sh_degree,
        sh_degree_active=sh_degree,
    )
    return out, stats
