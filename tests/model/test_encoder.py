"""Patch encoder: shapes, and loading local timm-format and original-DINOv2-format checkpoints by name."""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from aesplat.model import (
    EncoderConfig,
    PatchEncoder,
    build_model,
    convert_encoder_state_dict,
    load_encoder_weights,
)

DIM, DEPTH = 96, 4  # the tiny preset's encoder


def block_tensors(p: str, dim: int, r, head_dim: int | None = None) -> dict:
    """One block's tensors under prefix ``p`` (timm, DINOv2 and VGGT names); QK-norm when head_dim is given."""
    sd = {
        p + "norm1.weight": r(dim), p + "norm1.bias": r(dim),
        p + "attn.qkv.weight": r(3 * dim, dim), p + "attn.qkv.bias": r(3 * dim),
        p + "attn.proj.weight": r(dim, dim), p + "attn.proj.bias": r(dim),
        p + "ls1.gamma": r(dim),
        p + "norm2.weight": r(dim), p + "norm2.bias": r(dim),
        p + "mlp.fc1.weight": r(4 * dim, dim), p + "mlp.fc1.bias": r(4 * dim),
        p + "mlp.fc2.weight": r(dim, 4 * dim), p + "mlp.fc2.bias": r(dim),
        p + "ls2.gamma": r(dim),
    }  # fmt: skip
    if head_dim is not None:
        for name in ("q_norm", "k_norm"):
            sd |= {p + f"attn.{name}.weight": r(head_dim), p + f"attn.{name}.bias": r(head_dim)}
    return sd


def timm_state_dict(dim: int, depth: int, grid: int, registers: int = 0, cls_pos: bool = True) -> dict:
    """A ViT/14 state dict with timm's ``vit_*_patch14_dinov2`` key names, built from the names alone."""
    g = torch.Generator().manual_seed(1)

    def r(*shape):
        return torch.randn(*shape, generator=g)

    sd = {
        "cls_token": r(1, 1, dim),
        "pos_embed": r(1, grid * grid + (1 if cls_pos else 0), dim),
        "patch_embed.proj.weight": r(dim, 3, 14, 14),
        "patch_embed.proj.bias": r(dim),
        "norm.weight": r(dim),
        "norm.bias": r(dim),
    }
    if registers:
        sd["reg_token"] = r(1, registers, dim)
    for i in range(depth):
        sd |= block_tensors(f"blocks.{i}.", dim, r)
    return sd


def to_dinov2(sd: dict) -> dict:
    """The original DINOv2 release's names: ``register_tokens``, an (unused) ``mask_token``."""
    out = {("register_tokens" if k == "reg_token" else k): v for k, v in sd.items()}
    out["mask_token"] = torch.zeros(1, sd["cls_token"].shape[-1])
    return out


def test_encoder_output_shape_and_normalisation():
    enc = PatchEncoder(EncoderConfig(dim=DIM, depth=2, num_heads=3, num_registers=4, pos_grid=16))
    tokens = enc(torch.rand(2, 3, 28, 42))
    assert tokens.shape == (2, 2 * 3, DIM)
    torch.testing.assert_close(tokens.mean(-1), torch.zeros(2, 6), atol=1e-5, rtol=0)  # final LayerNorm


