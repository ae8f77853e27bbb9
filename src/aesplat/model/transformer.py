"""Geometry transformer: alternating frame / global attention with masked global attention (VGGT, SPFSplatV2).

Every view's tokens are [camera token, register tokens, patch tokens]. View 0 has its own camera and
register tokens; all other views (context or target) share a second set, so the network knows which view
defines the canonical frame. Frame blocks attend within one view; global blocks attend across views with
``masked_global_attention``: context tokens see context tokens only, target tokens see everything, so
target images can never change the Gaussians.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from .layers import Block, RoPE2D, RopeTables, init_weights


@dataclass(frozen=True)
class TransformerConfig:
    dim: int = 384
    depth: int = 12  # number of (frame, global) block pairs
    num_heads: int = 6
    mlp_ratio: float = 4.0
    num_register_tokens: int = 4
    rope: bool = True
    qk_norm: bool = True


def intermediate_layers(depth: int) -> tuple[int, int, int, int]:
    """Indices of the 4 block pairs whose outputs feed the DPT heads (VGGT uses 4, 11, 17, 23 of 24)."""
    if depth < 4:
        raise ValueError(f"the geometry transformer needs >= 4 block pairs for the DPT heads, got {depth}")
    return tuple(round(depth * f) - 1 for f in (0.25, 0.5, 0.75, 1.0))  # type: ignore[return-value]


class GeometryTransformer(nn.Module):
    """Alternating-attention decoder over the patch tokens of all views.

    Input patch tokens [B, V, P, in_dim] (context views first), output: 4 intermediate token maps
    [B, V, T, 2·dim] (frame-block and global-block outputs concatenated, as in VGGT), with
    T = 1 + num_register_tokens + P; the camera token is token 0, patches start at ``patch_start``.
    """

    def __init__(self, in_dim: int, cfg: TransformerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d = cfg.dim
        self.patch_start = 1 + cfg.num_register_tokens
        self.layers = intermediate_layers(cfg.depth)
        self.input_proj = nn.Linear(in_dim, d) if in_dim != d else nn.Identity()
        self.rope = RoPE2D(d // cfg.num_heads) if cfg.rope else None

        def block() -> Block:
            return Block(d, cfg.num_heads, cfg.mlp_ratio, 0.01, qk_norm=cfg.qk_norm)

        self.frame_blocks = nn.ModuleList(block() for _ in range(cfg.depth))
        self.global_blocks = nn.ModuleList(block() for _ in range(cfg.depth))
        # index 0: view 0; index 1: shared by every other view
        self.camera_token = nn.Parameter(torch.randn(1, 2, 1, d) * 1e-6)
        self.register_token = nn.Parameter(torch.randn(1, 2, cfg.num_register_tokens, d) * 1e-6)
        init_weights(self)

    def _special_tokens(self, b: int, v: int) -> Tensor:
        """[B, V, 1 + R, dim]: view 0 gets the first set, the other views the shared second set."""
        tokens = torch.cat([self.camera_token, self.register_token], dim=2)  # [1, 2, 1 + R, d]
        per_view = torch.cat([tokens[:, :1], tokens[:, 1:].expand(-1, v - 1, -1, -1)], dim=1)
        return per_view.expand(b, -1, -1, -1)

    def _positions(self, h: int, w: int, device: torch.device) -> Tensor:
        """RoPE positions of one view's tokens [T, 2]: special tokens at (0, 0), patches at (i + 1, j + 1)."""
        ys, xs = torch.meshgrid(torch.arange(h, device=device), torch.arange(w, device=device), indexing="ij")
        patches = torch.stack([ys.flatten(), xs.flatten()], dim=-1) + 1
        special = torch.zeros(self.patch_start, 2, dtype=patches.dtype, device=device)
        return torch.cat([special, patches], dim=0)

    def forward(self, patch_tokens: Tensor, grid: tuple[int, int], num_context: int) -> list[Tensor]:
        """patch_tokens [B, V, h·w, in_dim], grid (h, w), num_context = Vc -> 4 maps [B, V, T, 2·dim]."""
        b, v, p, _ = patch_tokens.shape
        x = torch.cat([self._special_tokens(b, v).to(patch_tokens.dtype), self.input_proj(patch_tokens)], dim=2)
        t = x.shape[2]
        # computed once here and shared by all blocks: one view's tokens, and all views' tokens in a row
        rope = self.rope.tables(self._positions(*grid, device=x.device)) if self.rope is not None else None
        rope_all = rope.repeat(v) if rope is not None else None
        outputs: list[Tensor] = []
        for i, (frame, global_) in enumerate(zip(self.frame_blocks, self.global_blocks)):
            x = frame(x.reshape(b * v, t, -1), rope=rope).reshape(b, v, t, -1)
            frame_out = x
            x = self.masked_global_attention(global_, x, rope_all, num_context)
            if i in self.layers:
                outputs.append(torch.cat([frame_out, x], dim=-1))
        return outputs

    @staticmethod
    def masked_global_attention(block: Block, x: Tensor, rope: RopeTables | None, num_context: int) -> Tensor:
        """One global block over all views' tokens [B, V, T, D]; context tokens attend to context only."""
        b, v, t, d = x.shape
        out = block(x.reshape(b, v * t, d), rope=rope, num_context=num_context * t)
        return out.reshape(b, v, t, d)
