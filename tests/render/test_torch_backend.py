"""The torch backend against the float64 sequential reference, gradcheck, and analytic cases."""

from __future__ import annotations

import math

import pytest
import torch

from aesplat.geometry import C0, intrinsics_from_fov, rgb_to_sh_dc
from aesplat.render import render
from aesplat.types import Gaussians

from .reference import reference_render
from .scenes import H, W, cameras, leaf_tensors, outputs_and_grads, random_scene, reference_fn, torch_fn


def _antialiased_reference_fn(g, ext, intr, bg):
    return reference_render(g, ext, intr, H, W, bg, antialiased=True)


def assert_float32_matches(out, grad, ref_out, ref_grad) -> None:
    """A float32 render and its gradients against the float64 reference's, to float32 tolerance."""
    for name, a, b in zip(("color", "depth", "alpha"), out, ref_out):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5, msg=name)
    names = ("means", "quats", "scales", "opacities", "sh", "extrinsics", "intrinsics", "background")
    for name, a, b in zip(names, grad, ref_grad):
        assert torch.isfinite(a).all(), name
        assert (a - b).abs().max() <= 1e-4 * b.abs().max(), f"{name}: {(a - b).abs().max()} vs {b.abs().max()}"


@pytest.mark.parametrize(
    ("seed", "options"),
    [(1, {"tile_size": 8, "chunk": 4}), (2, {"tile_size": 16, "chunk": 32}), (3, {"tile_size": 4, "chunk": 7})],
)
def test_matches_reference_float32(seed, options):
    g = random_scene(40, b=2, sh_degree=2, seed=seed)
    ext, intr = cameras(2, 2)
    bg = torch.rand(2, 3, dtype=torch.float64)
    weights = [torch.rand(2, 2, c, H, W, dtype=torch.float64) for c in (3, 1, 1)]
    ref_out, ref_grad = outputs_and_grads(reference_fn, leaf_tensors(g, ext, intr, bg, torch.float64), weights)
    out, grad = outputs_and_grads(torch_fn(**options), leaf_tensors(g, ext, intr, bg, torch.float32), weights)
    assert ref_out[2].max() > 0.9 and (ref_out[2] < 1e-6).any()  # saturated and empty pixels both occur
    assert_float32_matches(out, grad, ref_out, ref_grad)


def test_matches_reference_float64_exactly():
    g = random_scene(30, b=1, sh_degree=3, seed=4)
    ext, intr = cameras(1, 3)
    bg = torch.rand(1, 3, dtype=torch.float64)
    weights = [torch.rand(1, 3, c, H, W, dtype=torch.float64) for c in (3, 1, 1)]
    ref_out, ref_grad = outputs_and_grads(reference_fn, leaf_tensors(g, ext, intr, bg, torch.float64), weights)
    out, grad = outputs_and_grads(torch_fn(chunk=5), leaf_tensors(g, ext, intr, bg, torch.float64), weights)
    for a, b in zip(out + grad, ref_out + ref_grad):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)


def _small_scene(seed: int, b: int = 2) -> Gaussians:
    """A random scene whose Gaussians are partly below a pixel, where the antialiasing filter matters."""
    g = random_scene(40, b=b, sh_degree=2, seed=seed)
    shrink = torch.logspace(-3, 0, 40, dtype=torch.float64)[None, :, None]
    return Gaussians(g.means, g.quats, g.scales * shrink, g.opacities, g.sh)


def test_antialiased_matches_reference_float32():
    g = _small_scene(31)
    ext, intr = cameras(2, 2)
    bg = torch.rand(2, 3, dtype=torch.float64)
    weights = [torch.rand(2, 2, c, H, W, dtype=torch.float64) for c in (3, 1, 1)]
    ref_out, ref_grad = outputs_and_grads(
        _antialiased_reference_fn, leaf_tensors(g, ext, intr, bg, torch.float64), weights
    )
    out, grad = outputs_and_grads(
        torch_fn(rasterize_mode="antialiased", chunk=4), leaf_tensors(g, ext, intr, bg, torch.float32), weights
    )
    classic, _ = outputs_and_grads(reference_fn, leaf_tensors(g, ext, intr, bg, torch.float64), weights)
    assert (classic[2] - ref_out[2]).abs().max() > 0.1  # the filter changes this scene
    assert_float32_matches(out, grad, ref_out, ref_grad)


def test_antialiased_matches_reference_float64_exactly():
    g = _small_scene(32, b=1)
    ext, intr = cameras(1, 3)
    bg = torch.rand(1, 3, dtype=torch.float64)
    weights = [torch.rand(1, 3, c, H, W, dtype=torch.float64) for c in (3, 1, 1)]
    ref = outputs_and_grads(_antialiased_reference_fn, leaf_tensors(g, ext, intr, bg, torch.float64), weights)
    out = outputs_and_grads(
        torch_fn(rasterize_mode="antialiased", chunk=5), leaf_tensors(g, ext, intr, bg, torch.float64), weights
    )
    for a, b in zip(out[0] + out[1], ref[0] + ref[1]):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)


