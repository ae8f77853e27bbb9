"""The Gaussian head's scale modes: absolute (scene units) and pixel (pixels at the Gaussian's own depth)."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from aesplat.model import build_model
from aesplat.model.gaussian_head import GaussianHead, pixel_footprint, pixel_scales_to_scene


def _largest_axis_in_pixels(out, size: int) -> torch.Tensor:
    """The largest scale of every Gaussian in pixels of its own view [B, Vc·H·W] (depth / focal length)."""
    k = out.intrinsics[:, : out.num_context_views]
    unit = pixel_footprint(k, size, size)[..., None]  # [B, Vc, 1]
    return out.gaussians.scales.amax(-1) / (out.depth.flatten(2) * unit).flatten(1)


def _scale_outputs(model, bias: float | None = None):
    """Zero the weights of the Gaussian head's three scale outputs (and set their bias): a head whose features
    say nothing about the scales, so that each mode's scale is a function of the bias alone. A new head is
    NAS3R's, whose output convolution has PyTorch's default (random) initialisation."""
    out = model.gaussian_head.scratch.output_conv2[-1]
    with torch.no_grad():
        out.weight[1:4] = 0.0
        if bias is not None:
            out.bias[1:4] = bias
    return model


def test_pixel_mode_starts_at_one_pixel_at_every_depth_and_size():
    torch.manual_seed(0)
    for size in (28, 42):
        # near depths: a pixel at NAS3R's default depths (1 to 100) is wider than the cap scale_max at 42 px
        model = _scale_outputs(build_model("tiny", "full", 1, scale_mode="pixel", near=0.5, far=5.0))
        out = model(torch.rand(1, 2, 3, size, size), torch.rand(1, 1, 3, size, size))
        pixels = _largest_axis_in_pixels(out, size)
        assert out.depth.std() > 0  # the depths differ, the pixel scales do not
        torch.testing.assert_close(pixels, torch.ones_like(pixels), rtol=2e-3, atol=0)
        # ... while the scene-unit scales follow the depth
        assert out.gaussians.scales.amax(-1).std() > 1e-3 * out.gaussians.scales.mean()


def test_pixel_mode_starts_a_new_head_within_a_few_percent_of_one_pixel():
    """A new head's random output layer moves the pixel scales only a little off the bias's one pixel."""
    torch.manual_seed(0)
    model = build_model("tiny", "full", 1, scale_mode="pixel", near=0.5, far=5.0)
    out = model(torch.rand(1, 2, 3, 42, 42), torch.rand(1, 1, 3, 42, 42))
    pixels = _largest_axis_in_pixels(out, 42)
    torch.testing.assert_close(pixels, torch.ones_like(pixels), rtol=0.05, atol=0)


def test_absolute_mode_is_scene_units_and_far_below_a_pixel_at_the_start():
    """The paper's parametrisation is 0.001·softplus(raw) scene units, whatever the camera: raw 0 gives
    0.001·log 2 at every depth, at the demo's 42 pixels and depths from 1 to 100 far below a pixel."""
    torch.manual_seed(0)
    model = _scale_outputs(build_model("tiny", "full", 1), bias=0.0)
    out = model(torch.rand(1, 2, 3, 42, 42), torch.rand(1, 1, 3, 42, 42))
    assert out.depth.std() > 0
    torch.testing.assert_close(out.gaussians.scales, torch.full_like(out.gaussians.scales, 0.001 * math.log(2)),
                               rtol=2e-3, atol=0)  # fmt: skip
    assert _largest_axis_in_pixels(out, 42).max() < 0.1


def test_pixel_scales_follow_depth_and_focal_length_and_are_capped():
    scales = torch.full((1, 2, 4, 3), 2.0)  # two pixels
    depth = torch.tensor([1.0, 2.0, 3.0, 4.0]).reshape(1, 1, 2, 2).expand(1, 2, 2, 2)
    k = torch.eye(3).expand(1, 2, 3, 3).clone()
    k[0, 1, 0, 0] = k[0, 1, 1, 1] = 2.0  # view 1: twice the focal length
    world = pixel_scales_to_scene(scales, depth, k, scale_max=1.5)
    # a pixel at unit depth is 1 / (f·2 px) scene units: view 0 0.5, view 1 0.25
    torch.testing.assert_close(world[0, 0, :, 0], torch.tensor([1.0, 1.5, 1.5, 1.5]))  # 2 px·0.5·depth, capped
    torch.testing.assert_close(world[0, 1, :, 0], torch.tensor([0.5, 1.0, 1.5, 1.5]))


def test_pixel_mode_range_is_bounded_and_differentiable():
    head = GaussianHead(8, 8, (4, 4, 8, 8), 14, 0, scale_mode="pixel", scale_pixels=(0.5, 15.0))
    out_conv = head.scratch.output_conv2[-1]  # channels: opacity, 3 scales, 4 quaternion, SH
    with torch.no_grad():
        out_conv.bias[1:4] = torch.tensor([-1e4, 0.0, 1e4])
    tokens = [torch.randn(2, 4, 8) for _ in range(4)]  # 2 x 2 patches of 14 pixels
    out = head(tokens, torch.rand(2, 3, 28, 28))
    assert out.scales.shape == (2, 28 * 28, 3)
    assert out.scales[..., 0].min() >= 0.5 and out.scales[..., 2].max() <= 15.0
    assert out.scales[..., 1].min() > 0.5 and out.scales[..., 1].max() < 15.0
    out.scales[..., 1].sum().backward()
    assert out_conv.bias.grad[2] != 0


@pytest.mark.parametrize("pixels", [(0.0, 15.0), (1.5, 15.0), (0.5, 0.9)])
def test_pixel_range_must_hold_the_initial_pixel(pixels):
    with pytest.raises(ValueError, match="scale_pixels"):
        GaussianHead(8, 8, (4, 4, 8, 8), 14, 0, scale_mode="pixel", scale_pixels=pixels)


def test_unknown_scale_mode_is_refused():
    with pytest.raises(ValueError, match="scale_mode"):
        build_model("tiny", "full", 1, scale_mode="relative")


def test_weights_of_another_scale_mode_load_with_a_warning(tmp_path):
    torch.manual_seed(0)
    absolute = build_model("tiny", sh_degree=1)
    path = tmp_path / "absolute.ckpt"
    state = {f"model.{k}": v for k, v in absolute.state_dict().items()}
    torch.save({"state_dict": state, "hyper_parameters": {"net": {"size": "tiny", "sh_degree": 1}}}, path)
    with pytest.warns(UserWarning, match="scale_mode absolute, this model's is pixel"):
        pixel = build_model("tiny", sh_degree=1, scale_mode="pixel", weights=str(path))
    for name, value in absolute.gaussian_head.state_dict().items():  # every tensor, the scale outputs too
        assert torch.equal(pixel.gaussian_head.state_dict()[name], value), name
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the same mode: no warning
        build_model("tiny", sh_degree=1, weights=str(path))
