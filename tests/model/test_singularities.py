"""The camera head where training starts: identity rotations, and saturated FOV / translation outputs.

The model turns the head's rotations into quaternions (``matrix_to_quat``) to carry the Gaussians into view
0's frame; at the head's identity start that conversion sits on its singular point. Every camera-head
parameter must get a finite gradient there, whatever the torch release.
"""

import torch

from aesplat.geometry import matrix_to_quat
from aesplat.model.camera_head import FOV_MAX, CameraHead
from aesplat.model.model import _quat_multiply


def _camera_head_loss(head: CameraHead, tokens: torch.Tensor) -> torch.Tensor:
    """What the model does with the head's outputs, reduced to a scalar: quaternions of every view composed
    with fixed Gaussian rotations, translations and focal lengths."""
    ext, intr = head(tokens)
    quats = _quat_multiply(matrix_to_quat(ext[..., :3, :3]), torch.tensor([0.9, 0.1, -0.3, 0.2]))
    return (quats * torch.tensor([0.4, -1.0, 0.7, 2.0])).sum() + ext[..., :3, 3].sum() + intr.sum()


def test_camera_head_at_its_identity_start_has_finite_gradients():
    torch.manual_seed(0)
    head = CameraHead(in_dim=16, hidden=32)
    tokens = torch.randn(4, 3, 16)
    ext, _ = head(tokens)
    eye = torch.eye(3).expand(4, 2, 3, 3)
    torch.testing.assert_close(ext[:, 1:, :3, :3], eye, atol=1e-2, rtol=0)  # the start: near the identity
    for weight in (head.rotation.weight, head.translation.weight):  # exactly the identity, zero translation
        with torch.no_grad():
            weight.zero_()
        _camera_head_loss(head, tokens).backward()
        bad = [name for name, p in head.named_parameters() if not torch.isfinite(p.grad).all()]
        assert not bad, f"non-finite gradients: {bad}"
        assert head.rotation.bias.grad.abs().sum() > 0  # the rotation is still learned from there
        head.zero_grad()


def test_camera_head_with_saturated_outputs_has_finite_gradients():
    torch.manual_seed(1)
    head = CameraHead(in_dim=16, hidden=32)
    with torch.no_grad():
        head.fov.bias.fill_(60.0)  # sigmoid saturated: FOV at its 160° bound
        head.translation.bias[3] = -80.0  # homogeneous w -> softplus(-80) + eps = eps
        head.rotation.bias.copy_(torch.tensor([-1.0, 0.0, 0.0, 0.0, -1.0, 0.0]))  # a 180° turn about z
    _, intr = head(torch.randn(2, 3, 16))
    torch.testing.assert_close(intr[..., 0, 0], torch.full((2, 3), 0.5 / torch.tan(torch.tensor(FOV_MAX / 2))))
    _camera_head_loss(head, torch.randn(2, 3, 16)).backward()
    assert all(torch.isfinite(p.grad).all() for p in head.parameters())
