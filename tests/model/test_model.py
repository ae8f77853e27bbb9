"""The assembled model: output container, masked attention, cameras at initialisation, ablations, groups."""


import pytest
import torch

from aesplat.errors import UserError
from aesplat.geometry import DEFAULT_FOV, focal_to_fov, num_sh_coeffs
from aesplat.model import APPEARANCE_MODES, ModelOutput, build_model, i2dc
from aesplat.types import Gaussians

H = W = 28


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return build_model("tiny", appearance="full", sh_degree=4)


@pytest.fixture(scope="module")
def moving_model(model):
    """The model with its camera head's output weights moved off their initialisation, where the poses are
    the identity for any images."""
    moved = build_model("tiny", appearance="full", sh_degree=4)
    moved.load_state_dict(model.state_dict())
    with torch.no_grad():
        moved.camera_head.pose_branch.fc2.weight.normal_(0.0, 0.05, generator=torch.Generator().manual_seed(1))
    return moved


def _images(b: int, v: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, v, 3, H, W, generator=g)


def _gaussian_fields(g: Gaussians) -> dict[str, torch.Tensor]:
    return {name: getattr(g, name) for name in ("means", "quats", "scales", "opacities", "sh")}


def test_output_container_shapes(model):
    ctx, tgt = _images(2, 2, 0), _images(2, 1, 1)
    with torch.no_grad():
        out = model(ctx, tgt)
    assert isinstance(out, ModelOutput)
    g = out.gaussians
    n = 2 * H * W
    assert isinstance(g, Gaussians) and g.num_gaussians == n
    assert g.sh.shape == (2, n, num_sh_coeffs(4), 3)
    assert out.extrinsics.shape == (2, 3, 4, 4) and out.intrinsics.shape == (2, 3, 3, 3)
    assert out.depth.shape == (2, 2, H, W)
    assert (g.scales > 0).all() and (g.scales <= model.cfg.scale_max).all()
    assert ((g.opacities > 0) & (g.opacities < 1)).all()
    torch.testing.assert_close(g.quats.norm(dim=-1), torch.ones(2, n))
    assert ((out.depth >= model.cfg.near) & (out.depth <= model.cfg.far)).all()
    with pytest.raises(AttributeError):
        out.depth = out.depth  # frozen


def test_target_images_never_change_the_gaussians(moving_model):
    model = moving_model
    ctx, tgt = _images(1, 2, 0), _images(1, 2, 1)
    with torch.no_grad():
        a = model(ctx, tgt)
        b = model(ctx, 1.0 - tgt)  # a very different target
    for name, value in _gaussian_fields(a.gaussians).items():
        assert torch.equal(value, getattr(b.gaussians, name)), name
    assert torch.equal(a.depth, b.depth)
    assert torch.equal(a.extrinsics[:, :2], b.extrinsics[:, :2])
    assert torch.equal(a.intrinsics[:, :2], b.intrinsics[:, :2])
    # ... while the target cameras do depend on the target images.
    assert not torch.equal(a.extrinsics[:, 2:], b.extrinsics[:, 2:])
    # Without targets, the Gaussians are the same (up to GEMM blocking on different batch shapes).
    with torch.no_grad():
        c = model(ctx)
    torch.testing.assert_close(c.gaussians.means, a.gaussians.means)
    assert c.extrinsics.shape == (1, 2, 4, 4)


def test_context_images_change_the_gaussians(moving_model):
    model = moving_model
    ctx, tgt = _images(1, 2, 0), _images(1, 1, 1)
    ctx2 = ctx.clone()
    ctx2[:, 1, :, :14, :14] = 1.0 - ctx2[:, 1, :, :14, :14]
    with torch.no_grad():
        a, b = model(ctx, tgt), model(ctx2, tgt)
    # view 0's Gaussians change too: global attention mixes the context views
    n0 = H * W
    assert not torch.equal(a.gaussians.means[:, :n0], b.gaussians.means[:, :n0])
    assert not torch.equal(a.gaussians.sh[:, n0:], b.gaussians.sh[:, n0:])
    assert not torch.equal(a.extrinsics[:, 1], b.extrinsics[:, 1])


