"""The camera head where training starts (VGGT's, as NAS3R initialises it: identity rotation, zero translation,
FOV 2·atan(0.5)), and with saturated outputs (FOV beyond VGGT's clamp, a zero quaternion, far translations).

The pose encoding [T, quaternion x, y, z, w, fov_h, fov_w] becomes cameras through ``quat_to_matrix``, a pose
inversion and the pose relative to view 0; every camera-head parameter must get a finite gradient at the start
and at the saturated outputs. The model no longer turns the camera rotations into quaternions (the Gaussians'
rotations are taken in view 0's frame as the Gaussian head predicts them), so ``matrix_to_quat``'s singular
point is off the path.
"""

import math

import pytest
import torch

from aesplat.geometry import DEFAULT_FOV
from aesplat.model import build_model
from aesplat.model.camera_head import FOV_MAX, FOV_MIN, CameraHead


def _camera_head_loss(head: CameraHead, tokens: torch.Tensor, aspect: float = 1.0) -> torch.Tensor:
    """What rendering reads of the head's outputs as one scalar: rotations, translations, focal lengths."""
    ext, intr = head(tokens, aspect=aspect)
    weights = torch.linspace(-1.0, 2.0, 9).reshape(3, 3)
    return (
        (ext[..., :3, :3] * weights).sum()
        + (ext[..., :3, 3] * torch.tensor([0.3, -1.0, 2.0])).sum()
        + intr.sum()
    )


@pytest.mark.parametrize("iterations", [1, 4])
def test_camera_head_starts_at_the_identity_with_finite_gradients(iterations):
    torch.manual_seed(0)
    head = CameraHead(16, num_heads=2, trunk_depth=1, iterations=iterations)
    tokens = torch.randn(4, 3, 16)
    ext, intr = head(tokens, aspect=1.5)
    # every view at the identity with zero translation, exactly, whatever the tokens (and however many
    # refinements: each adds its share of the start)
    assert torch.equal(ext, torch.eye(4).expand(4, 3, 4, 4))
    focal = 0.5 / math.tan(DEFAULT_FOV / 2)  # 1: FOV 2·atan(0.5)
    expected = torch.tensor([[focal / 1.5, 0.0, 0.5], [0.0, focal, 0.5], [0.0, 0.0, 1.0]])
    torch.testing.assert_close(intr, expected.expand(4, 3, 3, 3))
    _camera_head_loss(head, tokens, aspect=1.5).backward()
    bad = [name for name, p in head.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all()]
    assert not bad, f"missing or non-finite gradients: {bad}"
    out = head.pose_branch.fc2  # rows: translation (3), quaternion x, y, z, w, fov_h, fov_w
    assert out.weight.grad[:3].abs().sum() > 0  # the translation is learned from there
    assert out.weight.grad[3:6].abs().sum() > 0  # ... the rotation
    assert out.bias.grad[7].abs() > 0  # ... the field of view


def test_camera_head_with_saturated_outputs_has_finite_gradients():
    torch.manual_seed(1)
    head = CameraHead(16, num_heads=2, trunk_depth=1)
    out = head.pose_branch.fc2
    for fov, clamped in ((60.0, FOV_MAX), (-60.0, FOV_MIN)):  # beyond the clamp (-60: through VGGT's ReLU)
        with torch.no_grad():
            out.weight.normal_(std=1e-3)
            out.bias[:3] = 1e4  # a camera far away
            out.bias[3:7] = 0.0  # a zero quaternion (near it: the weights' small outputs)
            out.bias[7] = fov
        tokens = torch.randn(2, 3, 16)
        ext, intr = head(tokens)
        torch.testing.assert_close(intr[..., 1, 1], torch.full((2, 3), 0.5 / math.tan(clamped / 2)))
        assert torch.isfinite(ext).all()
        head.zero_grad()
        _camera_head_loss(head, tokens).backward()
        assert all(torch.isfinite(p.grad).all() for p in head.parameters())
        assert out.bias.grad[7] == 0  # clamped: the FOV gets no gradient


def test_exactly_zero_quaternions_give_the_identity_and_finite_gradients():
    head = CameraHead(16, num_heads=2, trunk_depth=1)
    with torch.no_grad():
        head.pose_branch.fc2.bias[3:7] = 0.0  # the weights are zero at the start: the quaternion is exactly 0
    tokens = torch.randn(2, 3, 16)
    ext, _ = head(tokens)
    assert torch.equal(ext, torch.eye(4).expand(2, 3, 4, 4))
    _camera_head_loss(head, tokens).backward()
    assert all(torch.isfinite(p.grad).all() for p in head.parameters())


def test_gaussian_rotations_are_the_gaussian_heads_whatever_the_cameras():
    """NAS3R takes each Gaussian's rotation in view 0's frame as its head predicts it: a camera head that turns
    the other views changes their cameras, not the Gaussians' quaternions."""
    torch.manual_seed(0)
    model = build_model("tiny", sh_degree=1).eval()
    ctx, tgt = torch.rand(1, 2, 3, 28, 28), torch.rand(1, 1, 3, 28, 28)
    with torch.no_grad():
        start = model(ctx, tgt)
        model.camera_head.pose_branch.fc2.weight.normal_(std=0.5)  # the views' rotations now differ
        turned = model(ctx, tgt)
    rotation = turned.extrinsics[0, 1, :3, :3]
    assert (rotation - torch.eye(3)).abs().max() > 0.05
    torch.testing.assert_close(turned.gaussians.quats, start.gaussians.quats, rtol=0, atol=0)
    assert (turned.gaussians.means - start.gaussians.means).abs().max() > 1e-3  # the cameras did move them
