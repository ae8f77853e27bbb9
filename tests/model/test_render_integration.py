"""The model through the rasterizer: I2DC reproduces a plane; cameras learn by rendering."""

import torch

from aesplat.geometry import unproject_depth
from aesplat.model import build_model
from aesplat.render import render
from aesplat.types import Gaussians

H = W = 42


def _smooth_images(b: int, v: int) -> torch.Tensor:
    """Low-frequency colour images [B, V, 3, H, W] in [0.1, 0.9]."""
    ys = torch.linspace(0, 1, H)[:, None]
    xs = torch.linspace(0, 1, W)[None]
    views = []
    for i in range(v):
        chans = [0.5 + 0.4 * torch.sin(3.0 * xs + 2.0 * ys + i + c) for c in range(3)]
        views.append(torch.stack(chans))
    return torch.stack(views).expand(b, -1, -1, -1, -1).clone()


def test_i2dc_only_plane_reproduces_the_context_view():
    model = build_model("tiny", appearance="i2dc_only")
    images = _smooth_images(1, 2)
    with torch.no_grad():
        out = model(images)
    n = H * W
    k0, e0 = out.intrinsics[:, :1], out.extrinsics[:, :1]  # view 0: the identity, predicted FOV
    depth = torch.full((1, 1, H, W), 2.0)  # ground-truth depth: a fronto-parallel plane
    means = unproject_depth(depth, k0, e0).reshape(1, n, 3)
    g = out.gaussians
    assert g.sh.shape == (1, 2 * n, 1, 3)
    plane = Gaussians(
        means=means,
        quats=g.quats[:, :n],
        scales=torch.full((1, n, 3), 1e-4),
        opacities=torch.full((1, n), 1.0 - 1e-6),
        sh=g.sh[:, :n],
    )
    color = render(plane, e0, k0, H, W, background=torch.zeros(3), backend="torch").color
    mse = (color[:, 0] - images[:, 0]).square().mean()
    psnr = -10.0 * torch.log10(mse)
    assert psnr > 40.0, f"PSNR {psnr:.1f} dB"


def test_gradients_reach_the_camera_head_through_rendering():
    model = build_model("tiny", appearance="full", sh_degree=2, near=1.0, far=10.0)
    images = _smooth_images(1, 3)
    out = model(images[:, :2], images[:, 2:])
    out.extrinsics.retain_grad()
    out.intrinsics.retain_grad()
    rendered = render(out.gaussians, out.extrinsics[:, 2:], out.intrinsics[:, 2:], H, W, backend="torch")
    loss = (rendered.color - images[:, 2:]).square().mean()
    loss.backward()
    # The predicted target camera gets its gradient from the rasterizer ...
    assert out.extrinsics.grad[:, 2, :3].abs().sum() > 0 and out.intrinsics.grad[:, 2, 0, 0].abs() > 0
    assert torch.isfinite(out.extrinsics.grad).all() and torch.isfinite(out.intrinsics.grad).all()
    # ... and passes it on to the camera head.
    head = model.camera_head
    for name, p in head.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    # VGGT's pose encoding [T (3), quaternion x, y, z, w (4), fov_h, fov_w]: every part but fov_w, which
    # NAS3R's cameras do not use (one focal length for all views, from view 0's fov_h)
    out_layer = head.pose_branch.fc2
    assert out_layer.weight.grad[:3].abs().sum() > 0  # translation
    assert out_layer.weight.grad[3:7].abs().sum() > 0  # rotation
    assert out_layer.bias.grad[7].abs() > 0  # fov_h
    assert out_layer.bias.grad[8] == 0 and out_layer.weight.grad[8].abs().sum() == 0  # fov_w
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
