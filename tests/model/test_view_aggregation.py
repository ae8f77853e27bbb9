"""The ``pool`` view aggregation: one appearance head for any number of context views, blind to the order of
the non-reference views and to views that do not see a Gaussian; ``concat`` (the paper's) keeps its count."""

import warnings

import pytest
import torch

from aesplat.errors import UserError
from aesplat.geometry import make_pose, quat_to_matrix
from aesplat.model import (
    ConcatAppearance,
    NetConfig,
    PooledAppearance,
    build_appearance,
    build_model,
    masked_mean,
)
from aesplat.render import render

H = W = 28


def _images(v: int, seed: int, b: int = 1) -> torch.Tensor:
    return torch.rand(b, v, 3, H, W, generator=torch.Generator().manual_seed(seed))


def _pool_model(seed: int = 0, **kwargs):
    torch.manual_seed(seed)
    model = build_model("tiny", appearance="full", sh_degree=2, view_aggregation="pool", **kwargs).eval()
    with torch.no_grad():  # trained heads' outputs are not ~constant:
        model.appearance.view_dependent_head.net[-1].weight.normal_(std=0.3)  # higher orders matter in renders
        # depths spread over the range (a new head's lie within 47 ± 0.3: float32 ties between views, whose
        # sort order a permutation changes)
        model.depth_head.scratch.output_conv2[-1].weight.normal_(std=10.0)
    return model


def _permuted(x: torch.Tensor, order: list[int]) -> torch.Tensor:
    """Gaussians [B, V·P, ...] in (view, pixel) order, the view blocks re-ordered."""
    v = len(order)
    return x.unflatten(1, (v, -1))[:, order].flatten(1, 2)


def test_masked_mean_ignores_what_the_mask_leaves_out():
    x = torch.tensor([[1.0, 2.0], [3.0, 4.0], [float("nan"), float("inf")]])  # [V = 3, D = 2]
    mask = torch.tensor([1.0, 1.0, 0.0])
    torch.testing.assert_close(masked_mean(x, mask), torch.tensor([2.0, 3.0]))
    torch.testing.assert_close(masked_mean(x, torch.zeros(3)), torch.zeros(2))  # none valid: zero, not NaN


def test_pool_takes_any_count_with_one_set_of_weights():
    model = _pool_model()
    counts = {p.numel() for p in model.appearance.parameters()}
    for v in (2, 3, 5):
        with torch.no_grad():
            out = model(_images(v, v), _images(1, 9))
        assert out.gaussians.num_gaussians == v * H * W and out.extrinsics.shape == (1, v + 1, 4, 4)
        assert torch.isfinite(out.gaussians.sh).all()
    assert {p.numel() for p in model.appearance.parameters()} == counts


def test_permuting_the_other_context_views_permutes_the_gaussians_and_not_the_renders():
    model = _pool_model()
    ctx, tgt = _images(4, 0), _images(2, 1)
    order = [0, 2, 3, 1]  # view 0 is the reference frame and stays first
    with torch.no_grad():
        a, b = model(ctx, tgt), model(ctx[:, order], tgt)
    for name in ("means", "quats", "scales", "opacities", "sh"):
        got, want = getattr(b.gaussians, name), _permuted(getattr(a.gaussians, name), order)
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5, msg=name)
    torch.testing.assert_close(b.extrinsics[:, 4:], a.extrinsics[:, 4:], rtol=1e-4, atol=1e-5)  # targets
    assert a.gaussians.sh[..., 1:, :].abs().mean() > 1e-2  # the view-dependent part is not negligible

    def targets(out):
        return render(out.gaussians, out.extrinsics[:, 4:], out.intrinsics[:, 4:], H, W, backend="torch")

    ra, rb = targets(a), targets(b)
    assert ra.alpha.mean() > 0.3  # the targets see the Gaussians: the comparison is not background only
    torch.testing.assert_close(rb.color, ra.color, rtol=1e-4, atol=1e-4)

    # The paper's head reads the views in order: the same permutation changes its Gaussians' colours.
    torch.manual_seed(0)
    concat = build_model("tiny", sh_degree=2, num_context_views=4).eval()
    with torch.no_grad():
        concat.appearance.view_dependent_head.net[-1].weight.normal_(std=0.3)
        c, d = concat(ctx, tgt), concat(ctx[:, order], tgt)
    assert (d.gaussians.sh - _permuted(c.gaussians.sh, order)).abs().max() > 1e-3