def pil_bicubic(grid: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Reference resize of a position grid [1, g·g, D] -> [1, h·w, D], one channel at a time with PIL's bicubic
    (antialiased when shrinking; PyTorch's ``antialias=True`` follows PIL, which VGGT and timm rely on)."""
    g = math.isqrt(grid.shape[1])
    channels = grid[0].reshape(g, g, -1).permute(2, 0, 1).double().numpy().astype(np.float32)
    out = [np.asarray(Image.fromarray(c, mode="F").resize((w, h), Image.BICUBIC)) for c in channels]
    return torch.from_numpy(np.stack(out, -1)).reshape(1, h * w, -1)


@pytest.mark.parametrize("side", [224, 280, 700])
def test_position_grid_is_resized_as_vggt_dinov2_does(side):
    """DINOv2's 37 x 37 grid (518 px) at the training resolution 224 px (16 x 16), and up to 50 x 50."""
    enc = PatchEncoder(EncoderConfig(dim=32, depth=1, num_heads=2, pos_grid=37))
    n = side // 14
    pos = enc._pos_embed(n, n)
    assert torch.equal(pos[:, 0], enc.pos_embed[:, 0])  # the class token's position is not resized
    reference = pil_bicubic(enc.pos_embed[:, 1:].detach(), n, n)
    torch.testing.assert_close(pos[:, 1:].detach(), reference, rtol=0, atol=2e-5 * reference.abs().max().item())
    # Without antialiasing the 224 px grid is measurably different (a few percent): the test can tell.
    if side == 224:
        grid = enc.pos_embed[:, 1:].detach().reshape(1, 37, 37, -1).permute(0, 3, 1, 2)
        plain = F.interpolate(grid, size=(n, n), mode="bicubic", align_corners=False)
        plain = plain.permute(0, 2, 3, 1).reshape(1, n * n, -1)
        assert (plain - reference).abs().max() > 0.1 * reference.abs().max()
    assert torch.equal(enc._pos_embed(37, 37), enc.pos_embed)  # the native grid is used as it is


def test_load_timm_checkpoint(tmp_path):
    sd = timm_state_dict(DIM, DEPTH, grid=16)
    path = tmp_path / "vit_tiny_timm.pth"
    torch.save(sd, path)
    model = build_model("tiny", weights=str(path))
    report = model.weights_report
    assert report.format == "timm" and report.missing == [] and report.unexpected == []
    assert model.pretrained_backbone
    own = model.encoder.state_dict()
    for key, value in sd.items():
        assert torch.equal(own[key], value), key


def test_load_dinov2_checkpoint_interpolates_positions_and_reports_keys(tmp_path):
    sd = to_dinov2(timm_state_dict(DIM, DEPTH, grid=37, registers=4))  # 518-pixel position grid
    sd["head.weight"] = torch.zeros(10, DIM)  # a classifier this encoder does not have
    del sd["norm.bias"]
    path = tmp_path / "dinov2_reg.pth"
    torch.save({"model": {"backbone." + k: v for k, v in sd.items()}}, path)
    with pytest.warns(UserWarning, match="missing 1.*norm.bias.*unexpected 1.*head.weight"):
        model = build_model("tiny", weights=str(path), encoder_registers=4)
    report = model.weights_report
    assert report.format == "dinov2"
    assert report.missing == ["norm.bias"] and report.unexpected == ["head.weight"]
    assert report.ignored == ["backbone.mask_token"]
    own = model.encoder.state_dict()
    assert torch.equal(own["reg_token"], sd["register_tokens"])
    assert torch.equal(own["blocks.3.mlp.fc2.weight"], sd["blocks.3.mlp.fc2.weight"])
    assert own["pos_embed"].shape == (1, 1 + 16 * 16, DIM)
    assert torch.equal(own["pos_embed"][:, 0], sd["pos_embed"][:, 0])
    assert model.pretrained_backbone
    with torch.no_grad():
        assert torch.isfinite(model.encoder(torch.rand(1, 3, 28, 28))).all()


def test_load_timm_reg4_checkpoint_without_class_position(tmp_path):
    sd = timm_state_dict(DIM, DEPTH, grid=16, registers=4, cls_pos=False)
    path = tmp_path / "timm_reg4.pth"
    torch.save(sd, path)
    model = build_model("tiny", weights=str(path), encoder_registers=4)
    pos = model.encoder.state_dict()["pos_embed"]
    assert torch.equal(pos[:, 1:], sd["pos_embed"]) and pos[:, 0].eq(0).all()
    assert model.weights_report.missing == [] and model.weights_report.unexpected == []


def test_checkpoint_of_another_size_is_an_error(tmp_path):
    path = tmp_path / "vit_small.pth"
    torch.save(timm_state_dict(384, 1, grid=4), path)
    with pytest.raises(ValueError, match="pick the model size"):
        build_model("tiny", weights=str(path))


def test_missing_weights_file_is_an_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_encoder_weights(PatchEncoder(EncoderConfig(dim=DIM, depth=1, num_heads=3)), tmp_path / "nope.pth")


def test_dinov2_block_chunks_and_prefixes_are_mapped():
    sd = {"module.blocks.1.5.attn.qkv.weight": torch.zeros(1), "blocks.2.ls1.gamma": torch.ones(1)}
    out, fmt, ignored = convert_encoder_state_dict(sd)
    assert set(out) == {"blocks.5.attn.qkv.weight", "blocks.2.ls1.gamma"} and fmt == "timm" and ignored == []


def vggt_state_dict(dim: int, depth: int, registers: int) -> dict:
    """VGGT's aggregator names: ``aggregator.patch_embed.`` (DINOv2 reg4) plus frame / global blocks."""
    g = torch.Generator().manual_seed(2)

    def r(*shape):
        return torch.randn(*shape, generator=g)

    sd = {"aggregator.patch_embed." + k: v for k, v in to_dinov2(timm_state_dict(dim, depth, 37, 4)).items()}
    sd["aggregator.camera_token"] = r(1, 2, 1, dim)
    sd["aggregator.register_token"] = r(1, 2, registers, dim)
    for kind in ("frame_blocks", "global_blocks"):
        for i in range(depth):
            sd |= block_tensors(f"aggregator.{kind}.{i}.", dim, r, head_dim=dim // 3)
    sd["camera_head.trunk.0.weight"] = r(4, 4)  # VGGT's own heads are not ours
    return sd


def test_load_vggt_aggregator(tmp_path):
    sd = vggt_state_dict(DIM, DEPTH, registers=4)
    path = tmp_path / "vggt.pt"
    torch.save(sd, path)
    model = build_model("tiny", weights=str(path), encoder_registers=4, num_register_tokens=4)
    report = model.weights_report
    assert report.format == "vggt" and report.missing == [] and report.unexpected == []
    assert set(report.ignored) == {"aggregator.patch_embed.mask_token", "camera_head.trunk.0.weight"}
    assert model.pretrained_backbone
    t = model.transformer.state_dict()
    assert torch.equal(
        t["global_blocks.3.attn.k_norm.weight"], sd["aggregator.global_blocks.3.attn.k_norm.weight"]
    )
    assert torch.equal(t["register_token"], sd["aggregator.register_token"])
    assert torch.equal(model.encoder.state_dict()["reg_token"], sd["aggregator.patch_embed.register_tokens"])
    with pytest.raises(ValueError, match="register-token"):
        build_model("tiny", weights=str(path), encoder_registers=4, num_register_tokens=2)
