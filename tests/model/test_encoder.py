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
from aesplat.model.weights import load_pretrained_weights, load_vggt_weights

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
    """The original DINOv2 release's names: ``register_tokens``, a ``mask_token`` (not zero, as trained)."""
    out = {("register_tokens" if k == "reg_token" else k): v for k, v in sd.items()}
    out["mask_token"] = torch.randn(1, sd["cls_token"].shape[-1], generator=torch.Generator().manual_seed(3))
    return out


# timm's DINOv2 checkpoints have no mask_token (DINOv2's masked-image-modelling token); the encoder keeps one,
# frozen and unused, so that DINOv2's and VGGT's checkpoints load whole. A timm file lacking it is complete: the
# token is not reported missing (and it keeps its initialisation).
TIMM_MISSING: list[str] = []


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
    assert report.format == "timm" and report.missing == TIMM_MISSING and report.unexpected == []
    assert model.pretrained_backbone
    # the encoder is the aggregator's patch_embed, and the report names its tensors so
    assert model.encoder is model.aggregator.patch_embed
    assert sorted(report.loaded) == sorted("aggregator.patch_embed." + k for k in sd)
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
    assert report.missing == ["aggregator.patch_embed.norm.bias"]
    # the classifier is unexpected (under which name: test_an_encoder_checkpoint_reports_unexpected_keys_...)
    assert [k.removeprefix("aggregator.patch_embed.") for k in report.unexpected] == ["head.weight"]
    assert report.ignored == []
    own = model.encoder.state_dict()
    assert torch.equal(own["register_tokens"], sd["register_tokens"])
    assert torch.equal(own["mask_token"], sd["mask_token"])  # DINOv2's mask token loads too
    assert not model.encoder.mask_token.requires_grad  # ... and is never trained
    assert torch.equal(own["blocks.3.mlp.fc2.weight"], sd["blocks.3.mlp.fc2.weight"])
    assert own["pos_embed"].shape == (1, 1 + 16 * 16, DIM)
    assert torch.equal(own["pos_embed"][:, 0], sd["pos_embed"][:, 0])
    assert model.pretrained_backbone
    with torch.no_grad():
        assert torch.isfinite(model.encoder(torch.rand(1, 3, 28, 28))).all()


def test_an_encoder_checkpoint_reports_unexpected_keys_under_the_model_name(tmp_path):
    """Like its loaded and missing keys, and like a VGGT checkpoint's, a ViT/14 checkpoint's unexpected keys are
    named where they would sit in the model (``aggregator.patch_embed.``)."""
    sd = timm_state_dict(DIM, DEPTH, grid=16)
    sd["head.weight"] = torch.zeros(10, DIM)
    path = tmp_path / "with_head.pth"
    torch.save(sd, path)
    with pytest.warns(UserWarning, match="unexpected 1"):
        report = load_pretrained_weights(build_model("tiny"), path)
    assert report.missing == TIMM_MISSING
    assert report.unexpected == ["aggregator.patch_embed.head.weight"]


def test_load_timm_reg4_checkpoint_without_class_position(tmp_path):
    sd = timm_state_dict(DIM, DEPTH, grid=16, registers=4, cls_pos=False)
    path = tmp_path / "timm_reg4.pth"
    torch.save(sd, path)
    model = build_model("tiny", weights=str(path), encoder_registers=4)
    pos = model.encoder.state_dict()["pos_embed"]
    assert torch.equal(pos[:, 1:], sd["pos_embed"]) and pos[:, 0].eq(0).all()
    assert model.weights_report.missing == TIMM_MISSING and model.weights_report.unexpected == []
    assert torch.equal(model.encoder.state_dict()["register_tokens"], sd["reg_token"])  # timm's name, mapped


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


# Names of VGGT's camera and depth heads (facebookresearch/vggt, vggt/heads/camera_head.py and dpt_head.py),
# written out here so that a renamed module of ours fails the test rather than following the rename.
VGGT_HEAD_KEYS = [
    "camera_head.token_norm.weight",
    "camera_head.trunk.1.attn.qkv.weight",
    "camera_head.trunk.1.ls2.gamma",
    "camera_head.trunk_norm.bias",
    "camera_head.empty_pose_tokens",
    "camera_head.embed_pose.weight",
    "camera_head.poseLN_modulation.1.weight",
    "camera_head.pose_branch.fc1.weight",
    "camera_head.pose_branch.fc2.bias",
    "depth_head.norm.weight",
    "depth_head.projects.3.weight",
    "depth_head.resize_layers.0.weight",
    "depth_head.resize_layers.3.bias",
    "depth_head.scratch.layer4_rn.weight",
    "depth_head.scratch.refinenet1.resConfUnit1.conv2.weight",
    "depth_head.scratch.refinenet4.resConfUnit2.conv1.bias",
    "depth_head.scratch.refinenet2.out_conv.weight",
    "depth_head.scratch.output_conv1.weight",
    "depth_head.scratch.output_conv2.0.weight",
    "depth_head.scratch.output_conv2.2.bias",
]
VGGT_OTHER_HEADS = ["point_head.scratch.output_conv2.2.weight", "track_head.feature_extractor.norm.weight"]