def test_more_views_work_and_masking_still_holds():
    model = build_model("tiny", appearance="full", num_context_views=3)
    ctx, tgt = _images(1, 3, 0), _images(1, 2, 1)
    with torch.no_grad():
        a, b = model(ctx, tgt), model(ctx, tgt.flip(-1))
    assert a.gaussians.num_gaussians == 3 * H * W and a.extrinsics.shape == (1, 5, 4, 4)
    assert torch.equal(a.gaussians.sh, b.gaussians.sh) and torch.equal(a.gaussians.means, b.gaussians.means)


def test_view0_is_identity_and_initial_cameras(model):
    with torch.no_grad():
        out = model(_images(2, 2, 3), _images(2, 1, 4))
    assert torch.equal(out.extrinsics[:, 0], torch.eye(4).expand(2, 4, 4))
    assert torch.isfinite(out.extrinsics).all() and torch.isfinite(out.intrinsics).all()
    rot = out.extrinsics[..., :3, :3]
    torch.testing.assert_close(rot @ rot.transpose(-1, -2), torch.eye(3).expand_as(rot), atol=1e-5, rtol=0)
    k = out.intrinsics
    torch.testing.assert_close(focal_to_fov(k[..., 0, 0]), torch.full((2, 3), DEFAULT_FOV), atol=1e-6, rtol=0)
    torch.testing.assert_close(k[..., 0, 0], k[..., 1, 1])
    torch.testing.assert_close(k[..., :2, 2], torch.full((2, 3, 2), 0.5))
    # a new camera head starts at the identity rotation and zero translation (NAS3R's initialisation)
    torch.testing.assert_close(rot, torch.eye(3).expand_as(rot), atol=1e-6, rtol=0)
    assert out.extrinsics[..., :3, 3].abs().max() < 1e-6


def test_a_wide_input_gets_intrinsics_per_axis_with_square_pixels(model):
    ctx, tgt = torch.rand(1, 2, 3, H, 2 * W), torch.rand(1, 1, 3, H, 2 * W)  # 2:1
    with torch.no_grad():
        out = model(ctx, tgt)
    assert out.gaussians.num_gaussians == 2 * H * 2 * W and out.depth.shape == (1, 2, H, 2 * W)
    k = out.intrinsics
    torch.testing.assert_close(k[..., 0, 0], 0.5 * k[..., 1, 1])  # fx / fy = H / W: square pixels
    torch.testing.assert_close(focal_to_fov(k[..., 1, 1]), torch.full((1, 3), DEFAULT_FOV), atol=1e-6, rtol=0)


def test_dc_is_i2dc_of_the_context_pixels(model):
    ctx = _images(1, 2, 5)
    with torch.no_grad():
        out = model(ctx, _images(1, 1, 6))
    assert torch.equal(out.gaussians.sh[:, :, :1], i2dc(ctx))


# The tiny model at SH degree 3 (16 coefficients), two context views: mode -> (SH coefficients per Gaussian,
# SH coefficients taken from the Gaussian head, the view-dependent head's input width (Gaussian-head features 16
# + GVSRE 16 + colour and mask of the other view 4) or None, whether the DC coefficient is I2DC's). The head
# predicts all 16 in every mode (NAS3R's 8 + 3·K channels), so NAS3R's weights load into each.
ABLATIONS = {
    "full": (16, 0, 36, True),
    "no_gvsre": (16, 0, 20, True),
    "no_wcm": (16, 0, 32, True),
    "i2dc_only": (1, 0, None, True),
    "baseline": (16, 16, None, False),
    "baseline_i2dc": (16, 15, None, True),
}


def test_every_appearance_mode_is_tested():
    assert list(APPEARANCE_MODES) == list(ABLATIONS)


