"""The public interface: backend registry, argument checks, background, SH degree selection, statistics."""

from __future__ import annotations

import pytest
import torch

from aesplat.render import (
    BACKENDS,
    RenderStats,
    active_sh_degree,
    get_backend,
    gsplat_available,
    render,
    render_with_stats,
)
from aesplat.types import Gaussians, RenderOutput

from .scenes import cameras, random_scene


def _inputs(n=20, b=1, v=2, sh_degree=1, seed=0):
    g = random_scene(n, b=b, sh_degree=sh_degree, seed=seed, dtype=torch.float32)
    ext, intr = cameras(b, v, dtype=torch.float32)
    return g, ext, intr


def test_registry_and_auto_choice():
    assert set(BACKENDS) == {"torch", "gsplat"}
    name, fn = get_backend("auto", "cpu")
    assert name == "torch" and callable(fn)
    name, _ = get_backend("auto", "cuda")
    assert name == ("gsplat" if gsplat_available() else "torch")
    assert get_backend("torch", "cuda")[0] == "torch"
    with pytest.raises(ValueError, match="unknown render backend"):
        get_backend("optix", "cpu")


def test_auto_follows_the_tensors_device_and_dtype(pretend_gsplat):
    # On a GPU node, "auto" is gsplat only for float32 CUDA tensors; the working dtype decides (bf16 inputs
    # are rendered in float32, float64 inputs in float64, which gsplat cannot do).
    assert get_backend("auto", torch.device("cuda", 0), torch.float32)[0] == "gsplat"
    assert get_backend("auto", "cuda", torch.float64)[0] == "torch"
    assert get_backend("auto", "cpu", torch.float32)[0] == "torch"
    assert get_backend("auto", "cpu", torch.float64)[0] == "torch"
    assert get_backend("gsplat", "cpu")[0] == "gsplat", "an explicit name is taken as given"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16])
def test_auto_renders_cpu_tensors_with_torch_on_a_gsplat_machine(pretend_gsplat, dtype):
    g, ext, intr = _inputs()
    g = g.to(dtype=dtype)
    out, stats = render_with_stats(g, ext.to(dtype), intr.to(dtype), 8, 8, backend="auto")
    assert stats.backend == "torch"
    reference = render(g, ext.to(dtype), intr.to(dtype), 8, 8, backend="torch")
    assert torch.equal(out.color, reference.color)


def test_explicit_gsplat_on_cpu_tensors_is_a_clear_error(pretend_gsplat):
    g, ext, intr = _inputs()
    with pytest.raises(ValueError, match=r"'gsplat' needs CUDA tensors, got tensors on cpu.*backend='torch'"):
        render(g, ext, intr, 8, 8, backend="gsplat")


def test_output_types_and_shapes():
    g, ext, intr = _inputs(b=2, v=3)
    out = render(g, ext, intr, 10, 14)
    assert isinstance(out, RenderOutput)
    assert out.color.shape == (2, 3, 3, 10, 14)
    assert out.depth.shape == out.alpha.shape == (2, 3, 1, 10, 14)


def test_bad_arguments_have_clear_errors():
    g, ext, intr = _inputs()
    with pytest.raises(ValueError, match="extrinsics must be"):
        render(g, ext[:, :, :3], intr, 8, 8)
    with pytest.raises(ValueError, match="intrinsics must be"):
        render(g, ext, intr[:, :1], 8, 8)
    with pytest.raises(ValueError, match="height and width"):
        render(g, ext, intr, 0, 8)
    with pytest.raises(ValueError, match="background must be"):
        render(g, ext, intr, 8, 8, background=torch.zeros(2, 3))
    with pytest.raises(ValueError, match="sh_degree"):
        render(g, ext, intr, 8, 8, sh_degree=3)
    with pytest.raises(TypeError, match="unknown render option"):
        render(g, ext, intr, 8, 8, tile=8)
    with pytest.raises(ValueError, match="near"):
        render(g, ext, intr, 8, 8, near=-1.0)


def test_background_forms_agree():
    g, ext, intr = _inputs(b=2)
    bg = torch.tensor([0.3, 0.6, 0.9])
    a = render(g, ext, intr, 12, 12, background=bg)
    b = render(g, ext, intr, 12, 12, background=bg.expand(2, 3))
    black = render(g, ext, intr, 12, 12)
    torch.testing.assert_close(a.color, b.color)
    torch.testing.assert_close(a.color, black.color + (1 - black.alpha) * bg[:, None, None])


def test_sh_degree_argument_truncates_bands():
    g, ext, intr = _inputs(sh_degree=3)
    truncated = Gaussians(g.means, g.quats, g.scales, g.opacities, g.sh[:, :, :4])
    torch.testing.assert_close(render(g, ext, intr, 12, 12, sh_degree=1).color,
                               render(truncated, ext, intr, 12, 12).color)  # fmt: skip


def test_active_degree_from_coefficient_energy():
    sh = torch.zeros(1, 5, 25, 3)
    sh[..., 0, :] = 1.0
    assert active_sh_degree(sh, 4) == 0
    sh[0, 2, 5, 1] = 1e-3  # a degree-2 coefficient
    assert active_sh_degree(sh, 4) == 2
    assert active_sh_degree(sh, 1) == 0
    assert active_sh_degree(sh, 4, tol=1e-2) == 0


@pytest.mark.parametrize("silent_from", [1, 2, 4])
def test_silent_bands_are_skipped_with_identical_images(silent_from):
    g, ext, intr = _inputs(n=40, sh_degree=4)
    sh = g.sh.clone()
    sh[:, :, silent_from**2 :] = 0.0
    g = Gaussians(g.means, g.quats, g.scales, g.opacities, sh)
    out, stats = render_with_stats(g, ext, intr, 16, 16)
    assert stats.sh_degree_requested == 4 and stats.sh_degree_active == silent_from - 1
    full, full_stats = render_with_stats(
        g, ext, intr, 16, 16, sh_tol=-1.0
    )  # a negative tolerance keeps all bands
    assert full_stats.sh_degree_active == 4
    torch.testing.assert_close(out.color, full.color, rtol=0, atol=1e-6)


def test_silent_bands_are_kept_when_their_gradient_is_needed():
    g, ext, intr = _inputs(sh_degree=2)
    sh = g.sh.clone()
    sh[:, :, 1:] = 0.0
    sh.requires_grad_()
    out, stats = render_with_stats(Gaussians(g.means, g.quats, g.scales, g.opacities, sh), ext, intr, 12, 12)
    assert stats.sh_degree_active == 2
    (grad,) = torch.autograd.grad(out.color.sum(), sh)
    assert grad[:, :, 1:].abs().sum() > 0  # the silent bands still learn


def test_stats_count_each_cull_once():
    g, ext, intr = _inputs(n=40, v=2)
    means, opac = g.means.clone(), g.opacities.clone()
    opac[:, :5] = 1e-3  # transparent
    means[:, 5:10, 2] = -1.0  # behind every camera
    means[:, 10:15, 0] = means[:, 10:15, 2] = 30.0  # 45 degrees off axis: outside both 60-65 degree FOVs
    g = Gaussians(means, g.quats, g.scales, opac, g.sh)
    _, stats = render_with_stats(g, ext, intr, 16, 16)
    assert isinstance(stats, RenderStats) and stats.backend == "torch"
    assert stats.pairs == 80
    assert stats.culled_transparent == 10 and stats.culled_depth == 10 and stats.culled_footprint == 10
    assert stats.visible == 50 and stats.intersections >= 50
