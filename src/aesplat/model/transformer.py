"""The trunk: a DINOv2 patch encoder, then alternating frame / global attention with masked global attention
(VGGT's aggregator as NAS3R uses it).

Every view's tokens are [camera token, register tokens, patch tokens]; with ``intrinsics_tokens`` (NAS3R's
``-I`` checkpoints) a token embedding each view's normalised intrinsics comes first, [K, camera, registers,
patches], and it is what sits at index 0, where the camera head reads. View 0 has its own camera and register
tokens; all other views (context or target) share a second set, so the network knows which view defines the
canonical frame. Frame blocks attend within one view; global blocks attend across views with
``masked_global_attention``: context tokens see context tokens only, target tokens see everything, so target
images can never change the Gaussians.

Module and parameter names are VGGT's (``patch_embed``, ``frame_blocks``, ``global_blocks``, ``camera_token``,
``register_token``, ``intrinsic_encoder``), so VGGT's and NAS3R's ``aggregator.*`` tensors load by name.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from .encoder import EncoderConfig, PatchEncoder
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
    # the 4 block pairs whose outputs feed the DPT heads; None: intermediate_layers(depth) (VGGT: 4, 11, 17, 23)
    layers: tuple[int, int, int, int] | None = None
    intrinsics_tokens: bool = False  # NAS3R's -I: a token from each view's intrinsics, first in the view


def intermediate_layers(depth: int) -> tuple[int, int, int, int]:
    """Indices of the 4 block pairs whose outputs feed the DPT heads: VGGT's 4, 11, 17, 23 of 24, and at other
    depths the same fractions (1/6, 1/2, 3/4 and the last)."""
    if depth < 4:
        raise ValueError(f"the geometry transformer needs >= 4 block pairs for the DPT heads, got {depth}")
    return (max(depth // 6, 0), depth // 2 - 1, 3 * depth // 4 - 1, depth - 1)


class Aggregator(nn.Module):
    """Patch encoder plus alternating attention over the tokens of all views.

    Input images [B, V, 3, H, W] in [0, 1] (context views first), output: 4 intermediate token maps
    [B, V, T, 2·dim] (frame-block and global-block outputs concatenated, as in VGGT), the last one the last
    block pair's, with T = ``patch_start`` + P; the camera head reads token 0, patches start at
    ``patch_start``.
    """

    def __init__(self, encoder: EncoderConfig, cfg: TransformerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d = cfg.dim
        self.patch_embed = PatchEncoder(encoder)
        self.patch_start = 1 + cfg.num_register_tokens + int(cfg.intrinsics_tokens)
        self.layers = cfg.layers or intermediate_layers(cfg.depth)
        last = cfg.depth - 1
        if len(self.layers) != 4 or self.layers[-1] != last or sorted(set(self.layers)) != [*self.layers]:
            raise ValueError(f"layers must be 4 increasing block indices ending at {last}: {self.layers}")
        self.input_proj = nn.Linear(encoder.dim, d) if encoder.dim != d else nn.Identity()
        self.rope = RoPE2D(d // cfg.num_heads) if cfg.rope else None

        def block() -> Block:
            return Block(d, cfg.num_heads, cfg.mlp_ratio, 0.01, qk_norm=cfg.qk_norm, norm_eps=1e-5)

        self.frame_blocks = nn.ModuleList(block() for _ in range(cfg.depth))
        self.global_blocks = nn.ModuleList(block() for _ in range(cfg.depth))
        # index 0: view 0; index 1: shared by every other view
        self.camera_token = nn.Parameter(torch.randn(1, 2, 1, d) * 1e-6)
        self.register_token = nn.Parameter(torch.randn(1, 2, cfg.num_register_tokens, d) * 1e-6)
        self.intrinsic_encoder = nn.Linear(9, d) if cfg.intrinsics_tokens else None
        init_weights(self.frame_blocks)
        init_weights(self.global_blocks)
        if isinstance(self.input_proj, nn.Linear):
            init_weights(self.input_proj)

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

    def forward(self, images: Tensor, num_context: int, intrinsics: Tensor | None = None) -> list[Tensor]:
        """images [B, V, 3, H, W], num_context = Vc, intrinsics [B, V, 3, 3] normalised (with
        ``intrinsics_tokens`` only) -> 4 maps [B, V, T, 2·dim]."""
        b, v = images.shape[:2]
        p = self.patch_embed.cfg.patch_size
        grid = (images.shape[-2] // p, images.shape[-1] // p)
        patches = self.patch_embed(images.flatten(0, 1)).unflatten(0, (b, v))  # [B, V, P, D]
        tokens = [self._special_tokens(b, v).to(patches.dtype), self.input_proj(patches)]
        if self.intrinsic_encoder is not None:
            if intrinsics is None:
                raise ValueError("this network takes every view's intrinsics (an -I network); none were given")
            tokens.insert(0, self.intrinsic_encoder(intrinsics.flatten(2).to(patches.dtype))[:, :, None])
        x = torch.cat(tokens, dim=2)
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