@pytest.mark.parametrize(("mode", "expected"), ABLATIONS.items())
def test_every_ablation_runs_forward_and_backward(mode, expected):
    k, head_sh, width, uses_i2dc = expected
    model = build_model("tiny", appearance=mode, sh_degree=3)
    ctx, tgt = _images(1, 2, 0), _images(1, 1, 1)
    out = model(ctx, tgt)
    assert out.gaussians.sh.shape == (1, 2 * H * W, k, 3) and model.sh_degree == (0 if k == 1 else 3)
    g = out.gaussians
    loss = g.sh.square().mean() + g.means.square().mean() + g.scales.sum() + g.opacities.mean()
    (loss + g.quats.sum() + out.extrinsics[:, 1:].square().sum() + out.intrinsics.sum()).backward()
    groups = model.named_parameter_groups()
    for name, p in model.named_parameters():
        assert (p.grad is not None and torch.isfinite(p.grad).all()) == p.requires_grad, name
    head = model.appearance.view_dependent_head
    assert (len(groups["appearance"]) > 0) == (width is not None) == (head is not None)
    if head is not None:
        assert all(p.grad.abs().sum() > 0 for _, p in groups["appearance"])
        assert head.net[0].normalized_shape == (width,)
    assert model.appearance.gaussian_head_sh == head_sh
    assert model.gaussian_head.scratch.output_conv2[-1].out_channels == 8 + 3 * 16
    assert torch.equal(g.sh[:, :, :1], i2dc(ctx)) == uses_i2dc


def test_i2dc_only_ignores_a_requested_degree():
    assert build_model("tiny", appearance="i2dc_only", sh_degree=4).sh_degree == 0


def test_parameter_groups_partition_the_trainable_parameters(model):
    groups = model.named_parameter_groups()
    assert set(groups) == {"appearance", "backbone", "rest"}
    names = [n for g in groups.values() for n, _ in g]
    assert len(names) == len(set(names))
    assert set(names) == {n for n, p in model.named_parameters() if p.requires_grad}
    app = {n for n, _ in groups["appearance"]}
    assert any(n.startswith("appearance.view_dependent_head.") for n in app)
    assert any(n.startswith("appearance.gvsre.") for n in app)
    assert groups["backbone"] and all(n.startswith("aggregator.patch_embed.") for n, _ in groups["backbone"])
    assert any(n.startswith("aggregator.global_blocks.") for n, _ in groups["rest"])
    assert any(n.startswith("camera_head.") for n, _ in groups["rest"])
    assert model.pretrained_backbone is False


def test_tiny_is_small():
    assert sum(p.numel() for p in build_model("tiny").parameters()) < 5_000_000


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"size": "huge"}, ValueError, "unknown model size"),
        ({"appearance": "nope"}, ValueError, "unknown appearance"),
        ({"depth_range": 3}, TypeError, "unknown option 'depth_range'"),
        ({"near": 2.0, "far": 1.0}, ValueError, "near < far"),
    ],
)
def test_build_model_rejects_bad_options(kwargs, error, match):
    with pytest.raises(error, match=match):
        build_model(**kwargs)


def test_build_model_options_reach_the_modules():
    m = build_model("tiny", near=0.5, far=20.0, rope=False, num_register_tokens=3, sh_degree=2)
    assert m.aggregator.rope is None and m.aggregator.register_token.shape[2] == 3
    assert m.aggregator.patch_start == 4
    with torch.no_grad():
        out = m(_images(1, 2, 0))
    assert out.gaussians.sh.shape[2] == 9


