"""Transformer layers: the rotary tables and the attention against straightforward references."""

import math

import pytest
import torch

from aesplat.model.layers import Attention, RoPE2D


def _textbook_rope(x: torch.Tensor, pos: torch.Tensor, inv_freq: torch.Tensor) -> torch.Tensor:
    """2D RoPE written out: each half of the head rotates with one coordinate, rotate-half layout."""

    def rotate(half, p):
        angles = p.to(torch.float32)[:, None] * inv_freq[None]
        cos = torch.cat([angles.cos(), angles.cos()], dim=-1).to(half.dtype)
        sin = torch.cat([angles.sin(), angles.sin()], dim=-1).to(half.dtype)
        x1, x2 = half.chunk(2, dim=-1)
        return half * cos + torch.cat([-x2, x1], dim=-1) * sin

    xy, xx = x.chunk(2, dim=-1)
    return torch.cat([rotate(xy, pos[:, 0]), rotate(xx, pos[:, 1])], dim=-1)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float64])
def test_rope_tables_rotate_bit_identically_to_the_textbook_form(dtype):
    rope = RoPE2D(16)
    pos = torch.cat([torch.zeros(3, 2, dtype=torch.long), torch.randint(1, 9, (20, 2))])
    x = torch.randn(2, 4, 23, 16).to(dtype)
    assert torch.equal(rope.tables(pos).rotate(x), _textbook_rope(x, pos, rope.inv_freq))
    # the tables of several views in a row rotate each view as its own tables do
    tables = rope.tables(pos)
    x3 = torch.randn(2, 4, 3 * 23, 16).to(dtype)
    want = torch.cat([tables.rotate(part) for part in x3.split(23, dim=2)], dim=2)
    assert torch.equal(tables.repeat(3).rotate(x3), want)


def _reference_attention(attn: Attention, x, rope, num_context):
    """Dense softmax attention with an explicit context/target mask (float64)."""
    b, t, d = x.shape
    h, hd = attn.num_heads, attn.head_dim
    q, k, v = attn.qkv(x).reshape(b, t, 3, h, hd).permute(2, 0, 3, 1, 4)
    q, k = attn.q_norm(q), attn.k_norm(k)
    if rope is not None:
        q, k = rope.rotate(q), rope.rotate(k)
    logits = q @ k.transpose(-1, -2) / math.sqrt(hd)
    allowed = torch.ones(t, t, dtype=torch.bool)
    allowed[:num_context, num_context:] = False  # context queries never see target keys
    out = logits.masked_fill(~allowed, float("-inf")).softmax(-1) @ v
    return attn.proj(out.transpose(1, 2).reshape(b, t, d))


@pytest.mark.parametrize("num_context", [None, 7, 12])
@pytest.mark.parametrize("use_rope", [False, True])
def test_attention_matches_dense_masked_reference(num_context, use_rope):
    torch.manual_seed(0)
    attn = Attention(32, 4, qk_norm=True).double()
    t = 12
    x = torch.randn(2, t, 32, dtype=torch.float64)
    rope = RoPE2D(8).tables(torch.randint(0, 5, (t, 2))) if use_rope else None
    if rope is not None:
        rope = type(rope)(rope.cos.double(), rope.sin.double())
    got = attn(x, rope=rope, num_context=num_context)
    want = _reference_attention(attn, x, rope, t if num_context is None else num_context)
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
