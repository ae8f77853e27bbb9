"""LPIPS loading from the local torch hub cache (never downloaded) and the photometric loss."""

import math

import pytest
import torch

from aesplat.train.loss import (
    VGG16_FILE,
    LossConfig,
    LpipsWeightsMissing,
    PhotometricLoss,
    camera_loss,
    gaussian_blur,
    load_lpips_network,
    maybe_lpips,
    vgg16_weights_path,
)


@pytest.fixture
def empty_torch_home(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    return tmp_path / "torch_home"


@pytest.fixture
def fake_vgg_weights(empty_torch_home):
    """A VGG16 feature checkpoint with torchvision's key layout (random values) where torchvision keeps it."""
    # LPIPS itself is built on torchvision; the older-torch test leg has no torchvision build to match.
    torchvision = pytest.importorskip("torchvision")
    features = torchvision.models.vgg.make_layers(torchvision.models.vgg.cfgs["D"])
    path = empty_torch_home / "hub" / "checkpoints" / VGG16_FILE
    path.parent.mkdir(parents=True)
    torch.save({f"features.{k}": v for k, v in features.state_dict().items()}, path)
    return path, features


def test_missing_weights_error_names_file_directory_and_opt_out(empty_torch_home, monkeypatch):
    calls = []
    monkeypatch.setattr(torch.hub, "download_url_to_file", lambda *a, **k: calls.append(a))
    with pytest.raises(LpipsWeightsMissing) as info:
        load_lpips_network()
    message = str(info.value)
    expected = empty_torch_home / "hub" / "checkpoints" / VGG16_FILE
    assert vgg16_weights_path() == expected
    assert str(expected) in message and str(expected.parent) in message
    assert "lpips_weight 0" in message
    assert not calls, "nothing may be downloaded"


def test_optional_lpips_reports_unavailable(empty_torch_home):
    lpips, reason = maybe_lpips(required=False)
    assert lpips is None and VGG16_FILE in reason
    with pytest.raises(LpipsWeightsMissing):
        maybe_lpips(required=True)


def test_lpips_loads_local_weights_frozen_and_outside_the_module_tree(fake_vgg_weights):
    path, features = fake_vgg_weights
    lpips, reason = maybe_lpips(required=True)
    assert reason is None
    net = lpips._net
    assert torch.equal(getattr(net.net.slice1, "0").weight, features[0].weight)
    assert torch.equal(getattr(net.net.slice5, "28").weight, features[28].weight)
    assert not any(p.requires_grad for p in net.parameters())

    loss = PhotometricLoss(LossConfig(mse_weight=1.0, lpips_weight=0.05), lpips)
    assert list(loss.parameters()) == [] and loss.state_dict() == {}, "LPIPS must never be saved or trained"
    target = torch.rand(1, 2, 3, 32, 32)
    same = loss(target, target)
    pred = (target + 0.2 * torch.randn_like(target)).clamp(0, 1).requires_grad_()
    diff = loss(pred, target)
    assert same["lpips"].item() == pytest.approx(0.0, abs=1e-6)
    assert diff["lpips"].item() > 0
    assert diff["total"].item() == pytest.approx(diff["mse"].item() + 0.05 * diff["lpips"].item(), rel=1e-5)
    diff["total"].backward()
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0


def test_mse_only_loss():
    loss = PhotometricLoss(LossConfig(lpips_weight=0.0), None)
    pred, target = torch.zeros(1, 1, 3, 4, 4), torch.full((1, 1, 3, 4, 4), 0.5)
    terms = loss(pred, target)
    assert set(terms) == {"mse", "total"}
    assert terms["total"].item() == pytest.approx(0.25)
    with pytest.raises(ValueError, match="LPIPS"):
        PhotometricLoss(LossConfig(lpips_weight=0.05), None)


def test_gaussian_blur_keeps_constants_spreads_a_point_by_sigma_and_is_off_at_zero():
    images = torch.rand(2, 3, 21, 21)
    assert gaussian_blur(images, 0.0) is images
    constant = torch.full((1, 3, 21, 21), 0.3)
    assert torch.allclose(gaussian_blur(constant, 2.0), constant, atol=1e-6)
    point = torch.zeros(1, 1, 41, 41)
    point[0, 0, 20, 20] = 1.0
    blurred = gaussian_blur(point, 2.0)[0, 0]
    assert blurred.sum().item() == pytest.approx(1.0, abs=1e-5)
    x = torch.arange(41.0) - 20
    variance = (blurred.sum(0) * x**2).sum().item()  # spread along one axis
    assert variance == pytest.approx(4.0, rel=0.05)


def test_blur_schedule_shrinks_linearly_to_none():
    cfg = LossConfig(lpips_weight=0.0, blur_sigma=4.0, blur_steps=100)
    assert [cfg.blur_at(s) for s in (0, 50, 100, 500)] == [4.0, 2.0, 0.0, 0.0]
    assert LossConfig().blur_at(0) == 0.0
    with pytest.raises(ValueError, match="blur_steps"):
        LossConfig(blur_sigma=1.0)
    with pytest.raises(ValueError, match=">= 0"):
        LossConfig(context_weight=-1.0)


def test_coarse_to_fine_loss_compares_blurred_images_early_only():
    loss = PhotometricLoss(LossConfig(lpips_weight=0.0, blur_sigma=3.0, blur_steps=10), None)
    target = torch.zeros(1, 1, 3, 24, 24)
    pred = target.clone()
    pred[..., ::2, :] = 1.0  # stripes: mean 0.5, gone under a wide blur
    early, late = loss(pred, target, step=0)["mse"].item(), loss(pred, target, step=10)["mse"].item()
    assert late == pytest.approx(0.5)
    assert early == pytest.approx(0.25, rel=0.05)  # what remains is the stripes' mean 0.5, squared


def test_context_views_add_their_weighted_loss():
    loss = PhotometricLoss(LossConfig(lpips_weight=0.0, context_weight=0.5), None)
    assert loss.renders_context and not PhotometricLoss(LossConfig(lpips_weight=0.0), None).renders_context
    pred, target = torch.zeros(1, 1, 3, 4, 4), torch.full((1, 1, 3, 4, 4), 0.5)  # MSE 0.25
    context_pred, context = torch.zeros(1, 2, 3, 4, 4), torch.full((1, 2, 3, 4, 4), 0.2)  # MSE 0.04
    terms = loss(pred, target, 0, context_pred, context)
    assert terms["context_mse"].item() == pytest.approx(0.04)
    assert terms["total"].item() == pytest.approx(0.25 + 0.5 * 0.04)
    with pytest.raises(ValueError, match="context"):
        loss(pred, target)


def _pose(angle: float, axis: int, t) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    i, j = [k for k in range(3) if k != axis]
    pose = torch.eye(4, dtype=torch.float64)
    pose[i, i], pose[i, j], pose[j, i], pose[j, j] = c, -s, s, c
    pose[:3, 3] = torch.tensor(t, dtype=torch.float64)
    return pose


def test_camera_loss_is_zero_at_the_truth_and_measures_each_part():
    gt_e = torch.stack([torch.eye(4, dtype=torch.float64), _pose(0.3, 1, [0.5, 0.0, 0.1])])[None]
    gt_k = torch.tensor([[1.2, 0, 0.5], [0, 1.1, 0.5], [0, 0, 1]], dtype=torch.float64).expand(1, 2, 3, 3)
    zero = camera_loss(gt_e, gt_k, gt_e, gt_k)
    assert all(float(v) == 0 for v in zero.values())
    theta = 0.2  # view 1 turned a further 0.2 rad about y, moved 0.1 along x, focal lengths off by 0.05
    pred_e = torch.stack([torch.eye(4, dtype=torch.float64), _pose(0.3 + theta, 1, [0.6, 0.0, 0.1])])[None]
    pred_k = gt_k.clone()
    pred_k[..., 0, 0] += 0.05
    pred_k[..., 1, 1] -= 0.05
    terms = camera_loss(pred_e, pred_k, gt_e, gt_k)
    assert float(terms["rotation"]) == pytest.approx(theta, rel=1e-4)
    assert float(terms["translation"]) == pytest.approx(0.1, rel=1e-5)
    assert float(terms["focal"]) == pytest.approx(0.05, rel=1e-5)
    parts = sum(float(terms[k]) for k in ("rotation", "translation", "focal"))
    assert float(terms["total"]) == pytest.approx(parts)
    weighted = camera_loss(pred_e, pred_k, gt_e, gt_k, rotation_weight=10.0)
    assert float(weighted["rotation"]) == pytest.approx(theta, rel=1e-4)  # the reported term is unweighted
    assert float(weighted["total"]) == pytest.approx(parts + 9 * float(terms["rotation"]))


def test_camera_loss_gradient_is_finite_at_the_truth():
    gt_e = torch.eye(4).expand(2, 3, 4, 4).clone()
    pred_e = gt_e.clone().requires_grad_(True)
    k = torch.eye(3).expand(2, 3, 3, 3).clone().requires_grad_(True)
    camera_loss(pred_e, k, gt_e, torch.eye(3).expand(2, 3, 3, 3))["total"].backward()
    assert torch.isfinite(pred_e.grad).all() and torch.isfinite(k.grad).all()


@pytest.mark.parametrize("field", ["pose_weight", "pose_rotation_weight"])
def test_pose_weights_must_not_be_negative(field):
    with pytest.raises(ValueError, match="pose_rotation_weight must be >= 0"):
        LossConfig(**{field: -1.0})
