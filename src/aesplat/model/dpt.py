"""DPT (Ranftl et al.) over 4 intermediate token maps, and the depth head built on it."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class ResidualConvUnit(nn.Module):
    def __init__(self, c: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(c, c, 3, padding=1)
        self.conv2 = nn.Conv2d(c, c, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FusionBlock(nn.Module):
    """Add the skip connection, refine, upsample to ``size``, mix channels."""

    def __init__(self, c: int, has_skip: bool = True) -> None:
        super().__init__()
        self.skip_unit = ResidualConvUnit(c) if has_skip else None
        self.unit = ResidualConvUnit(c)
        self.out_conv = nn.Conv2d(c, c, 1)

    def forward(self, x: Tensor, skip: Tensor | None, size: tuple[int, int]) -> Tensor:
        if self.skip_unit is not None and skip is not None:
            x = x + self.skip_unit(skip)
        x = F.interpolate(self.unit(x), size=size, mode="bilinear", align_corners=False)
        return self.out_conv(x)


HEAD_PRECISIONS = ("fp32", "bf16")


class DPT(nn.Module):
    """Dense prediction trunk: 4 token maps on an h x w patch grid -> a feature map [N, features, 8h, 8w].

    The 4 maps are reassembled at 4x, 2x, 1x and 1/2x the patch grid and fused coarse to fine. With
    ``precision="bf16"`` the trunk's convolutions run under bf16 autocast (the feature map is returned in
    float32); the heads' output layers, and everything geometric after them, stay float32.
    """

    def __init__(
        self, in_dim: int, features: int, layer_channels: tuple[int, int, int, int], precision: str = "fp32"
    ) -> None:
        super().__init__()
        if precision not in HEAD_PRECISIONS:
            choices = ", ".join(HEAD_PRECISIONS)
            raise ValueError(f"unknown head precision {precision!r}; choose one of {choices}")
        self.precision = precision
        c = layer_channels
        self.norm = nn.LayerNorm(in_dim)
        self.project = nn.ModuleList(nn.Conv2d(in_dim, ci, 1) for ci in c)
        self.resize = nn.ModuleList(
            [
                nn.ConvTranspose2d(c[0], c[0], 4, stride=4),
                nn.ConvTranspose2d(c[1], c[1], 2, stride=2),
                nn.Identity(),
                nn.Conv2d(c[3], c[3], 3, stride=2, padding=1),
            ]
        )
        self.layer_rn = nn.ModuleList(nn.Conv2d(ci, features, 3, padding=1, bias=False) for ci in c)
        self.fusion = nn.ModuleList(FusionBlock(features, has_skip=i < 3) for i in range(4))  # [3]: coarsest

    def forward(self, tokens: list[Tensor], grid: tuple[int, int]) -> Tensor:
        """tokens: 4 maps [N, h·w, in_dim]; grid (h, w) -> [N, features, 8h, 8w] float32."""
        device = tokens[0].device.type
        with torch.autocast(device_type=device, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
            return self._trunk(tokens, grid).float()

    def _trunk(self, tokens: list[Tensor], grid: tuple[int, int]) -> Tensor:
        h, w = grid
        levels = []
        for x, project, resize, rn in zip(tokens, self.project, self.resize, self.layer_rn):
            x = self.norm(x).transpose(1, 2).reshape(x.shape[0], -1, h, w)
            levels.append(rn(resize(project(x))))
        l1, l2, l3, l4 = levels
        path = self.fusion[3](l4, None, l3.shape[-2:])  # built without a skip unit
        path = self.fusion[2](path, l3, l2.shape[-2:])
        path = self.fusion[1](path, l2, l1.shape[-2:])
        return self.fusion[0](path, l1, (2 * l1.shape[-2], 2 * l1.shape[-1]))


class DepthHead(nn.Module):
    """DPT -> per-pixel z-depth in [near, far] at the full image resolution.

    The bounded activation interpolates in log depth, depth = near·(far/near)^sigmoid(x), so the initial
    depth is the geometric mean of the range and tiny or huge raw outputs saturate at near / far.
    """

    def __init__(self, in_dim: int, features: int, layer_channels: tuple[int, int, int, int], near: float,
                 far: float, precision: str = "fp32") -> None:  # fmt: skip
        super().__init__()
        if not 0 < near < far:
            raise ValueError(f"depth range must satisfy 0 < near < far, got near={near}, far={far}")
        self.log_near, self.log_far = math.log(near), math.log(far)
        self.dpt = DPT(in_dim, features, layer_channels, precision)
        self.neck = nn.Conv2d(features, features // 2, 3, padding=1)
        self.out = nn.Sequential(nn.Conv2d(features // 2, 32, 3, padding=1), nn.ReLU(), nn.Conv2d(32, 1, 1))

    def forward(self, tokens: list[Tensor], grid: tuple[int, int], size: tuple[int, int]) -> Tensor:
        """tokens: 4 maps [N, h·w, in_dim] -> depth [N, H, W]."""
        x = F.interpolate(self.neck(self.dpt(tokens, grid)), size=size, mode="bilinear", align_corners=False)
        raw = self.out(x)[:, 0]
        return torch.exp(self.log_near + (self.log_far - self.log_near) * torch.sigmoid(raw))
