"""Patch encoder: a DINOv2-style ViT with 14-pixel patches, applied to every view independently.

The architecture and parameter names are those of timm's ``vit_*_patch14_dinov2`` (and of the original
DINOv2 release, which differs only in a few names), so a local checkpoint of either loads by name (see
``weights.py``). Nothing is ever downloaded.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .layers import Block, init_weights

PATCH_SIZE = 14
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True)
class EncoderConfig:
    """ViT/14 size. DINOv2 small/base/large are (384, 12, 6), (768, 12, 12), (1024, 24, 16)."""

    dim: int = 384
    depth: int = 12
    num_heads: int = 6
    mlp_ratio: float = 4.0
    num_registers: int = 0  # DINOv2 "reg4" models have 4
    pos_grid: int = 37  # learned position grid (DINOv2: 518 / 14); interpolated to the input grid
    # Pixels per patch side. DINOv2 (and any pretrained checkpoint) uses 14; a randomly initialised small model
    # may use a smaller patch for more tokens per image (42 px: 3x3 tokens at 14, 6x6 at 7).
    patch_size: int = PATCH_SIZE
    layerscale_init: float = 1.0  # DINOv2's (VGGT builds its ViT-L with 1.0)

    def __post_init__(self) -> None:
        if self.patch_size < 1:
            raise ValueError(f"encoder patch_size must be >= 1, got {self.patch_size}")


def resize_position_grid(patch_pos: Tensor, size: tuple[int, int]) -> Tensor:
    """A square grid of learned positions [1, g·g, D] -> [1, h·w, D] for an h x w patch grid.

    Bicubic with antialiasing, computed in float32, to the output size (not a scale factor): what VGGT's
    DINOv2 does (``interpolate_antialias=True, interpolate_offset=0.0``) and timm's
    ``resample_abs_pos_embed(..., antialias=True)``, so pretrained weights see the positions they were trained
    with at every resolution (224² from DINOv2's 37 x 37 grid differs by a few percent without antialiasing).
    """
    g = math.isqrt(patch_pos.shape[1])
    if g * g != patch_pos.shape[1]:
        raise ValueError(f"position embedding has {patch_pos.shape[1]} patch positions, not a square grid")
    if (g, g) == tuple(size):
        return patch_pos
    grid = patch_pos.float().reshape(1, g, g, -1).permute(0, 3, 1, 2)  # [1, D, g, g]
    grid = F.interpolate(grid, size=size, mode="bicubic", antialias=True, align_corners=False)
    return grid.permute(0, 2, 3, 1).reshape(1, size[0] * size[1], -1).to(patch_pos.dtype)


class PatchEncoder(nn.Module):
    """DINOv2-style ViT/14 (patch p = ``cfg.patch_size``, 14 unless set) with ImageNet normalisation inside.

    images [B, 3, H, W] in [0, 1] (H, W multiples of p) -> patch tokens [B, (H/p)·(W/p), dim] after the
    final LayerNorm (class and register tokens are dropped).
    """

    def __init__(self, cfg: EncoderConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d = cfg.dim
        self.patch_embed = nn.Module()
        self.patch_embed.proj = nn.Conv2d(3, d, cfg.patch_size, cfg.patch_size)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, d))
        self.register_tokens = (
            nn.Parameter(torch.zeros(1, cfg.num_registers, d)) if cfg.num_registers else None
        )
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + cfg.pos_grid**2, d))
        # DINOv2's masked-image-modelling token: kept so its checkpoints load whole, never used or trained
        self.mask_token = nn.Parameter(torch.zeros(1, d), requires_grad=False)
        self.blocks = nn.ModuleList(
            Block(d, cfg.num_heads, cfg.mlp_ratio, cfg.layerscale_init) for _ in range(cfg.depth)
        )
        self.norm = nn.LayerNorm(d, eps=1e-6)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        init_weights(self)
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        for p in (self.cls_token, self.register_tokens):
            if p is not None:
                nn.init.normal_(p, std=1e-6)

    def _pos_embed(self, h: int, w: int) -> Tensor:
        """Position embedding for an h x w patch grid: [1, 1 + h·w, dim] (class token first)."""
        cls_pos, patch_pos = self.pos_embed[:, :1], self.pos_embed[:, 1:]
        return torch.cat([cls_pos, resize_position_grid(patch_pos, (h, w))], dim=1)

    def forward(self, images: Tensor) -> Tensor:
        """images [B, 3, H, W] in [0, 1] -> patch tokens [B, h·w, dim]."""
        x = (images - self.mean) / self.std
        x = self.patch_embed.proj(x)  # [B, dim, h, w]
        h, w = x.shape[-2:]
        x = x.flatten(2).transpose(1, 2)
        x = torch.cat([self.cls_token.expand(x.shape[0], -1, -1), x], dim=1) + self._pos_embed(h, w)
        if self.register_tokens is not None:
            x = torch.cat([x[:, :1], self.register_tokens.expand(x.shape[0], -1, -1), x[:, 1:]], dim=1)
        for block in self.blocks:
            x = block(x)
        return self.norm(x)[:, 1 + self.cfg.num_registers :]