def test_gradcheck_float64_antialiased():
    g = random_scene(4, sh_degree=1, seed=33, spread=0.3)
    g = Gaussians(g.means, g.quats, g.scales * 0.2, g.opacities.clamp(0.3, 0.8), g.sh)
    ext, intr = cameras(1, 2)

    def fn(means, quats, scales, opacities, sh, extrinsics, intrinsics):
        out = render(Gaussians(means, quats, scales, opacities, sh), extrinsics, intrinsics, 7, 9,
                     backend="torch", tile_size=4, chunk=2, rasterize_mode="antialiased")  # fmt: skip
        return out.color, out.depth, out.alpha

    inputs = [t.clone().requires_grad_() for t in (g.means, g.quats, g.scales, g.opacities, g.sh, ext, intr)]
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("scale", [1e-5, 1e-3, 0.01, 0.05])
def test_antialiased_keeps_a_gaussians_coverage_whatever_its_size(scale):
    """A facing Gaussian of projected variance v px²: classic rendering shows it with alpha o at its centre
    however small it is (the 0.3 px² low-pass alone gives it a pixel's footprint); antialiased rendering scales
    that by v / (v + 0.3), so its summed alpha stays o·2π·v, its own, as long as nothing is clipped."""
    size, z, opacity = 41, 2.0, 0.5
    g = _facing_gaussian(opacity, scale, z)
    ext = torch.eye(4)[None, None]
    intr = intrinsics_from_fov(torch.tensor([[math.radians(60.0)]]))
    var = (intr[0, 0, 0, 0].item() * size * scale / z) ** 2
    centre = size // 2
    classic = render(g, ext, intr, size, size, backend="torch").alpha[0, 0, 0]
    aa = render(g, ext, intr, size, size, backend="torch", rasterize_mode="antialiased").alpha[0, 0, 0]
    assert classic[centre, centre] == pytest.approx(opacity, rel=1e-5)
    faded = opacity * var / (var + 0.3)
    if faded < 1 / 255:
        assert (aa == 0).all()  # faded below the alpha threshold: culled, as gsplat culls it
        return
    assert aa[centre, centre] == pytest.approx(faded, rel=1e-4)
    if var > 0.5:  # wide enough that pixel sums approximate the integral
        assert float(aa.sum()) == pytest.approx(opacity * 2 * math.pi * var, rel=0.02)


def test_gradcheck_float64_gaussians_and_cameras():
    g = random_scene(4, sh_degree=1, seed=5, spread=0.3)
    g = Gaussians(g.means, g.quats, g.scales * 2, g.opacities.clamp(0.3, 0.8), g.sh)
    ext, intr = cameras(1, 2)
    h, w = 7, 9

    def fn(means, quats, scales, opacities, sh, extrinsics, intrinsics):
        out = render(Gaussians(means, quats, scales, opacities, sh), extrinsics, intrinsics, h, w,
                     backend="torch", tile_size=4, chunk=2)  # fmt: skip
        return out.color, out.depth, out.alpha

    inputs = [t.clone().requires_grad_() for t in (g.means, g.quats, g.scales, g.opacities, g.sh, ext, intr)]
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def _facing_gaussian(opacity: float, scale: float, z: float, rgb=(0.9, 0.4, 0.1)) -> Gaussians:
    dc = rgb_to_sh_dc(torch.tensor(rgb))
    return Gaussians(
        means=torch.tensor([[[0.0, 0.0, z]]]),
        quats=torch.tensor([[[1.0, 0.0, 0.0, 0.0]]]),
        scales=torch.full((1, 1, 3), scale),
        opacities=torch.tensor([[opacity]]),
        sh=dc.reshape(1, 1, 1, 3),
    )


def test_single_gaussian_centre_and_footprint():
    size, z, scale, opacity = 33, 2.0, 0.01, 0.7
    g = _facing_gaussian(opacity, scale, z)
    ext = torch.eye(4)[None, None]
    intr = intrinsics_from_fov(torch.tensor([[math.radians(60.0)]]))
    out = render(g, ext, intr, size, size, backend="torch")
    centre = size // 2  # the optical axis passes through the centre of the middle pixel
    torch.testing.assert_close(out.color[0, 0, :, centre, centre], opacity * torch.tensor([0.9, 0.4, 0.1]))
    assert out.alpha[0, 0, 0, centre, centre] == pytest.approx(opacity, rel=1e-5)
    assert out.depth[0, 0, 0, centre, centre] == pytest.approx(z, rel=1e-5)
    focal = intr[0, 0, 0, 0].item() * size
    var = (focal * scale / z) ** 2 + 0.3  # EWA variance in pixels^2, low-pass included
    for d in range(1, 8):
        expect = opacity * math.exp(-0.5 * d * d / var)
        got = out.alpha[0, 0, 0, centre, centre + d].item()
        assert got == pytest.approx(expect if expect >= 1 / 255 else 0.0, rel=1e-5, abs=1e-7)
        assert out.alpha[0, 0, 0, centre + d, centre].item() == pytest.approx(got, rel=1e-5, abs=1e-9)
    assert (out.alpha[0, 0, 0] > 0).sum() < size * size / 4  # a compact footprint