def vggt_state_dict(dim: int, depth: int, registers: int, heads: bool = True) -> dict:
    """VGGT's layout: ``aggregator.patch_embed.`` (DINOv2 reg4), the frame / global blocks and the camera and
    register tokens, with ``heads`` its camera and depth heads (the tiny network's shapes) and the point and
    track heads this project does not have."""
    g = torch.Generator().manual_seed(2)

    def r(*shape):
        return torch.randn(*shape, generator=g)

    sd = {"aggregator.patch_embed." + k: v for k, v in to_dinov2(timm_state_dict(dim, depth, 37, 4)).items()}
    sd["aggregator.camera_token"] = r(1, 2, 1, dim)
    sd["aggregator.register_token"] = r(1, 2, registers, dim)
    for kind in ("frame_blocks", "global_blocks"):
        for i in range(depth):
            sd |= block_tensors(f"aggregator.{kind}.{i}.", dim, r, head_dim=dim // 3)
    if heads:
        shapes = build_model("tiny", encoder_registers=4, num_register_tokens=registers).state_dict()
        sd |= {k: r(*v.shape) for k, v in shapes.items() if k.startswith(("camera_head.", "depth_head."))}
        assert set(VGGT_HEAD_KEYS) <= set(sd), sorted(set(VGGT_HEAD_KEYS) - set(sd))
        sd |= {k: r(4, 4) for k in VGGT_OTHER_HEADS}
    return sd


def test_load_vggt_aggregator_and_heads(tmp_path):
    sd = vggt_state_dict(DIM, DEPTH, registers=4)
    path = tmp_path / "vggt.pt"
    torch.save(sd, path)
    model = build_model("tiny", weights=str(path), encoder_registers=4, num_register_tokens=4)
    report = model.weights_report
    assert report.format == "vggt" and report.missing == [] and report.unexpected == []
    assert sorted(report.ignored) == VGGT_OTHER_HEADS  # VGGT's point and track heads
    assert sorted(report.loaded) == sorted(set(sd) - set(VGGT_OTHER_HEADS))
    assert model.pretrained_backbone
    own = model.state_dict()
    resized = "aggregator.patch_embed.pos_embed"  # 37 x 37 positions, resized to the tiny encoder's 16 x 16
    assert own[resized].shape == (1, 1 + 16 * 16, DIM) and torch.equal(own[resized][:, 0], sd[resized][:, 0])
    for key in set(report.loaded) - {
        resized
    }:  # every tensor by its own name: aggregator, camera and depth heads
        assert torch.equal(own[key], sd[key]), key
    # the Gaussian head and the appearance (VGGT has neither) are new: neither loaded nor missing
    assert not any(k.startswith(("gaussian_head.", "appearance.")) for k in report.loaded + report.missing)
    agg = model.aggregator.state_dict()
    assert torch.equal(
        agg["global_blocks.3.attn.k_norm.weight"], sd["aggregator.global_blocks.3.attn.k_norm.weight"]
    )
    assert torch.equal(agg["register_token"], sd["aggregator.register_token"])
    assert torch.equal(model.encoder.mask_token, sd["aggregator.patch_embed.mask_token"])
    assert torch.equal(model.encoder.register_tokens, sd["aggregator.patch_embed.register_tokens"])
    with pytest.raises(ValueError, match="register-token"):
        build_model("tiny", weights=str(path), encoder_registers=4, num_register_tokens=2)


def test_a_vggt_checkpoint_without_heads_reports_them_missing(tmp_path):
    sd = vggt_state_dict(DIM, DEPTH, registers=4, heads=False)
    path = tmp_path / "vggt_aggregator.pt"
    torch.save(sd, path)
    with pytest.warns(UserWarning, match="missing"):
        model = build_model("tiny", weights=str(path), encoder_registers=4, num_register_tokens=4)
    report = model.weights_report
    heads = sorted(k for k in model.state_dict() if k.startswith(("camera_head.", "depth_head.")))
    assert report.missing == heads and report.unexpected == [] and report.ignored == []
    assert sorted(report.loaded) == sorted(sd)


def test_loaders_take_the_whole_model(tmp_path):
    """load_vggt_weights and load_pretrained_weights fill an AESplatModel: a VGGT checkpoint by name, a ViT/14
    into its patch encoder."""
    vggt, timm = tmp_path / "vggt.pt", tmp_path / "timm.pth"
    torch.save(vggt_state_dict(DIM, DEPTH, registers=4), vggt)
    torch.save(timm_state_dict(DIM, DEPTH, grid=16), timm)
    for load in (load_vggt_weights, load_pretrained_weights):
        model = build_model("tiny", encoder_registers=4, num_register_tokens=4)
        before = model.camera_head.embed_pose.weight.clone()
        report = load(model, vggt)
        assert report.format == "vggt" and report.missing == []
        assert not torch.equal(model.camera_head.embed_pose.weight, before)
        assert torch.equal(
            model.camera_head.embed_pose.weight, torch.load(vggt)["camera_head.embed_pose.weight"]
        )
    model = build_model("tiny")
    mask = model.encoder.mask_token.clone()
    report = load_pretrained_weights(model, timm)
    assert report.format == "timm" and report.missing == TIMM_MISSING
    assert torch.equal(model.encoder.mask_token, mask) and not model.encoder.mask_token.requires_grad
    assert torch.equal(model.encoder.patch_embed.proj.weight, torch.load(timm)["patch_embed.proj.weight"])
