"""Gaussian head: a second DPT plus a small conv branch on the RGB image -> per-pixel Gaussian attributes."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from aesplat.geometry import safe_norm

from .dpt import DPT

# How the head's scale outputs become Gaussian scales (``model.net.options.scale_mode``):
#   absolute  scene units, multiplier * softplus(raw) (the paper's and NoPoSplat's parametrisation);
#   pixel     pixels at the Gaussian's own depth, lo + (hi - lo) * sigmoid(raw) with (lo, hi) = scale_pixels,
#             turned into scene units by depth / focal length (pixelSplat's and MVSplat's): a Gaussian is at
#             least ``lo`` pixels wide in its own view at any depth and image size, never a sub-pixel point.
SCALE_MODES = ("absolute", "pixel")
PIXEL_SCALE_INIT = 1.0  # pixel mode: the initial scale, in pixels


@dataclass(frozen=True)
class GaussianHeadOutput:
    """Per-pixel attributes of N views' Gaussians, pixels in raster order (P = H·W).

    quats      [N, P, 4]  rotation in the camera frame (w, x, y, z), unit length
    scales     [N, P, 3]  > 0: scene units, capped (absolute), or pixels at the Gaussian's depth (pixel: the
                          model turns them into scene units, ``pixel_scales_to_scene``)
    opacities  [N, P]     in (0, 1)
    sh         [N, P, S, 3] SH coefficients the head predicts itself (baseline modes), else None
    features   [N, P, F]  intermediate features (the view-dependent appearance head's input)
    """

    quats: Tensor
    scales: Tensor
    opacities: Tensor
    sh: Tensor | None
    features: Tensor


class GaussianHead(nn.Module):
    """DPT features, upsampled to full resolution and fused with an RGB conv branch, then a 1x1 output conv.

    ``num_sh`` is the number of SH coefficients this head predicts (0 when I2DC and the view-dependent
    head supply them, K in ``baseline``, K - 1 in ``baseline_i2dc``). ``scale_mode`` (``SCALE_MODES``) says
    what the scale outputs mean: ``scale_multiplier`` serves the absolute mode, ``scale_pixels`` the pixel mode.
    """

    def __init__(
        self,
        in_dim: int,
        features: int,
        layer_channels: tuple[int, int, int, int],
        feature_dim: int,
        num_sh: int,
        scale_multiplier: float = 0.001,
        scale_max: float = 0.3,
        precision: str = "fp32",
        scale_mode: str = "absolute",
        scale_pixels: tuple[float, float] = (0.5, 15.0),
    ) -> None:
        super().__init__()
        if scale_mode not in SCALE_MODES:
            raise ValueError(f"unknown scale_mode {scale_mode!r}; choose one of {', '.join(SCALE_MODES)}")
        lo, hi = scale_pixels
        if scale_mode == "pixel" and not 0 < lo < PIXEL_SCALE_INIT < hi:
            raise ValueError(
                f"scale_pixels must be (lo, hi) with 0 < lo < {PIXEL_SCALE_INIT} < hi, got {scale_pixels}"
            )
        self.num_sh = num_sh
        self.scale_mode = scale_mode
        self.scale_multiplier = scale_multiplier
        self.scale_max = scale_max
        self.scale_pixels = (float(lo), float(hi))
        half = features // 2
        self.dpt = DPT(in_dim, features, layer_channels, precision)
        self.neck = nn.Conv2d(features, half, 3, padding=1)
        self.rgb_branch = nn.Sequential(
            nn.Conv2d(3, half, 3, padding=1), nn.ReLU(), nn.Conv2d(half, half, 3, padding=1)
        )
        self.feature_conv = nn.Conv2d(half, feature_dim, 3, padding=1)
        self.out = nn.Conv2d(feature_dim, 4 + 3 + 1 + 3 * num_sh, 1)
        nn.init.normal_(self.out.weight, std=1e-3)
        with torch.no_grad():
            self.out.bias.zero_()
            self.out.bias[0] = 1.0  # identity rotation
            if scale_mode == "pixel":  # start at PIXEL_SCALE_INIT pixels
                self.out.bias[4:7] = math.log((PIXEL_SCALE_INIT - lo) / (hi - PIXEL_SCALE_INIT))

    def forward(self, tokens: list[Tensor], grid: tuple[int, int], images: Tensor) -> GaussianHeadOutput:
        """tokens: 4 maps [N, h·w, in_dim]; images [N, 3, H, W] in [0, 1]."""
        size = images.shape[-2:]
        x = F.interpolate(self.neck(self.dpt(tokens, grid)), size=size, mode="bilinear", align_corners=False)
        feats = F.relu(self.feature_conv(F.relu(x + self.rgb_branch(images))))  # [N, F, H, W]
        raw = self.out(feats).flatten(2).transpose(1, 2)  # [N, P, C]
        quats = raw[..., :4]
        quats = quats / safe_norm(quats, keepdim=True).clamp_min(1e-6)
        if self.scale_mode == "pixel":
            lo, hi = self.scale_pixels
            scales = lo + (hi - lo) * torch.sigmoid(raw[..., 4:7])
        else:
            scales = (self.scale_multiplier * F.softplus(raw[..., 4:7]) + 1e-7).clamp_max(self.scale_max)
        opacities = torch.sigmoid(raw[..., 7]).clamp(1e-6, 1.0 - 1e-6)
        sh = raw[..., 8:].reshape(*raw.shape[:2], self.num_sh, 3) if self.num_sh else None
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
