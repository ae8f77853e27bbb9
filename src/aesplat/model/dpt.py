"""DPT (Ranftl et al.) over 4 intermediate token maps, laid out as VGGT's and NAS3R's DPT heads.

Module and parameter names (``projects``, ``resize_layers``, ``scratch.layer1_rn``, ``scratch.refinenet4``,
``scratch.output_conv2`` ...) are those of VGGT's ``DPTHead``, so VGGT's and NAS3R's trained heads load by
name. The computation is theirs too, including three details that change every output:

- a sinusoidal position embedding of the patch grid (scaled by 0.1) is added after each projection and again
  to the full-resolution map;
- every resize is bilinear with ``align_corners=True``;
- the residual units apply their first ReLU in place, so the unit adds its convolutions to ReLU(x), not x.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

HEAD_PRECISIONS = ("fp32", "bf16")


def sincos_embed(dim: int, pos: Tensor, omega_0: float = 100.0) -> Tensor:
    """1D sinusoidal embedding of positions [M] -> [M, dim]: sines then cosines of pos·omega_0^(-2k/dim)."""
    omega = torch.arange(dim // 2, dtype=torch.float64, device=pos.device) / (dim / 2.0)
    angles = pos.reshape(-1, 1) * (1.0 / omega_0**omega)[None]
    return torch.cat([angles.sin(), angles.cos()], dim=1).float()


def grid_position_embed(channels: int, height: int, width: int, aspect: float, device: torch.device) -> Tensor:
    """Position embedding of an h x w grid [channels, h, w]: half the channels embed the column, half the row,
    on coordinates that span the image's aspect ``aspect`` (W / H) scaled by its diagonal, cell centres."""
    diag = (aspect**2 + 1.0) ** 0.5
    span_x, span_y = aspect / diag, 1.0 / diag
    xs = torch.linspace(-span_x * (width - 1) / width, span_x * (width - 1) / width, width, device=device)
    ys = torch.linspace(-span_y * (height - 1) / height, span_y * (height - 1) / height, height, device=device)
    uu, vv = torch.meshgrid(xs, ys, indexing="xy")  # [h, w]
    emb = torch.cat([sincos_embed(channels // 2, uu), sincos_embed(channels // 2, vv)], dim=-1)
    return emb.reshape(height, width, channels).permute(2, 0, 1)


def add_position_embed(x: Tensor, aspect: float, ratio: float = 0.1) -> Tensor:
    """x [N, C, h, w] + ratio · the grid's position embedding."""
    return x + ratio * grid_position_embed(x.shape[1], *x.shape[-2:], aspect, x.device).to(x.dtype)[None]


class ResidualConvUnit(nn.Module):
    """ReLU, conv, ReLU, conv, plus the input after its (in-place) ReLU."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(c, c, 3, padding=1)
        self.conv2 = nn.Conv2d(c, c, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        x = F.relu(x)  # VGGT's unit runs ReLU(inplace=True) on its input, so its skip carries ReLU(x)
        return self.conv2(F.relu(self.conv1(x))) + x


class FusionBlock(nn.Module):
    """Add the refined skip connection, refine, upsample (to ``size`` or 2x), mix channels (VGGT's names)."""

    def __init__(self, c: int, has_residual: bool = True) -> None:
        super().__init__()
        self.resConfUnit1 = ResidualConvUnit(c) if has_residual else None
        self.resConfUnit2 = ResidualConvUnit(c)
        self.out_conv = nn.Conv2d(c, c, 1)

    def forward(self, x: Tensor, skip: Tensor | None = None, size: tuple[int, int] | None = None) -> Tensor:
        if self.resConfUnit1 is not None and skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        size = size or (2 * x.shape[-2], 2 * x.shape[-1])
        return self.out_conv(F.interpolate(x, size=size, mode="bilinear", align_corners=True))


class DPTHead(nn.Module):
    """VGGT's DPT head: 4 token maps of the context views -> a full-resolution map.

    ``output_dim`` > 0: ``scratch.output_conv2`` (3x3 conv to 32, ReLU, 1x1 conv) gives [N, output_dim, H, W]
    raw (the caller activates). ``output_dim`` = 0 (``feature_only``): the [N, features // 2, H, W] map before
    that conv, which the Gaussian head extends. With ``precision="bf16"`` the trunk's convolutions (up to
    ``output_conv1``) run under bf16 autocast; the output convolutions, and what is returned, are float32.
    """

    def __init__(self, in_dim: int, features: int, layer_channels: tuple[int, int, int, int], patch_size: int,
                 output_dim: int = 0, precision: str = "fp32") -> None:  # fmt: skip
        super().__init__()
        if precision not in HEAD_PRECISIONS:
            choices = ", ".join(HEAD_PRECISIONS)
            raise ValueError(f"unknown head precision {precision!r}; choose one of {choices}")
        self.precision = precision
        self.patch_size = patch_size
        c = layer_channels
        self.norm = nn.LayerNorm(in_dim)
        self.projects = nn.ModuleList(nn.Conv2d(in_dim, ci, 1) for ci in c)
        self.resize_layers = nn.ModuleList(
            [
                nn.ConvTranspose2d(c[0], c[0], 4, stride=4),
                nn.ConvTranspose2d(c[1], c[1], 2, stride=2),
                nn.Identity(),
                nn.Conv2d(c[3], c[3], 3, stride=2, padding=1),
            ]
        )
        self.scratch = nn.Module()
        for i, ci in enumerate(c, start=1):
            setattr(self.scratch, f"layer{i}_rn", nn.Conv2d(ci, features, 3, padding=1, bias=False))
        for i in range(1, 5):
            setattr(self.scratch, f"refinenet{i}", FusionBlock(features, has_residual=i < 4))
        self.scratch.output_conv1 = nn.Conv2d(features, features // 2, 3, padding=1)
        if output_dim:
            self.scratch.output_conv2 = nn.Sequential(
                nn.Conv2d(features // 2, 32, 3, padding=1), nn.ReLU(), nn.Conv2d(32, output_dim, 1)
            )

    @property
    def out_features(self) -> int:
        """Channels of the map before ``output_conv2``."""
        return self.scratch.output_conv1.out_channels

    def features(self, tokens: list[Tensor], size: tuple[int, int]) -> Tensor:
        """tokens: 4 maps [N, h·w, in_dim] (patch tokens only); size (H, W) -> [N, features // 2, H, W], with
        the position embedding added at full resolution."""
        device = tokens[0].device.type
        with torch.autocast(device_type=device, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
            return self._features(tokens, size).float()

    def _features(self, tokens: list[Tensor], size: tuple[int, int]) -> Tensor:
        h, w = size[0] // self.patch_size, size[1] // self.patch_size
        aspect = size[1] / size[0]
        levels = []
        for x, project, resize in zip(tokens, self.projects, self.resize_layers):
            x = self.norm(x).transpose(1, 2).reshape(x.shape[0], -1, h, w)
            levels.append(resize(add_position_embed(project(x), aspect)))
        s = self.scratch
        l1, l2, l3, l4 = (rn(x) for rn, x in zip((s.layer1_rn, s.layer2_rn, s.layer3_rn, s.layer4_rn), levels))
        out = s.refinenet4(l4, size=l3.shape[-2:])
        out = s.refinenet3(out, l3, size=l2.shape[-2:])
        out = s.refinenet2(out, l2, size=l1.shape[-2:])
        out = s.output_conv1(s.refinenet1(out, l1))
        out = F.interpolate(out, size=(h * self.patch_size, w * self.patch_size), mode="bilinear",
                            align_corners=True)  # fmt: skip
        return add_position_embed(out, aspect)

    def forward(self, tokens: list[Tensor], size: tuple[int, int]) -> Tensor:
        """tokens: 4 maps [N, h·w, in_dim]; size (H, W) -> raw output [N, output_dim, H, W] (float32: the
        output convolutions run in float32 whatever ``precision``)."""
        return self.scratch.output_conv2(self.features(tokens, size))


class DepthHead(DPTHead):
    """VGGT's depth head as NAS3R configures it: 2 channels, depth = near + (far − near)·sigmoid(x) (NAS3R's
    near 1, far 100) and confidence = 1 + exp(y)."""

    def __init__(self, in_dim: int, features: int, layer_channels: tuple[int, int, int, int], patch_size: int,
                 near: float, far: float, precision: str = "fp32") -> None:  # fmt: skip
        if not 0 <= near < far:
            raise ValueError(f"depth range must satisfy 0 <= near < far, got near={near}, far={far}")
        super().__init__(in_dim, features, layer_channels, patch_size, 2, precision)
        self.near, self.far = float(near), float(far)

    def forward(self, tokens: list[Tensor], size: tuple[int, int]) -> tuple[Tensor, Tensor]:
        """tokens: 4 maps [N, h·w, in_dim] -> depth [N, H, W] in (near, far), confidence [N, H, W] > 1."""
        raw = super().forward(tokens, size)
        s = torch.sigmoid(raw[:, 0])
        return (1 - s) * self.near + s * self.far, 1 + raw[:, 1].exp()
