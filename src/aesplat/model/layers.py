"""Transformer building blocks shared by the patch encoder and the geometry transformer.

Parameter names follow timm / DINOv2 (``attn.qkv``, ``attn.proj``, ``ls1.gamma``, ``mlp.fc1`` ...) so that
pretrained checkpoints load by name.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class RopeTables(NamedTuple):
    """Rotary tables of one token sequence: ``rotate`` gives x·cos + partner(x)·sin, both [T, head_dim]."""

    cos: Tensor
    sin: Tensor  # signed: −sin on the first quarter of each half, +sin on the second

    def repeat(self, n: int) -> RopeTables:
        """Tables of n copies of the sequence one after another ([n·T, head_dim])."""
        return RopeTables(self.cos.repeat(n, 1), self.sin.repeat(n, 1))

    def rotate(self, x: Tensor) -> Tensor:
        """x [..., T, head_dim] -> x rotated, same shape and dtype.

        Each half of the head (row, column) is in rotate-half layout: its partner swaps the half's two
        quarters, and the sign lives in ``sin``. The same products and sum as the textbook form
        x·cos + cat(−x2, x1)·sin, so the result is bit-identical to it.
        """
        partner = x.unflatten(-1, (2, 2, -1)).flip(-2).flatten(-3)
        return x * self.cos.to(x.dtype) + partner * self.sin.to(x.dtype)


class RoPE2D(nn.Module):
    """2D rotary position embedding: half of each head's channels rotate with the row, half with the column.

    Positions are integer (row, col) pairs; the geometry transformer gives special tokens (0, 0) and patch
    tokens (i + 1, j + 1), as VGGT does. ``tables`` is computed once per forward and shared by every block.
    """

    def __init__(self, head_dim: int, base: float = 100.0) -> None:
        super().__init__()
        if head_dim % 4 != 0:
            raise ValueError(f"2D RoPE needs a head dimension divisible by 4, got {head_dim}")
        quarter = head_dim // 4
        inv_freq = 1.0 / (base ** (torch.arange(quarter, dtype=torch.float32) / quarter))
        self.register_buffer("inv_freq", inv_freq, persistent=False)

    def tables(self, pos: Tensor) -> RopeTables:
        """pos [T, 2] integer (row, col) -> cos, signed sin [T, head_dim] (float32)."""
        angles = pos.to(torch.float32)[:, :, None, None] * self.inv_freq  # [T, 2 (row, col), 1, head_dim / 4]
        sign = torch.tensor([-1.0, 1.0], device=angles.device)[:, None]  # per quarter of each half
        cos = angles.cos().expand(-1, -1, 2, -1).flatten(1)
        sin = (angles.sin() * sign).flatten(1)
        return RopeTables(cos, sin)


class Attention(nn.Module):
    """Multi-head self-attention on ``F.scaled_dot_product_attention``, optionally masked for context/target.

    With ``num_context`` set, the first ``num_context`` tokens are context tokens: they attend to context
    tokens only, and the remaining (target) tokens attend to everything. This is done as two SDPA calls
    rather than a mask, so the context outputs are computed from context tokens alone and are bit-identical
    whatever the target tokens hold.
    """

    def __init__(self, dim: int, num_heads: int, qk_norm: bool = False) -> None:
        super().__init__()
        if dim % num_heads != 0:
            raise ValueError(f"width {dim} is not divisible by {num_heads} heads")
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.q_norm = nn.LayerNorm(self.head_dim) if qk_norm else nn.Identity()
        self.k_norm = nn.LayerNorm(self.head_dim) if qk_norm else nn.Identity()
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor, rope: RopeTables | None = None, num_context: int | None = None) -> Tensor:
        """x [B, T, D], rope: tables of the T tokens (None: no RoPE), num_context: see the class docstring
        -> [B, T, D]."""
        b, t, d = x.shape
        qkv = self.qkv(x).reshape(b, t, 3, self.num_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)  # [B, heads, T, head_dim]
        q, k = self.q_norm(q), self.k_norm(k)
        if rope is not None:
            q, k = rope.rotate(q), rope.rotate(k)
        if num_context is None or num_context >= t:
            out = F.scaled_dot_product_attention(q, k, v).transpose(1, 2)  # [B, T, heads, head_dim]
        else:
            c = num_context
            out_context = F.scaled_dot_product_attention(q[:, :, :c], k[:, :, :c], v[:, :, :c])
            out_target = F.scaled_dot_product_attention(q[:, :, c:], k, v)
            # joined token-major, so the reshape below is a view (one copy, not two)
            out = torch.cat([out_context.transpose(1, 2), out_target.transpose(1, 2)], dim=1)
        return self.proj(out.reshape(b, t, d))


class LayerScale(nn.Module):
    def __init__(self, dim: int, init: float) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), init))

    def forward(self, x: Tensor) -> Tensor:
        return x * self.gamma


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int, out: int | None = None) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, out or dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(self.act(self.fc1(x)))


class Block(nn.Module):
    """Pre-norm transformer block with LayerScale (DINOv2 / VGGT layout). DINOv2's blocks normalise with eps
    1e-6, VGGT's alternating-attention and camera-head blocks with PyTorch's default 1e-5 (``norm_eps``)."""

    def __init__(
        self,
        dim: int,
        num_heads: int,
        mlp_ratio: float = 4.0,
        layerscale_init: float = 1e-5,
        qk_norm: bool = False,
        norm_eps: float = 1e-6,
    ) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=norm_eps)
        self.attn = Attention(dim, num_heads, qk_norm=qk_norm)
        self.ls1 = LayerScale(dim, layerscale_init)
        self.norm2 = nn.LayerNorm(dim, eps=norm_eps)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))
        self.ls2 = LayerScale(dim, layerscale_init)

    def forward(self, x: Tensor, rope: RopeTables | None = None, num_context: int | None = None) -> Tensor:
        """x [B, T, D] -> [B, T, D]; see :class:`Attention` for ``rope`` and ``num_context``."""
        x = x + self.ls1(self.attn(self.norm1(x), rope=rope, num_context=num_context))
        return x + self.ls2(self.mlp(self.norm2(x)))


def init_weights(module: nn.Module, std: float = 0.02) -> None:
    """Truncated-normal Linear weights and zero biases (the ViT default)."""
    for m in module.modules():
        if isinstance(m, nn.Linear):
            nn.init.trunc_normal_(m.weight, std=std)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