def test_depth_is_linear_in_the_sigmoid_between_near_and_far():
    """NAS3R's depth = near + (far - near)·sigmoid(raw): the same weights put a pixel at the same fraction of
    either range, and that fraction is the sigmoid of the depth head's first raw channel."""
    fractions, raws = [], []
    for near, far in ((0.5, 20.0), (1.0, 100.0)):
        torch.manual_seed(0)  # the same weights for both ranges
        m = build_model("tiny", near=near, far=far, rope=False, num_register_tokens=3, sh_degree=2)
        hook = m.depth_head.scratch.output_conv2.register_forward_hook(lambda mod, i, o: raws.append(o))
        with torch.no_grad():
            depth = m(_images(1, 2, 0)).depth
        hook.remove()
        fractions.append((depth - near) / (far - near))
    torch.testing.assert_close(fractions[0], fractions[1])
    torch.testing.assert_close(fractions[0], torch.sigmoid(raws[0][:, 0]).reshape_as(fractions[0]))
    assert fractions[0].std() > 1e-4  # the depth depends on the pixel


@pytest.mark.parametrize(
    ("ctx_shape", "tgt_shape", "match"),
    [
        ((1, 2, 3, 30, 28), None, "multiples of the patch size 14"),
        ((1, 1, 3, 28, 28), None, "at least 2 context views"),
        ((1, 2, 28, 28), None, r"\[B, Vc, 3, H, W\]"),
        ((1, 2, 3, 28, 28), (1, 1, 3, 42, 42), "target_images"),
    ],
)
def test_forward_rejects_bad_inputs(model, ctx_shape, tgt_shape, match):
    tgt = None if tgt_shape is None else torch.rand(tgt_shape)
    with pytest.raises(ValueError, match=match):
        model(torch.rand(ctx_shape), tgt)


def test_concat_head_refuses_another_count_in_one_line_naming_pool(model):
    with pytest.raises(UserError, match="model.net.view_aggregation: pool") as err:
        model(_images(1, 3, 0))
    assert "\n" not in str(err.value) and "built for 2 context views and got 3" in str(err.value)


def _all_finite(out: ModelOutput) -> bool:
    g = out.gaussians
    tensors = [g.means, g.quats, g.scales, g.opacities, g.sh, out.extrinsics, out.intrinsics, out.depth]
    return all(torch.isfinite(t).all() for t in tensors)


def _backward_is_finite(model, out: ModelOutput) -> bool:
    """Every parameter receives a gradient (this loss reaches them all), and every gradient is finite: a
    parameter the backward never reached is a failure, not a pass."""
    model.zero_grad(set_to_none=True)
    g = out.gaussians
    loss = g.sh.square().mean() + g.means.square().mean() + g.scales.sum() + out.extrinsics[:, 1:].sum()
    (loss + g.opacities.sum() + g.quats.sum()).backward()
    missing = [name for name, p in model.named_parameters() if p.requires_grad and p.grad is None]
    assert not missing, f"no gradient reached {missing[:5]}"
    return all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


@pytest.mark.parametrize("fill", [0.0, 1.0])
def test_constant_images_stay_finite(model, fill):
    images = torch.full((1, 3, 3, H, W), fill)
    out = model(images[:, :2], images[:, 2:])
    assert _all_finite(out) and _backward_is_finite(model, out)


@pytest.mark.parametrize("raw_depth", [-1e4, 1e4])
def test_extreme_depth_stays_finite(raw_depth):
    model = build_model("tiny")
    with torch.no_grad():
        model.depth_head.scratch.output_conv2[-1].bias[0].fill_(raw_depth)
    images = _images(1, 3, 0)
    out = model(images[:, :2], images[:, 2:])
    bound = model.cfg.near if raw_depth < 0 else model.cfg.far
    torch.testing.assert_close(out.depth, torch.full_like(out.depth, bound))
    assert _all_finite(out) and _backward_is_finite(model, out)


def test_bf16_autocast_runs_transformer_in_bf16_and_heads_in_fp32(model):
    images = _images(1, 3, 0)
    seen = {}

    def record(module, inputs, outputs):
        seen["dtype"] = outputs.dtype

    hook = model.aggregator.global_blocks[-1].attn.qkv.register_forward_hook(record)  # a transformer matmul
    try:
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out = model(images[:, :2], images[:, 2:])
    finally:
        hook.remove()
    assert seen["dtype"] == torch.bfloat16
    g = out.gaussians
    assert all(t.dtype == torch.float32 for t in (g.means, g.sh, g.scales, out.extrinsics, out.depth))
    assert _all_finite(out) and _backward_is_finite(model, out)


