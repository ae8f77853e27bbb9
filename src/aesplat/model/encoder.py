"""Patch encoder: a DINOv2-style ViT with 14-pixel patches, applied to every view independently.

The architecture and parameter names are those of timm's ``vit_*_patch14_dinov2`` (and of the original
DINOv2 release, which differs only in a few names), so a local checkpoint of either loads by name; see
:func:`load_encoder_weights`. Nothing is ever downloaded.
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

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


class PatchEncoder(nn.Module):
    """DINOv2-style ViT/14 with ImageNet normalisation inside.

    images [B, 3, H, W] in [0, 1] (H, W multiples of 14) -> patch tokens [B, (H/14)·(W/14), dim] after the
    final LayerNorm (class and register tokens are dropped).
    """

    def __init__(self, cfg: EncoderConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d = cfg.dim
        self.patch_embed = nn.Module()
        self.patch_embed.proj = nn.Conv2d(3, d, PATCH_SIZE, PATCH_SIZE)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, d))
        self.reg_token = nn.Parameter(torch.zeros(1, cfg.num_registers, d)) if cfg.num_registers else None
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + cfg.pos_grid**2, d))
        self.blocks = nn.ModuleList(Block(d, cfg.num_heads, cfg.mlp_ratio) for _ in range(cfg.depth))
        self.norm = nn.LayerNorm(d, eps=1e-6)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        init_weights(self)
        for p in (self.cls_token, self.pos_embed, self.reg_token):
            if p is not None:
                nn.init.trunc_normal_(p, std=0.02)

    def _pos_embed(self, h: int, w: int) -> Tensor:
        """Position embedding for an h x w patch grid: [1, 1 + h·w, dim] (class token first)."""
        g = self.cfg.pos_grid
        cls_pos, patch_pos = self.pos_embed[:, :1], self.pos_embed[:, 1:]
        if (h, w) != (g, g):
            grid = patch_pos.reshape(1, g, g, -1).permute(0, 3, 1, 2)
            grid = F.interpolate(grid, size=(h, w), mode="bicubic", align_corners=False)
            patch_pos = grid.permute(0, 2, 3, 1).reshape(1, h * w, -1)
        return torch.cat([cls_pos, patch_pos], dim=1)

    def forward(self, images: Tensor) -> Tensor:
        """images [B, 3, H, W] in [0, 1] -> patch tokens [B, h·w, dim]."""
        x = (images - self.mean) / self.std
        x = self.patch_embed.proj(x)  # [B, dim, h, w]
        h, w = x.shape[-2:]
        x = x.flatten(2).transpose(1, 2)
        x = torch.cat([self.cls_token.expand(x.shape[0], -1, -1), x], dim=1) + self._pos_embed(h, w)
        if self.reg_token is not None:
            x = torch.cat([x[:, :1], self.reg_token.expand(x.shape[0], -1, -1), x[:, 1:]], dim=1)
        for block in self.blocks:
            x = block(x)
        return self.norm(x)[:, 1 + self.cfg.num_registers :]


@dataclass
class WeightsReport:
    """What :func:`load_encoder_weights` did: the detected format and the keys it could not match."""

    path: str
    format: str  # "timm" or "dinov2"
    loaded: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)  # encoder parameters the checkpoint lacks
    unexpected: list[str] = field(default_factory=list)  # checkpoint keys the encoder does not have
    ignored: list[str] = field(default_factory=list)  # known keys with no use here (DINOv2's mask_token)


# Keys of the original DINOv2 release that the encoder deliberately has no use for.
_DINOV2_UNUSED = {"mask_token"}


def _unwrap(obj: object) -> dict[str, Tensor]:
    """Find the state dict inside a checkpoint ({"model": ...}, {"state_dict": ...}, {"teacher": ...})."""
    while isinstance(obj, dict) and not any(isinstance(v, Tensor) for v in obj.values()):
        for key in ("model", "state_dict", "teacher", "module"):
            if key in obj:
                obj = obj[key]
                break
        else:
            break
    if not isinstance(obj, dict) or not obj:
        raise ValueError("the checkpoint holds no state dict (expected a dict of tensors)")
    return {k: v for k, v in obj.items() if isinstance(v, Tensor)}


def convert_encoder_state_dict(state: dict[str, Tensor]) -> tuple[dict[str, Tensor], str, list[str]]:
    """Map a timm or original-DINOv2 ViT/14 state dict onto :class:`PatchEncoder` names.

    Returns (converted state, detected format, ignored keys). Handles "module."/"backbone."/"encoder."
    prefixes, DINOv2's block chunks (``blocks.c.i.``), ``register_tokens`` -> ``reg_token``, and position
    embeddings without a class-token entry (timm's ``reg4`` models), which get a zero class-token row.
    """
    out: dict[str, Tensor] = {}
    ignored: list[str] = []
    fmt = "dinov2" if any(k.endswith(("register_tokens", "mask_token")) for k in state) else "timm"
    for key, value in state.items():
        k = re.sub(r"^(module\.|backbone\.|encoder\.|model\.)+", "", key)
        k = re.sub(r"^blocks\.\d+\.(\d+)\.", r"blocks.\1.", k)  # DINOv2 block chunks
        if k in _DINOV2_UNUSED:
            ignored.append(key)
            continue
        if k == "register_tokens":
            k = "reg_token"
        out[k] = value
    pos = out.get("pos_embed")
    if pos is not None and pos.ndim == 3 and math.isqrt(pos.shape[1]) ** 2 == pos.shape[1]:
        out["pos_embed"] = torch.cat([pos.new_zeros(1, 1, pos.shape[2]), pos], dim=1)
    return out, fmt, ignored


def _resize_pos_embed(pos: Tensor, grid: int) -> Tensor:
    """Position embedding [1, 1 + g·g, D] from a checkpoint -> [1, 1 + grid·grid, D] (bicubic)."""
    g = math.isqrt(pos.shape[1] - 1)
    if g * g != pos.shape[1] - 1:
        raise ValueError(f"checkpoint pos_embed has {pos.shape[1] - 1} patch positions, not a square grid")
    if g == grid:
        return pos
    patch = pos[:, 1:].reshape(1, g, g, -1).permute(0, 3, 1, 2).float()
    patch = F.interpolate(patch, size=(grid, grid), mode="bicubic", align_corners=False)
    return torch.cat([pos[:, :1], patch.permute(0, 2, 3, 1).reshape(1, grid * grid, -1).to(pos.dtype)], 1)


def load_encoder_weights(encoder: PatchEncoder, path: str | Path) -> WeightsReport:
    """Load a local timm-format or original-DINOv2 ViT/14 checkpoint into ``encoder``. Never downloads.

    Keys the encoder lacks and encoder parameters the checkpoint lacks are reported with a warning and
    returned in the :class:`WeightsReport`; a shape mismatch (a checkpoint of another size) is an error.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"encoder weights file {path} does not exist; give the path of a local timm or DINOv2 ViT/14 "
            "checkpoint (.pth/.pt/.bin), or leave `weights` unset for random initialisation"
        )
    state = _unwrap(torch.load(path, map_location="cpu", weights_only=True))
    state, fmt, ignored = convert_encoder_state_dict(state)
    own = encoder.state_dict()
    report = WeightsReport(path=str(path), format=fmt, ignored=ignored)
    to_load: dict[str, Tensor] = {}
    for key, value in state.items():
        if key not in own:
            report.unexpected.append(key)
            continue
        if key == "pos_embed":
            value = _resize_pos_embed(value, encoder.cfg.pos_grid)
        if value.shape != own[key].shape:
            raise ValueError(
                f"{path}: '{key}' has shape {tuple(value.shape)} but the encoder expects "
                f"{tuple(own[key].shape)}; pick the model size that matches the checkpoint "
                f"(encoder width {encoder.cfg.dim}, depth {encoder.cfg.depth})"
            )
        to_load[key] = value.to(own[key].dtype)
    report.loaded = sorted(to_load)
    report.missing = sorted(set(own) - set(to_load))
    encoder.load_state_dict(to_load, strict=False)
    if report.missing or report.unexpected:
        warnings.warn(
            f"encoder weights {path} ({fmt} format): loaded {len(report.loaded)} tensors; "
            f"missing {len(report.missing)}: {report.missing[:8]}; "
            f"unexpected {len(report.unexpected)}: {report.unexpected[:8]}",
            stacklevel=2,
        )
    return report
