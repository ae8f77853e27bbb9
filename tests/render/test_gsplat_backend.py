"""gsplat backend: the camera folding (checked on the CPU through the torch backend) and, with CUDA, gsplat."""

from __future__ import annotations

import pytest
import torch

from aesplat.render import RenderSettings, fold_cameras, gsplat_available, render
from aesplat.render.torch_backend import render_torch
from aesplat.types import Gaussians

from .scenes import cameras, random_scene

H, W = 18, 22


def _render_folded(g: Gaussians, ext, intr, sh_degree: int):
    """Render the folded Gaussians with the torch backend: identity poses, the fixed reference camera."""
    folded = fold_cameras(g, ext, intr, sh_degree)
    c, n = folded.opacities.shape
    eye = torch.eye(4, dtype=ext.dtype).expand(c, 1, 4, 4)
    ref_k = folded.intrinsics.expand(c, 1, 3, 3)
    carrier = Gaussians(  # shape and colour come from ``covariances`` / ``colors``; these fields are unused
        folded.means, torch.zeros(c, n, 4, dtype=ext.dtype), torch.zeros(c, n, 3, dtype=ext.dtype),
        folded.opacities, torch.zeros(c, n, 1, 3, dtype=ext.dtype),
    )  # fmt: skip
    bg = torch.zeros(c, 3, dtype=ext.dtype)
    out, _ = render_torch(carrier, eye, ref_k, H, W, bg, 0, RenderSettings(), folded.covariances, folded.colors)
    b, v = ext.shape[:2]
    return [t.reshape(b, v, *t.shape[2:]) for t in (out.color, out.depth, out.alpha)]


def test_folded_render_equals_unfolded_render_with_same_gradients():
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
    out_b, grad_b = run(lambda gg, e, i: _render_folded(gg, e, i, 2))
    assert out_a[2].max() > 0.5
    for a, b in zip(out_a + list(grad_a), out_b + list(grad_b)):
        torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-9)


def test_gsplat_backend_without_gsplat_says_how_to_get_it():
    if gsplat_available():
        pytest.skip("gsplat is installed")
    g = random_scene(5, dtype=torch.float32)
    ext, intr = cameras(1, 1, dtype=torch.float32)
    with pytest.raises((ImportError, ValueError), match="gsplat|CUDA"):
        render(g, ext, intr, 8, 8, backend="gsplat")


@pytest.mark.gpu
@pytest.mark.skipif(not gsplat_available(), reason="needs CUDA and gsplat")
def test_gsplat_matches_torch_backend_on_gpu():
    g = random_scene(200, b=2, sh_degree=2, seed=22, dtype=torch.float32, spread=0.8)
    g = Gaussians(g.means, g.quats, g.scales, g.opacities.clamp_max(0.9), g.sh)  # gsplat caps alpha at 0.999
    ext, intr = cameras(2, 2, dtype=torch.float32)
    dev = torch.device("cuda")
    leaves = [t.to(dev).requires_grad_() for t in (g.means, g.quats, g.scales, g.opacities, g.sh, ext, intr)]
    outs, grads = [], []
    for backend in ("torch", "gsplat"):
        out = render(Gaussians(*leaves[:5]), leaves[5], leaves[6], 64, 80, backend=backend)
        outs.append(out)
        grads.append(torch.autograd.grad(out.color.sum() + out.depth.sum() + out.alpha.sum(), leaves))
    for a, b in zip(
        (outs[0].color, outs[0].depth, outs[0].alpha), (outs[1].color, outs[1].depth, outs[1].alpha)
    ):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-3)
    for a, b in zip(*grads):
        assert torch.isfinite(b).all()
        assert (a - b).abs().max() <= 1e-2 * a.abs().max() + 1e-5
