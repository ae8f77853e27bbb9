"""I2DC, GVSRE and the warped colour map against hand-computed values; the view-dependent head's layout."""

import math

import pytest
import torch
from torch import nn

from aesplat.geometry import C0, make_pose, num_sh_coeffs, quat_to_matrix, sh_dc_to_rgb
from aesplat.model import (
    APPEARANCE_MODES,
    ConcatAppearance,
    ViewDependentHead,
    build_appearance,
    gvsre_descriptor,
    i2dc,
    warped_color_map,
)


def _pose(tx: float = 0.0, ty: float = 0.0, tz: float = 0.0) -> torch.Tensor:
    """Camera-to-world with identity rotation and the given centre."""
    pose = torch.eye(4)
    pose[:3, 3] = torch.tensor([tx, ty, tz])
    return pose


def _unit_intrinsics(v: int) -> torch.Tensor:
    k = torch.tensor([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    return k.expand(1, v, 3, 3).clone()


def test_i2dc_is_exact_and_in_view_row_column_order():
    images = torch.rand(2, 3, 3, 5, 7)
    dc = i2dc(images)
    assert dc.shape == (2, 3 * 5 * 7, 1, 3)
    # Gaussian index = (view * H + row) * W + column
    v, r, c = 2, 4, 6
    assert torch.equal(dc[1, (v * 5 + r) * 7 + c, 0], (images[1, v, :, r, c] - 0.5) / C0)
    torch.testing.assert_close(
        sh_dc_to_rgb(dc[..., 0, :]).reshape(2, 3, 5, 7, 3), images.permute(0, 1, 3, 4, 2)
    )


def test_gvsre_descriptor_hand_computed():
    centres = torch.stack([_pose()[:3, 3], _pose(1.0)[:3, 3]])[None]  # cameras at the origin and at x = 1
    means = torch.tensor([[[0.0, 0.0, 2.0], [1.0, 0.0, 0.0]]], requires_grad=True)  # second one at camera 1
    desc = gvsre_descriptor(means, centres, min_distance=1e-4)
    s5 = math.sqrt(5.0)
    expected = torch.tensor(
        [
            [0.0, 0.0, -1.0, math.log(2.0), 1 / s5, 0.0, -2 / s5, math.log(s5)],
            [-1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, math.log(1e-4)],
        ]
    )
    torch.testing.assert_close(desc[0], expected)
    desc.sum().backward()
    assert torch.isfinite(means.grad).all()


def _linear_image(offset: float, h: int = 4, w: int = 4) -> torch.Tensor:
    """[3, H, W] with value offset + 100 c + 10 row + column at each pixel."""
    rows = torch.arange(h, dtype=torch.float32)[:, None]
    cols = torch.arange(w, dtype=torch.float32)[None]
    return torch.stack([offset + 100 * c + 10 * rows + cols for c in range(3)])


def test_warped_color_map_two_cameras_hand_computed():
    # Camera 0 at the origin, camera 1 at x = 1, both looking down +z; 4x4 images, focal 1 (normalised).
    extrinsics = torch.stack([_pose(), _pose(1.0)])[None]
    intrinsics = _unit_intrinsics(2)
    images = torch.stack([_linear_image(1000.0), _linear_image(0.0)])[None]  # [1, 2, 3, 4, 4]
    # Points of view 0, projected into camera 1 (pixel uv = (x / z + 0.5) * 4 in camera 1's frame):
    points_v0 = [
        (1.0, 0.0, 2.0),  # uv (2, 2): the corner between 4 pixels -> their mean
        (1.25, -0.25, 2.0),  # uv (2.5, 1.5): centre of pixel row 1, column 2
        (0.875, 0.25, 2.0),  # uv (1.75, 2.5): a quarter of the way between columns 1 and 2, row 2
        (0.125, 0.25, 2.0),  # uv (0.25, 2.5): inside the image, left of the first pixel centre -> column 0
        (3.0, 0.0, 2.0),  # uv (6, 2): outside the image
        (1.0, 0.0, -2.0),  # behind camera 1
        (1.0, 0.0, 0.0),  # at camera 1's centre
    ]
    points_v1 = [(0.0, 0.0, 2.0)] * len(points_v0)  # uv (2, 2) in camera 0
    means = torch.tensor([points_v0, points_v1])[None].requires_grad_(True)  # [1, 2, 7, 3]
    colors, mask = warped_color_map(means, images, intrinsics, extrinsics)
    assert colors.shape == (1, 2, 7, 1, 3) and mask.shape == (1, 2, 7, 1)

    channel = torch.tensor([0.0, 100.0, 200.0])
    expected_v0 = torch.stack(
        [
            channel + 16.5,  # mean of (row, col) in {1, 2}^2: 10 * 1.5 + 1.5
            channel + 12.0,
            channel + 21.25,  # 10 * 2 + 1.25
            channel + 20.0,  # border: column 0 of row 2
            torch.zeros(3),
            torch.zeros(3),
            torch.zeros(3),
        ]
    )
    torch.testing.assert_close(colors[0, 0, :, 0], expected_v0)
    torch.testing.assert_close(mask[0, 0, :, 0], torch.tensor([1.0, 1, 1, 1, 0, 0, 0]))
    torch.testing.assert_close(colors[0, 1, :, 0], (channel + 1016.5).expand(7, 3))
    assert mask[0, 1].eq(1).all()

    (colors.sum() + mask.sum()).backward()
    assert torch.isfinite(means.grad).all()


def test_warped_color_map_orders_the_other_views():
    # Three cameras side by side; image q is constant q + 1; every point is visible in every camera.
    extrinsics = torch.stack([_pose(), _pose(0.1), _pose(0.2)])[None]
    images = torch.stack([torch.full((3, 4, 4), q + 1.0) for q in range(3)])[None]
    means = torch.tensor([0.1, 0.0, 5.0]).expand(1, 3, 2, 3)
    colors, mask = warped_color_map(means, images, _unit_intrinsics(3), extrinsics)
    assert colors.shape == (1, 3, 2, 2, 3)
    assert mask.eq(1).all()
    others = {0: [2.0, 3.0], 1: [1.0, 3.0], 2: [1.0, 2.0]}
    for p, values in others.items():
        torch.testing.assert_close(colors[0, p, :, :, 0], torch.tensor(values).expand(2, 2))


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
def test_view_dependent_head_architecture(degree):
    head = ViewDependentHead(in_dim=20, hidden=16, sh_degree=degree)
    layers = list(head.net)
    assert isinstance(layers[0], nn.LayerNorm) and layers[0].normalized_shape == (20,)
    linears = [m for m in head.modules() if isinstance(m, nn.Linear)]
    gelus = [m for m in head.modules() if isinstance(m, nn.GELU)]
    assert len(linears) == 4 and len(gelus) == 3
    assert [type(m) for m in layers[1:]] == [nn.Linear, nn.GELU] * 3 + [nn.Linear]  # linear output layer
    assert linears[-1].out_features == (num_sh_coeffs(degree) - 1) * 3
    assert head(torch.randn(5, 20)).shape == (5, num_sh_coeffs(degree) - 1, 3)


def test_view_dependent_head_needs_higher_orders():
    with pytest.raises(ValueError, match="sh_degree >= 1"):
        ViewDependentHead(8, 8, sh_degree=0)


@pytest.mark.parametrize("aggregation", ["concat", "pool"])
@pytest.mark.parametrize("mode", APPEARANCE_MODES)
def test_appearance_mode_inputs_and_outputs(mode, aggregation):
    feature_dim, gvsre_dim, views, degree = 12, 6, 3, 2
    app = build_appearance(aggregation, mode, degree, feature_dim, num_context_views=views, gvsre_dim=gvsre_dim,
                           hidden=8)  # fmt: skip
    head = app.view_dependent_head
    if aggregation == "concat":  # GVSRE of all cameras, colour + mask of each other view, in view order
        expected_in = {"full": gvsre_dim + 4 * (views - 1), "no_gvsre": 4 * (views - 1), "no_wcm": gvsre_dim}
        gvsre_in = 4 * views
    else:  # one GVSRE embedding; one colour embedding + whether any other view sees the Gaussian
        expected_in = {"full": 2 * gvsre_dim + 1, "no_gvsre": gvsre_dim + 1, "no_wcm": gvsre_dim}
        gvsre_in = 5  # direction, log distance, own view
        wcm = getattr(app, "wcm", None)
        assert (wcm is not None) == (mode in ("full", "no_gvsre"))
        if wcm is not None:  # warped colour, own colour (and with GVSRE the view's relation)
            assert wcm.mlp[0].in_features == (10 if mode == "full" else 6)
    if mode in expected_in:
        assert head.net[0].normalized_shape == (feature_dim + expected_in[mode],)
    else:
        assert head is None
    assert (app.gvsre is not None) == (mode in ("full", "no_wcm"))
    if app.gvsre is not None:
        assert app.gvsre.mlp[0].in_features == gvsre_in
    k = num_sh_coeffs(app.sh_degree)
    sh_degree, head_sh = {"i2dc_only": (0, 0), "baseline": (2, 9), "baseline_i2dc": (2, 8)}.get(mode, (2, 0))
    assert (app.sh_degree, app.gaussian_head_sh) == (sh_degree, head_sh)
    assert (sum(p.numel() for p in app.parameters()) == 0) == (head is None)

    b, p, h, w = 1, 16, 4, 4
    images = torch.rand(b, views, 3, h, w)
    means = torch.randn(b, views, p, 3) + torch.tensor([0.0, 0.0, 4.0])
    extrinsics = torch.stack([_pose(0.2 * i) for i in range(views)])[None]
    features = torch.randn(b, views, p, feature_dim)
    # the Gaussian head always predicts SH of the model's degree (here 2: 9 coefficients)
    head_sh = torch.randn(b, views, p, num_sh_coeffs(degree), 3)
    sh = app(images, means, features, head_sh, _unit_intrinsics(views), extrinsics)
    assert sh.shape == (b, views * p, k, 3)
    flat_head_sh = head_sh.reshape(b, views * p, -1, 3)
    if mode == "baseline":  # every coefficient the head's, as it gives them
        assert torch.equal(sh, flat_head_sh)
    else:
        assert torch.equal(sh[:, :, :1], i2dc(images))
    if mode == "baseline_i2dc":  # the head's degree >= 1 coefficients, as it gives them
        assert torch.equal(sh[:, :, 1:], flat_head_sh[:, :, 1:])
    # the modes that do not take the Gaussian head's SH ignore them
    other = app(images, means, features, torch.randn_like(head_sh), _unit_intrinsics(views), extrinsics)
    assert torch.equal(other, sh) == (app.gaussian_head_sh == 0)


def _turned_camera(dtype=torch.float64) -> torch.Tensor:
    """Camera-to-view-0 pose [4, 4] of a second camera turned by about 50 degrees and shifted."""
    rot = quat_to_matrix(torch.tensor([0.9, 0.25, -0.3, 0.2], dtype=dtype))
    return make_pose(rot, torch.tensor([0.6, -0.2, 0.3], dtype=dtype))


@pytest.mark.parametrize("mode", ["baseline", "baseline_i2dc"])
def test_baseline_sh_are_taken_as_the_head_gives_them_whatever_the_cameras(mode):
    """NAS3R takes the Gaussian head's SH of every view in view 0's frame as they are: a turned camera does not
    rotate them (they are not turned from camera v's frame into view 0's), and nothing else about the cameras
    changes them."""
    degree, p, dtype = 3, 6, torch.float64
    app = ConcatAppearance(mode, degree, feature_dim=4)
    k, s = num_sh_coeffs(degree), app.gaussian_head_sh
    turned = torch.stack([torch.eye(4, dtype=dtype), _turned_camera()])[None]  # [1, 2, 4, 4]
    assert (turned[0, 1, :3, :3] - torch.eye(3, dtype=dtype)).abs().max() > 0.5  # a real turn
    images = torch.rand(1, 2, 3, 2, 3, dtype=dtype)  # P = 6 pixels per view
    means = torch.randn(1, 2, p, 3, dtype=dtype) + torch.tensor([0.0, 0.0, 4.0], dtype=dtype)
    head_sh = torch.randn(1, 2, p, k, 3, dtype=dtype)
    k_unit = _unit_intrinsics(2).to(dtype)
    sh = app(images, means, torch.zeros(1, 2, p, 4, dtype=dtype), head_sh, k_unit, turned).reshape(
        1, 2, p, k, 3
    )
    assert torch.equal(sh[..., k - s :, :], head_sh[..., k - s :, :])  # view 1's too, not rotated
    if mode == "baseline_i2dc":
        assert torch.equal(sh[..., :1, :].reshape(1, 2 * p, 1, 3), i2dc(images))
    # another pose of view 1 (and of view 0) gives the same SH
    moved = torch.stack([_turned_camera(), torch.eye(4, dtype=dtype)])[None]
    again = app(images, means, torch.zeros(1, 2, p, 4, dtype=dtype), head_sh, k_unit, moved)
    assert torch.equal(again.reshape(1, 2, p, k, 3), sh)
