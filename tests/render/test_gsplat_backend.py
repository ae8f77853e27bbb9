"""gsplat backend: the intrinsics folding (checked on the CPU through the torch backend); with CUDA, gsplat."""

from __future__ import annotations

import pytest
import torch

from aesplat.geometry import covariance_from_scale_rot, eval_sh, invert_pose, safe_unit_quat
from aesplat.render import RenderSettings, fold_intrinsics, gsplat_available, reference_intrinsics, render
from aesplat.render.torch_backend import render_torch
from aesplat.types import Gaussians

from .scenes import cameras, random_scene

H, W = 18, 22


def _render_like_gsplat(g: Gaussians, viewmats: torch.Tensor, sh_degree: int):
    """What ``gsplat.rasterization`` (1.5) computes from general view matrices and the reference camera,
    written out in torch and rendered by the torch backend.

    gsplat maps means by M μ + t and covariances by M Σ Mᵀ with the view matrix's upper 3×3 block M, whatever
    it is (its projection kernel and its vector-Jacobian products never assume a rotation), builds Σ from the
    normalised quaternion and the scales, and evaluates the SH along μ − inverse(viewmat)[:3, 3].
    """
    b, v = viewmats.shape[:2]
    n, dtype = g.means.shape[1], g.means.dtype
    m, t = viewmats[..., :3, :3], viewmats[..., :3, 3]
    means = torch.einsum("bvij,bnj->bvni", m, g.means) + t[:, :, None]  # [B, V, N, 3]
    cov_w = covariance_from_scale_rot(g.scales, safe_unit_quat(g.quats))  # [B, N, 3, 3]
    cov = m[:, :, None] @ cov_w[:, None] @ m[:, :, None].transpose(-1, -2)  # [B, V, N, 3, 3]
    campos = torch.linalg.inv(viewmats)[..., :3, 3]  # [B, V, 3]
    d = g.means[:, None] - campos[:, :, None]
    colors = eval_sh(g.sh[:, None].expand(b, v, *g.sh.shape[1:]), d / d.norm(dim=-1, keepdim=True), sh_degree)
    c = b * v
    carrier = Gaussians(  # shape and colour come from ``covariances`` / ``colors``; these fields are unused
        means.reshape(c, n, 3), torch.zeros(c, n, 4, dtype=dtype), torch.zeros(c, n, 3, dtype=dtype),
        g.opacities[:, None].expand(b, v, n).reshape(c, n), torch.zeros(c, n, 1, 3, dtype=dtype),
    )  # fmt: skip
    eye = torch.eye(4, dtype=dtype).expand(c, 1, 4, 4)
    ref_k = reference_intrinsics(dtype, g.means.device).expand(c, 1, 3, 3)
    bg = torch.zeros(c, 3, dtype=dtype)
    out, _ = render_torch(
        carrier, eye, ref_k, H, W, bg, 0, RenderSettings(), cov.reshape(c, n, 3, 3), colors.reshape(c, n, 3)
    )
    return [t.reshape(b, v, *t.shape[2:]) for t in (out.color, out.depth, out.alpha)]


def test_folded_view_matrices_render_the_real_cameras_with_same_gradients():
    g = random_scene(30, b=2, sh_degree=2, seed=21, dtype=torch.float64)
    ext, intr = cameras(2, 3, dtype=torch.float64)
    weights = [torch.rand(2, 3, c, H, W, dtype=torch.float64) for c in (3, 1, 1)]

    def run(fn):
        leaves = [
            t.clone().requires_grad_() for t in (g.means, g.quats, g.scales, g.opacities, g.sh, ext, intr)
        ]
        outs = fn(Gaussians(*leaves[:5]), leaves[5], leaves[6])
        loss = sum((o * w).sum() for o, w in zip(outs, weights))
        return [o.detach() for o in outs], torch.autograd.grad(loss, leaves)

    def direct(gg, e, i):
        out = render(gg, e, i, H, W, backend="torch")
        return out.color, out.depth, out.alpha

    out_a, grad_a = run(direct)
    out_b, grad_b = run(lambda gg, e, i: _render_like_gsplat(gg, fold_intrinsics(e, i), 2))
    assert out_a[2].max() > 0.5
    assert all(grad.abs().max() > 0 for grad in grad_a[5:])  # the cameras do receive gradients
    for a, b in zip(out_a + list(grad_a), out_b + list(grad_b)):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-9)


def test_fold_is_the_pose_for_the_reference_camera_and_keeps_the_camera_centre():
    ext, intr = cameras(2, 3, dtype=torch.float64)
    ref = reference_intrinsics(torch.float64, ext.device).expand_as(intr)
    torch.testing.assert_close(fold_intrinsics(ext, ref), invert_pose(ext), rtol=0, atol=1e-15)
    folded = fold_intrinsics(ext, intr)
    assert not torch.allclose(folded, invert_pose(ext))
    torch.testing.assert_close(torch.linalg.inv(folded)[..., :3, 3], ext[..., :3, 3])


def test_safe_unit_quat_is_safe_at_zero():
    q = torch.tensor([[0.0, 0.0, 0.0, 0.0], [2.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]], requires_grad=True)
    u = safe_unit_quat(q)
    torch.testing.assert_close(u.detach(), torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0], [0.5, 0.5, 0.5, 0.5]]))
    u.sum().backward()
    assert torch.isfinite(q.grad).all() and (q.grad[0] == 0).all()


def test_gsplat_backend_without_gsplat_says_how_to_get_it():
    if gsplat_available():
        pytest.skip("gsplat is installed")
    g = random_scene(5, dtype=torch.float32)
    ext, intr = cameras(1, 1, dtype=torch.float32)
    with pytest.raises((ImportError, ValueError), match="gsplat|CUDA"):
        render(g, ext, intr, 8, 8, backend="gsplat")


@pytest.mark.gpu
@pytest.mark.skipif(not gsplat_available(), reason="needs CUDA and gsplat")
@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_gsplat_matches_torch_backend_on_gpu(mode):
    g = random_scene(200, b=2, sh_degree=2, seed=22, dtype=torch.float32, spread=0.8)
    shrink = torch.logspace(-2, 0, 200)[None, :, None]  # some below a pixel, where the two modes differ
    g = Gaussians(
        g.means, g.quats, g.scales * shrink, g.opacities.clamp_max(0.9), g.sh
    )  # gsplat: alpha <= 0.999
    ext, intr = cameras(2, 2, dtype=torch.float32)
    dev = torch.device("cuda")
    leaves = [t.to(dev).requires_grad_() for t in (g.means, g.quats, g.scales, g.opacities, g.sh, ext, intr)]
    outs, grads = [], []
    for backend in ("torch", "gsplat"):
        out = render(Gaussians(*leaves[:5]), leaves[5], leaves[6], 64, 80, backend=backend, rasterize_mode=mode)
        outs.append(out)
        grads.append(torch.autograd.grad(out.color.sum() + out.depth.sum() + out.alpha.sum(), leaves))
    for a, b in zip(
        (outs[0].color, outs[0].depth, outs[0].alpha), (outs[1].color, outs[1].depth, outs[1].alpha)
    ):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-3)
    for a, b in zip(*grads):
        assert torch.isfinite(b).all()
        assert (a - b).abs().max() <= 1e-2 * a.abs().max() + 1e-5
