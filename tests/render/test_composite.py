"""Compositing step sizes: fixed chunks and steps that grow as tiles drop out both match the reference."""

from __future__ import annotations

import pytest
import torch

import aesplat.render.composite as composite
from aesplat.render import render
from aesplat.render.composite import _StepSizes
from aesplat.types import Gaussians

from .scenes import H, W, cameras, leaf_tensors, outputs_and_grads, random_scene, reference_fn, torch_fn


def test_step_grows_only_while_few_tiles_are_active():
    steps = _StepSizes(chunk=32, npix=64, step_elements=1 << 18, max_elements=1 << 22)
    assert steps(tiles=784, remaining=5000) == 32  # many tiles: the block is big enough already
    assert steps(tiles=4, remaining=5000) == 1024  # 4 x 64 x 1024 = 2^18
    assert steps(tiles=4, remaining=100) == 128  # never (much) past the longest remaining list
    assert steps(tiles=1, remaining=1 << 20) == 4096  # 64 x 4096 = 2^18
    assert _StepSizes(32, 64, 1 << 18, max_elements=1 << 15)(tiles=4, remaining=5000) == 128  # memory bound
    assert _StepSizes(32, 64, 0, 1 << 22)(tiles=1, remaining=5000) == 32  # growth off


def _layered_scene() -> Gaussians:
    """60 opaque layers: long lists, pixels that stop near T = 1e-4 while their tile goes on."""
    g = random_scene(60, b=1, sh_degree=1, seed=8)
    means = g.means.clone()
    means[0, :, 2] = torch.linspace(2.0, 4.0, 60, dtype=torch.float64)
    return Gaussians(means, g.quats, g.scales * 3, torch.full_like(g.opacities, 0.95), g.sh)


# 12 tiles of 64 pixels at chunk 3: 0 keeps every step at 3 (every chunk boundary is crossed); 768 lets the
# step grow once fewer than 4 tiles are active (steps of 3, then 6, 12, ... mid-walk); 2^18 takes whole
# lists in one step.
@pytest.mark.parametrize("step_elements", [0, 768, 1 << 18])
def test_step_sizes_match_reference_float64(step_elements):
    g = _layered_scene()
    ext, intr = cameras(1, 1)
    weights = [torch.rand(1, 1, c, H, W, dtype=torch.float64) for c in (3, 1, 1)]
    bg = torch.rand(1, 3, dtype=torch.float64)
    ref_out, ref_grad = outputs_and_grads(reference_fn, leaf_tensors(g, ext, intr, bg, torch.float64), weights)
    fn = torch_fn(chunk=3, tile_size=8, step_elements=step_elements)
    out, grad = outputs_and_grads(fn, leaf_tensors(g, ext, intr, bg, torch.float64), weights)
    for a, b in zip(out + grad, ref_out + ref_grad):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11)


@pytest.mark.parametrize("step_elements", [0, 48])
def test_gradcheck_with_fixed_and_growing_steps(step_elements):
    g = random_scene(6, sh_degree=1, seed=5, spread=0.3)
    g = Gaussians(g.means, g.quats, g.scales * 2, g.opacities.clamp(0.3, 0.8), g.sh)
    ext, intr = cameras(1, 2)

    def fn(means, quats, scales, opacities, sh, extrinsics, intrinsics):
        out = render(Gaussians(means, quats, scales, opacities, sh), extrinsics, intrinsics, 7, 9,
                     backend="torch", tile_size=4, chunk=1, step_elements=step_elements)  # fmt: skip
        return out.color, out.depth, out.alpha

    inputs = [t.clone().requires_grad_() for t in (g.means, g.quats, g.scales, g.opacities, g.sh, ext, intr)]
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_small_image_walks_its_long_lists_in_few_steps(monkeypatch):
    """Few tiles with long lists (a small target): the steps grow, the walk is short, the image the same."""
    g = random_scene(400, b=1, sh_degree=0, seed=3, dtype=torch.float32)
    ext, intr = cameras(1, 1, dtype=torch.float32)
    calls = []
    step = composite._forward_chunk
    monkeypatch.setattr(composite, "_forward_chunk", lambda p, *a: calls.append(p.shape[1]) or step(p, *a))
    grown = render(g, ext, intr, 10, 10, backend="torch", chunk=4)
    grown_steps, calls[:] = list(calls), []
    fixed = render(g, ext, intr, 10, 10, backend="torch", chunk=4, step_elements=0)
    assert set(calls) == {4} and len(calls) >= 25  # 4 tiles, lists of 100+ Gaussians
    assert len(grown_steps) <= 3 and max(grown_steps) >= 128
    for a, b in zip((grown.color, grown.depth, grown.alpha), (fixed.color, fixed.depth, fixed.alpha)):
        torch.testing.assert_close(a, b, rtol=3e-5, atol=1e-5)