def _three_cameras_one_looking_away() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Means [1, 3, P, 3] in front of cameras 0 and 1 (seen by both); camera 2 turned round (sees none of
    views 0's and 1's Gaussians). Returns means, intrinsics [1, 3, 3, 3], extrinsics [1, 3, 4, 4]."""
    p = 16
    gen = torch.Generator().manual_seed(4)
    means = (torch.rand(1, 3, p, 3, generator=gen) - 0.5) * torch.tensor([0.8, 0.8, 0.5])
    means[..., 2] += 4.0
    turned = quat_to_matrix(torch.tensor([0.0, 0.0, 1.0, 0.0]))  # 180 degrees about y: looks down -z
    extrinsics = torch.stack([torch.eye(4), make_pose(torch.eye(3), torch.tensor([0.2, 0.0, 0.0])),
                              make_pose(turned, torch.tensor([0.0, 0.3, 0.5]))])[None]  # fmt: skip
    means[:, 2] = means[:, 2] * torch.tensor([1.0, 1.0, -1.0]) + torch.tensor([0.0, 0.3, 0.5])  # before cam 2
    k = torch.tensor([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]]).expand(1, 3, 3, 3)
    return means, k, extrinsics


def test_a_view_that_does_not_see_a_gaussian_has_no_influence_on_its_colour_embedding():
    means, k, extrinsics = _three_cameras_one_looking_away()
    torch.manual_seed(0)
    app = PooledAppearance("full", 2, feature_dim=4, gvsre_dim=8, hidden=16)
    images = torch.rand(1, 3, 3, 4, 4, generator=torch.Generator().manual_seed(5))
    dim, p = 8, means.shape[2]
    with torch.no_grad():
        three = app.view_inputs(images, means, k, extrinsics)  # [1, 3·P, 8 + 8 + 1]
        other_image = images.clone()
        other_image[:, 2] = 1.0 - other_image[:, 2]
        changed = app.view_inputs(other_image, means, k, extrinsics)
        two = app.view_inputs(images[:, :2], means[:, :2], k[:, :2], extrinsics[:, :2])
    # Views 0's and 1's Gaussians: camera 2's image changes nothing, and their colour embedding is the one
    # they get without camera 2 at all (only GVSRE, the relation to every camera centre, sees camera 2).
    torch.testing.assert_close(changed[:, : 2 * p], three[:, : 2 * p], rtol=0, atol=0)
    torch.testing.assert_close(three[:, : 2 * p, dim:], two[:, :, dim:], rtol=1e-6, atol=1e-6)
    assert (three[:, : 2 * p, :dim] - two[:, :, :dim]).abs().max() > 1e-3
    assert torch.equal(three[:, : 2 * p, -1], torch.ones(1, 2 * p))  # each is seen by the other view
    # ... whereas camera 2's image does reach the Gaussians that camera 2 sees: none here (camera 2's own
    # Gaussians are behind cameras 0 and 1), so they are "unseen" with a zero colour embedding.
    torch.testing.assert_close(three[:, 2 * p :, dim:], torch.zeros(1, p, dim + 1))


@pytest.mark.parametrize("views", [2, 5])
def test_every_pool_appearance_parameter_gets_a_finite_nonzero_gradient(views):
    model = _pool_model()
    model.train()
    out = model(_images(views, 3), _images(1, 4))
    g = out.gaussians
    r = render(g, out.extrinsics[:, views:], out.intrinsics[:, views:], H, W, backend="torch")
    (r.color.square().mean() + g.sh[..., 1:, :].square().mean()).backward()
    params = dict(model.named_parameter_groups()["appearance"])
    assert {n.split(".")[1] for n in params} == {"gvsre", "wcm", "view_dependent_head"}
    for name, param in params.items():
        assert param.grad is not None, name
        assert torch.isfinite(param.grad).all() and param.grad.abs().sum() > 0, name


@pytest.mark.parametrize("case", ["black", "white", "at_camera_centre", "seen_by_no_other_view"])
def test_pool_hard_cases_stay_finite_with_finite_gradients(case):
    means, k, extrinsics = _three_cameras_one_looking_away()
    images = torch.rand(1, 3, 3, 4, 4, generator=torch.Generator().manual_seed(6))
    if case in ("black", "white"):
        images = torch.full_like(images, 0.0 if case == "black" else 1.0)
    elif case == "at_camera_centre":
        means[:, 0, :4] = extrinsics[:, 1, :3, 3]  # on camera 1's centre: distance clamped in GVSRE
        means[:, 1, :4] = 0.0  # on camera 0's
    else:  # no Gaussian inside another camera's image: no warped colour at all
        means[:, :2, :, 0] += 100.0
    means.requires_grad_(True)
    extrinsics = extrinsics.clone().requires_grad_(True)
    images = images.clone().requires_grad_(True)
    torch.manual_seed(0)
    app = PooledAppearance("full", 2, feature_dim=4, gvsre_dim=8, hidden=16)
    sh = app(images, means, torch.randn(1, 3, 16, 4), None, k, extrinsics)
    assert torch.isfinite(sh).all()
    sh[..., 1:, :].square().sum().backward()
    for name, t in [("means", means), ("extrinsics", extrinsics), ("images", images),
                    *app.named_parameters()]:  # fmt: skip
        assert t.grad is not None and torch.isfinite(t.grad).all(), name
    assert app.gvsre.mlp[0].weight.grad.abs().sum() > 0
    if case == "seen_by_no_other_view":
        assert app.wcm.mlp[0].weight.grad.abs().sum() == 0  # no view takes part in the colour embedding


def test_concat_refusal_is_one_line_before_anything_runs():
    app = build_appearance("concat", "full", 2, feature_dim=4, num_context_views=2)
    with pytest.raises(UserError, match=r"built for 2 context views and got 3.*view_aggregation: pool"):
        app.check_context_views(3)
    for mode in ("i2dc_only", "baseline"):  # no view-dependent head: any count is fine
        build_appearance("concat", mode, 2, feature_dim=4).check_context_views(5)
    with pytest.raises(ValueError, match="unknown view aggregation 'mean'"):
        build_appearance("mean", "full", 2, feature_dim=4)
    with pytest.raises(ValueError, match="model.net.view_aggregation"):
        NetConfig(view_aggregation="mean")


def test_a_concat_checkpoint_warm_starts_a_pool_model_except_its_appearance_head(tmp_path):
    torch.manual_seed(0)
    concat = build_model("tiny", sh_degree=2)
    path = tmp_path / "concat.ckpt"
    state = {f"model.{k}": v for k, v in concat.state_dict().items()}
    torch.save({"state_dict": state, "hyper_parameters": {"net": {"size": "tiny", "sh_degree": 2}}}, path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pool = build_model("tiny", sh_degree=2, view_aggregation="pool", weights=str(path))
    assert any("view_aggregation concat" in str(w.message) for w in caught)
    report = pool.weights_report
    assert report.loaded and all(not k.startswith("appearance.") for k in report.loaded)
    assert set(report.missing) == {k for k in pool.state_dict() if k.startswith("appearance.")}
    for name, value in pool.state_dict().items():
        if not name.startswith("appearance."):
            assert torch.equal(value, concat.state_dict()[name]), name


def test_a_model_net_section_saved_before_view_aggregation_builds_the_papers_head():
    """A run's ``model.net`` section from before the view aggregation was selectable (as ``aesplat fit`` stored
    it then) builds the paper's head, for the two context views it was built for."""
    net = {"size": "tiny", "appearance": "full", "sh_degree": 2, "near": 0.1, "far": 20.0, "weights": None,
           "options": {}, "compile": "none"}  # fmt: skip
    model = NetConfig(**net).build()
    assert isinstance(model.appearance, ConcatAppearance) and model.appearance.num_context_views == 2
    with pytest.raises(UserError, match="built for 2 context views"):
        model.check_context_views(3)
