"""Gaussian head: a second DPT plus a small conv branch on the RGB image -> per-pixel Gaussian attributes."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from aesplat.geometry import safe_norm

from .dpt import DPT


@dataclass(frozen=True)
class GaussianHeadOutput:
    """Per-pixel attributes of N views' Gaussians, pixels in raster order (P = H·W).

    quats      [N, P, 4]  rotation in the camera frame (w, x, y, z), unit length
    scales     [N, P, 3]  > 0, capped
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
    head supply them, K in ``baseline``, K - 1 in ``baseline_i2dc``).
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
    ) -> None:
        super().__init__()
        self.num_sh = num_sh
        self.scale_multiplier = scale_multiplier
        self.scale_max = scale_max
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

    def forward(self, tokens: list[Tensor], grid: tuple[int, int], images: Tensor) -> GaussianHeadOutput:
        """tokens: 4 maps [N, h·w, in_dim]; images [N, 3, H, W] in [0, 1]."""
        size = images.shape[-2:]
        x = F.interpolate(self.neck(self.dpt(tokens, grid)), size=size, mode="bilinear", align_corners=False)
        feats = F.relu(self.feature_conv(F.relu(x + self.rgb_branch(images))))  # [N, F, H, W]
        raw = self.out(feats).flatten(2).transpose(1, 2)  # [N, P, C]
        quats = raw[..., :4]
        quats = quats / safe_norm(quats, keepdim=True).clamp_min(1e-6)
        scales = (self.scale_multiplier * F.softplus(raw[..., 4:7]) + 1e-7).clamp_max(self.scale_max)
        opacities = torch.sigmoid(raw[..., 7]).clamp(1e-6, 1.0 - 1e-6)
        sh = raw[..., 8:].reshape(*raw.shape[:2], self.num_sh, 3) if self.num_sh else None
        return GaussianHeadOutput(quats, scales, opacities, sh, feats.flatten(2).transpose(1, 2))
