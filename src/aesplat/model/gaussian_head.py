"""Gaussian head: NAS3R's DPT Gaussian head (a DPT plus a conv branch on the image) -> per-pixel attributes."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from aesplat.geometry import safe_norm

from .dpt import DPTHead

# How the head's scale outputs become Gaussian scales (``model.net.options.scale_mode``):
#   absolute  scene units, multiplier * softplus(raw) (the paper's and NoPoSplat's parametrisation);
#   pixel     pixels at the Gaussian's own depth, lo + (hi - lo) * sigmoid(raw) with (lo, hi) = scale_pixels,
#             turned into scene units by depth / focal length (pixelSplat's and MVSplat's): a Gaussian is at
#             least ``lo`` pixels wide in its own view at any depth and image size, never a sub-pixel point.
SCALE_MODES = ("absolute", "pixel")
PIXEL_SCALE_INIT = 1.0  # pixel mode: the initial scale, in pixels


def sh_mask(sh_degree: int) -> Tensor:
    """NAS3R's (pixelSplat's) factor on the head's SH coefficients [K]: 1 for degree 0, 0.1·0.25^l for degree
    l, so a new head starts almost view-independent."""
    return torch.cat([torch.full((2 * l + 1,), 1.0 if l == 0 else 0.1 * 0.25**l) for l in range(sh_degree + 1)])


@dataclass(frozen=True)
class GaussianHeadOutput:
    """Per-pixel attributes of N views' Gaussians, pixels in raster order (P = H·W).

    quats      [N, P, 4]  rotation (w, x, y, z), unit length, in view 0's frame as NAS3R takes it (the head
                          is not told its view's rotation)
    scales     [N, P, 3]  > 0: scene units, capped (absolute), or pixels at the Gaussian's depth (pixel: the
                          model turns them into scene units, ``pixel_scales_to_scene``)
    opacities  [N, P]     in (0, 1)
    sh         [N, P, K, 3] SH coefficients the head predicts (times ``sh_mask``); the appearance mode says
                          which of them are used
    features   [N, P, F]  the map before the output convolution (the view-dependent appearance head's input)
    """

    quats: Tensor
    scales: Tensor
    opacities: Tensor
    sh: Tensor
    features: Tensor


class GaussianHead(DPTHead):
    """NAS3R's Gaussian head: VGGT's DPT with a 7x7 conv branch on the raw [0, 1] image (``input_merger``) added
    to its full-resolution map, then the output convolutions -> 1 + 3 + 4 + 3·K channels per pixel: opacity
    (sigmoid), scales, quaternion (normalised), SH of degree ``sh_degree`` channel-major (all red
    coefficients, then green, then blue; NAS3R: 83 channels at degree 4) times ``sh_mask``.

    ``scale_mode`` (``SCALE_MODES``): ``absolute`` is NAS3R's ``scale_multiplier``·softplus(x) capped at
    ``scale_max``; ``pixel`` is ``scale_pixels`` (lo, hi) as lo + (hi − lo)·sigmoid(x) pixels.
    """

    def __init__(
        self,
        in_dim: int,
        features: int,
        layer_channels: tuple[int, int, int, int],
        patch_size: int,
        sh_degree: int,
        scale_multiplier: float = 0.001,
        scale_max: float = 0.3,
        precision: str = "fp32",
        scale_mode: str = "absolute",
        scale_pixels: tuple[float, float] = (0.5, 15.0),
    ) -> None:
        if scale_mode not in SCALE_MODES:
            raise ValueError(f"unknown scale_mode {scale_mode!r}; choose one of {', '.join(SCALE_MODES)}")
        lo, hi = scale_pixels
        if scale_mode == "pixel" and not 0 < lo < PIXEL_SCALE_INIT < hi:
            raise ValueError(
                f"scale_pixels must be (lo, hi) with 0 < lo < {PIXEL_SCALE_INIT} < hi, got {scale_pixels}"
            )
        self.num_sh = (sh_degree + 1) ** 2
        super().__init__(in_dim, features, layer_channels, patch_size, 8 + 3 * self.num_sh, precision)
        self.input_merger = nn.Sequential(nn.Conv2d(3, features // 2, 7, 1, 3), nn.ReLU())
        self.scale_mode = scale_mode
        self.scale_multiplier = scale_multiplier
        self.scale_max = scale_max
        self.scale_pixels = (float(lo), float(hi))
        self.register_buffer("sh_mask", sh_mask(sh_degree), persistent=False)
        if scale_mode == "pixel":  # start at PIXEL_SCALE_INIT pixels
            with torch.no_grad():
                start = math.log((PIXEL_SCALE_INIT - lo) / (hi - PIXEL_SCALE_INIT))
                self.scratch.output_conv2[-1].bias[1:4] = start

    def forward(self, tokens: list[Tensor], images: Tensor) -> GaussianHeadOutput:
        """tokens: 4 maps [N, h·w, in_dim] (patch tokens); images [N, 3, H, W] in [0, 1]."""
        feats = self.features(tokens, images.shape[-2:]) + self.input_merger(images)
        raw = self.scratch.output_conv2(feats).flatten(2).transpose(1, 2)  # [N, P, C]
        opacities = torch.sigmoid(raw[..., 0]).clamp(1e-6, 1.0 - 1e-6)
        if self.scale_mode == "pixel":
            lo, hi = self.scale_pixels
            scales = lo + (hi - lo) * torch.sigmoid(raw[..., 1:4])
        else:
            scales = (self.scale_multiplier * F.softplus(raw[..., 1:4])).clamp(1e-9, self.scale_max)
        quats = raw[..., 4:8]
        quats = quats / (safe_norm(quats, keepdim=True) + 1e-8)
        sh = raw[..., 8:].unflatten(-1, (3, self.num_sh)).transpose(-1, -2) * self.sh_mask[:, None]
        return GaussianHeadOutput(quats, scales, opacities, sh, feats.flatten(2).transpose(1, 2))


def pixel_footprint(intrinsics: Tensor, height: int, width: int) -> Tensor:
    """Side of a pixel at unit depth, in scene units per unit depth [...]: the mean of 1 / (fx·W) and 1 / (fy·H)
    of normalised intrinsics [..., 3, 3]."""
    return 0.5 / (intrinsics[..., 0, 0] * width) + 0.5 / (intrinsics[..., 1, 1] * height)


def pixel_scales_to_scene(
    scales: Tensor,  # [B, V, P, 3] pixels at the Gaussian's depth
    depth: Tensor,  # [B, V, H, W] z-depth of each pixel's Gaussian in its view
    intrinsics: Tensor,  # [B, V, 3, 3] normalised, of the views
    scale_max: float,
) -> Tensor:
    """Pixel-mode scales -> scene units [B, V, P, 3]: pixels x depth x a pixel's size at unit depth, capped at
    ``scale_max``."""
    h, w = depth.shape[-2:]
    unit = pixel_footprint(intrinsics, h, w)[..., None, None]  # [B, V, 1, 1]
    return (scales * depth.flatten(2)[..., None] * unit).clamp_max(scale_max)
