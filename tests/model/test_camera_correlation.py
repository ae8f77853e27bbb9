"""The camera head's optional correlation branch (``camera_correlation``)."""

import pytest
import torch

from aesplat.model.camera_head import CameraHead, ViewCorrelation, cost_volume
from aesplat.model.model import build_model


def _trained(head: CameraHead) -> CameraHead:
    """``head`` with a non-zero pose output layer, as a trained head has: a new head's pose and FoV weights are
    zero (it starts at the identity), so no gradient would reach the layers below it."""
    with torch.no_grad():
        head.pose_branch.fc2.weight.normal_(std=0.05)
    return head


def test_cost_volume_peaks_at_the_shift_between_the_maps():
    torch.manual_seed(0)
    ref = torch.nn.functional.normalize(torch.randn(1, 8, 12, 16), dim=1)
    dy, dx = 1, -3  # other[i, j] = ref[i + dy, j + dx]
    other = torch.roll(ref, shifts=(-dy, -dx), dims=(-2, -1))
    ry, rx = 2, 4
    volume = cost_volume(ref, other, (ry, rx))
    assert volume.shape == (1, (2 * ry + 1) * (2 * rx + 1), 12, 16)
    inner = volume[0, :, ry:-ry, rx:-rx]  # cells whose matches lie inside ref (no wrap-around)
    best = inner.argmax(0)
    assert (best == (dy + ry) * (2 * rx + 1) + (dx + rx)).all()
    torch.testing.assert_close(inner.amax(0), torch.ones_like(inner[0]))


def test_view_zero_gets_zeros_and_each_view_only_its_pair():
    torch.manual_seed(0)
    corr = ViewCorrelation(hidden=8)
    images = torch.rand(2, 3, 3, 42, 42)
    out = corr(images)
    assert out.shape == (2, 3, 8)
    assert (out[:, 0] == 0).all() and out[:, 1:].abs().sum() > 0
    changed = images.clone()
    changed[:, 2] = torch.rand(2, 3, 42, 42)
    out2 = corr(changed)
    torch.testing.assert_close(out2[:, 1], out[:, 1])  # view 1 depends on views 0 and 1 only
    assert not torch.allclose(out2[:, 2], out[:, 2])
    changed[:, 0] = torch.rand(2, 3, 42, 42)
    assert not torch.allclose(corr(changed)[:, 1], out[:, 1])  # ... and on view 0


def test_other_image_sizes_are_resized_to_the_working_size():
    corr = ViewCorrelation(hidden=8)
    assert corr(torch.rand(1, 2, 3, 56, 70)).shape == (1, 2, 8)


@pytest.mark.parametrize("fill", [0.0, 1.0])
def test_constant_images_keep_the_branch_finite(fill):
    torch.manual_seed(0)
    head = _trained(CameraHead(16, num_heads=2, trunk_depth=1, correlation=True))
    images = torch.full((2, 3, 3, 42, 42), fill)
    ext, intr = head(torch.randn(2, 3, 16), images)
    (ext.sum() + intr.sum()).backward()
    assert torch.isfinite(ext).all() and torch.isfinite(intr).all()
    missing = [name for name, p in head.named_parameters() if p.grad is None]
    assert not missing, f"no gradient reached {missing}"  # the branch is in the graph, even on flat images
    assert all(torch.isfinite(p.grad).all() for p in head.parameters())
    assert head.correlation.reduce[-1].weight.grad.abs().sum() > 0  # the branch moves the poses


def test_the_branch_needs_the_images():
    head = CameraHead(16, num_heads=2, trunk_depth=1, correlation=True)
    with pytest.raises(ValueError, match="needs the images"):
        head(torch.randn(1, 2, 16))


def test_model_option_adds_the_branch_and_keeps_the_other_keys():
    torch.manual_seed(0)
    plain, corr = build_model("tiny"), build_model("tiny", camera_correlation=True)
    assert plain.camera_head.correlation is None and corr.camera_head.correlation is not None
    extra = set(corr.state_dict()) - set(plain.state_dict())
    assert extra and all(k.startswith("camera_head.correlation.") for k in extra)
    assert set(plain.state_dict()) <= set(corr.state_dict())  # a checkpoint without it still names the same
    _trained(corr.camera_head)
    ctx, tgt = torch.rand(2, 2, 3, 42, 42), torch.rand(2, 1, 3, 42, 42)
    out = corr(ctx, tgt)
    out.extrinsics[:, 1:, :3, 3].sum().backward()
    assert corr.camera_head.correlation.features[0].weight.grad.abs().sum() > 0