def test_gaussian_rotations_are_the_heads_in_view_0s_frame(model):
    """As NAS3R: each Gaussian's rotation is the Gaussian head's quaternion as it is, whatever its view's
    camera rotation (not composed with it)."""
    seen = []
    hook = model.gaussian_head.register_forward_hook(lambda mod, i, o: seen.append(o.quats))
    with torch.no_grad():
        out = model(_images(1, 2, 0), _images(1, 1, 1))
    hook.remove()
    assert torch.equal(out.gaussians.quats, seen[0].reshape(1, -1, 4))


def test_given_cameras_replace_the_camera_head(model):
    """Cameras passed in are used as they are; the camera head does not run and targets are not needed.
    Given the head's own prediction, the Gaussians are those of the plain forward pass."""
    ctx, tgt = _images(1, 2, 0), _images(1, 1, 1)
    calls = []
    handle = model.camera_head.register_forward_hook(lambda *args: calls.append(1))
    try:
        with torch.no_grad():
            own = model(ctx, tgt)
            assert calls == [1]
            given = model(ctx, extrinsics=own.extrinsics, intrinsics=own.intrinsics)
            ext = own.extrinsics.clone()
            ext[:, 1, :3, 3] += torch.tensor([0.5, 0.0, 0.0])  # move context camera 1
            moved = model(ctx, extrinsics=ext, intrinsics=own.intrinsics)
    finally:
        handle.remove()
    assert calls == [1]  # only the first call ran the camera head
    assert torch.equal(given.extrinsics, own.extrinsics) and torch.equal(given.intrinsics, own.intrinsics)
    assert given.extrinsics.shape == (1, 3, 4, 4)  # the target camera is passed through
    for name, value in _gaussian_fields(own.gaussians).items():
        torch.testing.assert_close(getattr(given.gaussians, name), value, msg=name)
    n = H * W  # view 1's centres follow its camera; view 0's do not move
    torch.testing.assert_close(
        moved.gaussians.means[:, n:], given.gaussians.means[:, n:] + torch.tensor([0.5, 0, 0])
    )
    torch.testing.assert_close(moved.gaussians.means[:, :n], given.gaussians.means[:, :n])


def test_given_cameras_with_targets_also_return_the_heads_prediction(model):
    """The posed warm start: the given cameras make the Gaussians; the head's cameras (the same as a plain
    pose-free pass) come back to be supervised. Targets never change the Gaussians (attention masking)."""
    ctx, tgt = _images(1, 2, 0), _images(1, 1, 1)
    with torch.no_grad():
        own = model(ctx, tgt)
        ext = own.extrinsics.clone()
        ext[:, 1, :3, 3] += torch.tensor([0.5, 0.0, 0.0])
        both = model(ctx, tgt, extrinsics=ext, intrinsics=own.intrinsics)
        given = model(ctx, extrinsics=ext, intrinsics=own.intrinsics)
    assert given.predicted_cameras is None and own.predicted_cameras is None
    pred_e, pred_k = both.predicted_cameras
    torch.testing.assert_close(pred_e, own.extrinsics)
    torch.testing.assert_close(pred_k, own.intrinsics)
    assert torch.equal(both.extrinsics, ext)
    for name, value in _gaussian_fields(given.gaussians).items():
        torch.testing.assert_close(getattr(both.gaussians, name), value, msg=name)
    with pytest.raises(ValueError, match="give cameras for all 3 views"):
        model(ctx, tgt, extrinsics=ext[:, :2], intrinsics=own.intrinsics[:, :2])