def test_single_gaussian_sh_colour_is_dc_only_at_degree0():
    g = _facing_gaussian(0.5, 0.05, 3.0, rgb=(0.2, 0.6, 1.0))
    ext, intr = torch.eye(4)[None, None], intrinsics_from_fov(torch.tensor([[1.0]]))
    out = render(g, ext, intr, 9, 9, backend="torch", background=torch.tensor([1.0, 1.0, 1.0]))
    # colour + (1 - alpha) * white
    expect = 0.5 * (C0 * g.sh[0, 0, 0] + 0.5) + 0.5
    torch.testing.assert_close(out.color[0, 0, :, 4, 4], expect)


@pytest.mark.parametrize("case", ["empty", "behind", "transparent", "offscreen"])
def test_nothing_visible_gives_background_and_zero_gradients(case):
    n = 0 if case == "empty" else 5
    g = random_scene(max(n, 1), seed=6, dtype=torch.float32)
    means = g.means[:, :n].clone()
    opac = g.opacities[:, :n].clone()
    if case == "behind":
        means[..., 2] = -means[..., 2]
    if case == "transparent":
        opac = torch.full_like(opac, 1e-3)
    if case == "offscreen":
        means[..., 0] += 100.0
    leaves = [t.requires_grad_() for t in (means, g.quats[:, :n].clone(), g.scales[:, :n].clone(), opac,
                                          g.sh[:, :n].clone())]  # fmt: skip
    ext, intr = cameras(1, 2, dtype=torch.float32)
    ext.requires_grad_()
    intr.requires_grad_()
    bg = torch.tensor([0.2, 0.3, 0.4], requires_grad=True)
    out = render(Gaussians(*leaves), ext, intr, 12, 10, background=bg, backend="torch")
    torch.testing.assert_close(out.color, bg[None, None, :, None, None].expand_as(out.color).detach())
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    loss = out.color.sum() + out.depth.sum() + out.alpha.sum()
    grads = torch.autograd.grad(loss, [*leaves, ext, intr, bg], allow_unused=True)
    for x in grads[:-1]:
        assert x is None or (torch.isfinite(x).all() and (x == 0).all())
    torch.testing.assert_close(grads[-1], torch.full((3,), 2.0 * 12 * 10))


def test_tiling_options_do_not_change_the_result():
    g = random_scene(60, b=2, sh_degree=1, seed=7, dtype=torch.float32)
    ext, intr = cameras(2, 2, dtype=torch.float32)
    base = render(g, ext, intr, 30, 41, backend="torch")
    for options in ({"tile_size": 8, "chunk": 3}, {"tile_size": 5, "chunk": 64}, {"max_elements": 100}):
        other = render(g, ext, intr, 30, 41, backend="torch", **options)
        for a, b in zip((other.color, other.depth, other.alpha), (base.color, base.depth, base.alpha)):
            torch.testing.assert_close(a, b, rtol=3e-5, atol=1e-5)


def test_pixels_that_stop_early_match_reference():
    """Many opaque layers: pixels stop (T would drop below 1e-4) in an early chunk while their tile goes on."""
    g = random_scene(60, b=1, sh_degree=0, seed=8)
    means = g.means.clone()
    means[0, :, 2] = torch.linspace(2.0, 4.0, 60, dtype=torch.float64)
    g = Gaussians(means, g.quats, g.scales * 3, torch.full_like(g.opacities, 0.95), g.sh)
    ext, intr = cameras(1, 1)
    weights = [torch.rand(1, 1, c, H, W, dtype=torch.float64) for c in (3, 1, 1)]
    bg = torch.rand(1, 3, dtype=torch.float64)
    ref_out, ref_grad = outputs_and_grads(reference_fn, leaf_tensors(g, ext, intr, bg, torch.float64), weights)
    out, grad = outputs_and_grads(
        torch_fn(chunk=3, tile_size=8), leaf_tensors(g, ext, intr, bg, torch.float64), weights
    )
    trans = 1 - ref_out[2]
    assert ((trans > 1e-5) & (trans < 1e-3)).float().mean() > 0.2  # many pixels stopped near T = 1e-4
    for a, b in zip(out + grad, ref_out + ref_grad):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)


@pytest.mark.slow
def test_compiled_kernels_match_eager():
    g = random_scene(60, b=2, sh_degree=1, seed=9, dtype=torch.float32)
    ext, intr = cameras(2, 2, dtype=torch.float32)
    weights = [torch.rand(2, 2, c, H, W) for c in (3, 1, 1)]
    bg = torch.rand(2, 3)
    eager = outputs_and_grads(torch_fn(), leaf_tensors(g, ext, intr, bg, torch.float32), weights)
    compiled = outputs_and_grads(torch_fn(compile=True), leaf_tensors(g, ext, intr, bg, torch.float32), weights)
    for a, b in zip(eager[0] + eager[1], compiled[0] + compiled[1]):
        # Fused and eager float32 arithmetic may put a pixel that sits right at the 1/255 or 1e-4 threshold
        # on different sides of it; that moves a gradient entry by far less than 1e-3 of the tensor's scale.
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-3 * float(a.abs().max()))
