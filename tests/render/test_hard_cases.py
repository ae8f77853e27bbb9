"""Degenerate inputs never give NaN or Inf, in outputs or in any gradient."""

from __future__ import annotations

import math

import pytest
import torch

from aesplat.geometry import intrinsics_from_fov
from aesplat.render import render
from aesplat.types import Gaussians

from .scenes import cameras, random_scene


def _scene(case: str) -> tuple[Gaussians, torch.Tensor, torch.Tensor]:
    g = random_scene(32, b=2, sh_degree=2, seed=11, dtype=torch.float32)
    means, quats, scales, opac, sh = (t.clone() for t in (g.means, g.quats, g.scales, g.opacities, g.sh))
    ext, intr = cameras(2, 2, dtype=torch.float32)
    half = slice(0, 16)
    if case == "at_camera_centre":
        means[:, half] = 0.0
    elif case == "on_near_plane":
        means[:, half, 2] = 0.01
    elif case == "just_past_near_plane":
        means[:, half, 2] = 0.01 + 1e-6
    elif case == "behind_camera":
        means[:, half, 2] = -means[:, half, 2]
    elif case == "zero_scales":
        scales[:, half] = 0.0
    elif case == "tiny_scales":
        scales[:, half] = 1e-8
    elif case == "huge_scales":
        scales[:, half] = 1e4
    elif case == "huge_scales_near":
        scales[:, half] = 1e4
        means[:, half, 2] = 0.02
    elif case == "zero_quaternions":
        quats[:, half] = 0.0
    elif case == "opacity_zero":
        opac[:, half] = 0.0
    elif case == "opacity_one":
        opac[:] = 1.0
    elif case == "pile_on_one_pixel":
        means = torch.tensor([0.0, 0.0, 3.0]).expand(2, 2000, 3).clone()
        means[..., 2] += torch.linspace(0, 1e-3, 2000)
        g2 = random_scene(2000, b=2, sh_degree=2, seed=12, dtype=torch.float32)
        quats, scales, opac, sh = g2.quats, g2.scales * 0.01, g2.opacities, g2.sh
    elif case == "identical_depths":
        means[..., 2] = 3.0
    elif case in ("fov_1deg", "fov_170deg"):
        fov = math.radians(1.0 if case == "fov_1deg" else 170.0)
        intr = intrinsics_from_fov(torch.full((2, 2), fov))
        if case == "fov_1deg":
            means[..., :2] *= 0.01
    elif case == "far_off_axis":
        means[:, half, 0] = 50.0  # way outside the FOV: exercises the Jacobian clamp
        scales[:, half] = 3.0
    else:
        raise ValueError(case)
    return Gaussians(means, quats, scales, opac, sh), ext, intr


CASES = [
    "at_camera_centre", "on_near_plane", "just_past_near_plane", "behind_camera", "zero_scales", "tiny_scales",
    "huge_scales", "huge_scales_near", "zero_quaternions", "opacity_zero", "opacity_one", "pile_on_one_pixel",
    "identical_depths", "fov_1deg", "fov_170deg", "far_off_axis",
]  # fmt: skip


def _check_finite(g: Gaussians, ext, intr, h=16, w=20, **kw):
    leaves = [t.detach().clone().requires_grad_() for t in (g.means, g.quats, g.scales, g.opacities, g.sh)]
    ext = ext.detach().clone().requires_grad_()
    intr = intr.detach().clone().requires_grad_()
    bg = torch.tensor([0.1, 0.5, 0.9], requires_grad=True)
    out = render(Gaussians(*leaves), ext, intr, h, w, background=bg, backend="torch", **kw)
    for name, t in (("color", out.color), ("depth", out.depth), ("alpha", out.alpha)):
        assert t.dtype == torch.float32 and torch.isfinite(t).all(), name
    assert (out.alpha >= 0).all() and (out.alpha <= 1).all()
    loss = (out.color * torch.rand_like(out.color)).sum() + out.depth.mean() + out.alpha.sum()
    grads = torch.autograd.grad(loss, [*leaves, ext, intr, bg])
    names = ("means", "quats", "scales", "opacities", "sh", "extrinsics", "intrinsics", "background")
    for name, x in zip(names, grads):
        assert torch.isfinite(x).all(), f"non-finite gradient for {name}"
    return out


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
@pytest.mark.parametrize("case", CASES)
def test_hard_case_is_finite(case, mode):
    g, ext, intr = _scene(case)
    out = _check_finite(g, ext, intr, rasterize_mode=mode)
    if (
        case == "pile_on_one_pixel" and mode == "classic"
    ):  # the centre pixel stops just before its transmittance reaches 1e-4
        trans = 1 - out.alpha[:, 0, 0, 8, 10].double()
        assert ((trans > 1e-4 - 1e-6) & (trans < 1e-2)).all()


@pytest.mark.parametrize("as_bf16", ["inputs", "autocast"])
def test_bfloat16_is_computed_in_float32(as_bf16):
    g, ext, intr = _scene("identical_depths")
    ref = render(g, ext, intr, 16, 20, backend="torch")
    if as_bf16 == "inputs":
        gb = g.to(dtype=torch.bfloat16)
        out = render(gb, ext.bfloat16(), intr.bfloat16(), 16, 20, backend="torch")
        ref = render(gb.to(dtype=torch.float32), ext.bfloat16().float(), intr.bfloat16().float(), 16, 20,
                     backend="torch")  # fmt: skip
        leaves = [
            t.detach().clone().requires_grad_() for t in (gb.means, gb.quats, gb.scales, gb.opacities, gb.sh)
        ]
        out_g = render(Gaussians(*leaves), ext.bfloat16(), intr.bfloat16(), 16, 20, backend="torch")
        grads = torch.autograd.grad(out_g.color.sum(), leaves)
        assert all(x.dtype == torch.bfloat16 and torch.isfinite(x).all() for x in grads)
    else:
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out = render(g, ext, intr, 16, 20, backend="torch")
    assert out.color.dtype == torch.float32
    torch.testing.assert_close(out.color, ref.color, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out.depth, ref.depth, rtol=1e-5, atol=1e-5)