@pytest.mark.parametrize(
    ("ext_shape", "intr_shape", "match"),
    [((1, 2, 4, 4), None, "both extrinsics and intrinsics"), ((1, 1, 4, 4), (1, 1, 3, 3), "V >= 2"),
     ((1, 3, 4, 4), (1, 2, 3, 3), "given cameras"), ((2, 2, 4, 4), (2, 2, 3, 3), "B = 1")],
)  # fmt: skip
def test_given_cameras_are_checked(model, ext_shape, intr_shape, match):
    intrinsics = None if intr_shape is None else torch.eye(3).expand(intr_shape)
    with pytest.raises(ValueError, match=match):
        model(_images(1, 2, 0), extrinsics=torch.eye(4).expand(ext_shape), intrinsics=intrinsics)


def test_bf16_head_precision_runs_dpt_trunks_in_bf16_and_the_rest_in_fp32(model):
    bf16 = build_model("tiny", appearance="full", sh_degree=4, head_precision="bf16")
    bf16.load_state_dict(model.state_dict())
    seen = {}
    trunk_conv, out_conv = bf16.depth_head.scratch.refinenet1.out_conv, bf16.depth_head.scratch.output_conv2
    hooks = [
        trunk_conv.register_forward_hook(lambda m, i, o: seen.update(trunk=o.dtype)),
        out_conv.register_forward_hook(lambda m, i, o: seen.update(out=o.dtype)),
    ]
    images = _images(1, 2, 3)
    try:
        with torch.no_grad():
            got, want = bf16(images), model(images)
    finally:
        for hook in hooks:
            hook.remove()
    assert seen == {"trunk": torch.bfloat16, "out": torch.float32}
    assert got.depth.dtype == torch.float32 and not torch.equal(got.depth, want.depth)
    torch.testing.assert_close(got.depth, want.depth, rtol=1e-2, atol=0)
    torch.testing.assert_close(got.gaussians.means, want.gaussians.means, rtol=1e-2, atol=1e-3)
    with pytest.raises(ValueError, match="head precision"):
        build_model("tiny", head_precision="fp16")


def test_a_smaller_patch_gives_more_tokens_per_view():
    torch.manual_seed(0)
    m = build_model("tiny", sh_degree=1, patch_size=7)
    assert m.encoder.patch_embed.proj.kernel_size == (7, 7)
    images = torch.rand(1, 2, 3, 42, 42)
    assert m.encoder(images[:, 0]).shape[1] == 36  # 6x6 tokens where patch 14 gives 3x3
    assert build_model("tiny", sh_degree=1).encoder(images[:, 0]).shape[1] == 9
    with torch.no_grad():
        out = m(images, torch.rand(1, 1, 3, 42, 42))
    assert out.depth.shape == (1, 2, 42, 42) and out.gaussians.means.shape == (1, 2 * 42 * 42, 3)
    with pytest.raises(ValueError, match="multiples of the patch size 7"):
        m(torch.rand(1, 2, 3, 45, 42))


def test_pixel_offset_puts_each_gaussian_on_the_ray_through_that_place_in_its_pixel():
    """0.0 (NAS3R's): the ray through the pixel's top-left corner; 0.5: through its centre, where the renderer
    samples the pixel. The depth, cameras and everything else are the same."""
    from aesplat.geometry import unproject_depth

    outs = {}
    for offset in (0.0, 0.5):
        torch.manual_seed(0)
        m = build_model("tiny", sh_degree=1, pixel_offset=offset)
        with torch.no_grad():
            outs[offset] = m(_images(1, 2, 0))
    a, b = outs[0.0], outs[0.5]
    assert torch.equal(a.depth, b.depth) and torch.equal(a.extrinsics, b.extrinsics)
    for offset, out in outs.items():
        rays = unproject_depth(out.depth, out.intrinsics, out.extrinsics, offset=offset).reshape(1, -1, 3)
        torch.testing.assert_close(out.gaussians.means, rays)
    assert not torch.allclose(a.gaussians.means, b.gaussians.means)
