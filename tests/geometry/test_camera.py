import math

import pytest
import torch

from aesplat.geometry import (
    DEFAULT_FOV,
    denormalize_intrinsics,
    focal_to_fov,
    fov_to_focal,
    intrinsics_from_fov,
    invert_pose,
    make_pose,
    normalize_intrinsics,
    project_points,
    quat_to_matrix,
    relative_to_first,
    unproject_depth,
)


def random_cameras(b: int, v: int, dtype=torch.float32):
    q = torch.randn(b, v, 4, dtype=dtype)
    t = torch.randn(b, v, 3, dtype=dtype)
    extr = make_pose(quat_to_matrix(q), t)
    fov = torch.empty(b, v, dtype=dtype).uniform_(0.6, 1.6)
    intr = intrinsics_from_fov(fov)
    intr[..., 0, 2] += torch.empty(b, v, dtype=dtype).uniform_(-0.05, 0.05)
    intr[..., 1, 1] *= torch.empty(b, v, dtype=dtype).uniform_(0.9, 1.1)
    return extr, intr


def test_project_unproject_round_trip_float32():
    b, v, h, w = 2, 3, 12, 17
    extr, intr = random_cameras(b, v)
    depth = torch.empty(b, v, h, w).uniform_(0.5, 20.0)
    pts = unproject_depth(depth, intr, extr)  # [B, V, H, W, 3]
    for view in range(v):
        uv, z, valid = project_points(pts[:, view].reshape(b, -1, 3), intr, extr, h, w)
        ys, xs = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
        expected = torch.stack([xs, ys], -1).reshape(-1, 2).expand(b, -1, -1)
        # float32 with depths up to 20 and translations of O(1): 1e-3 px and 1e-4 relative depth.
        torch.testing.assert_close(uv[:, view], expected, atol=1e-3, rtol=0)
        torch.testing.assert_close(z[:, view], depth[:, view].reshape(b, -1), rtol=1e-4, atol=1e-5)
        assert valid[:, view].all()


def test_project_behind_and_outside_are_invalid_and_finite():
    extr = torch.eye(4).expand(1, 1, 4, 4)
    intr = intrinsics_from_fov(torch.full((1, 1), DEFAULT_FOV))
    pts = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [5.0, 0.0, 1.0]]])
    uv, z, valid = project_points(pts, intr, extr, 10, 10)
    assert valid.tolist() == [[[True, False, False, False]]]
    assert torch.isfinite(uv).all()
    torch.testing.assert_close(uv[0, 0, 0], torch.tensor([5.0, 5.0]))


def test_intrinsics_normalisation_round_trip_and_fov():
    fov = torch.tensor([0.3, DEFAULT_FOV, 2.0])
    k = intrinsics_from_fov(fov)
    torch.testing.assert_close(focal_to_fov(fov_to_focal(fov)), fov)
    torch.testing.assert_close(k[1, 0, 0], torch.tensor(1.0))  # 2 atan(0.5) <-> normalised focal 1
    kp = denormalize_intrinsics(k, 48, 64)
    assert kp[0, 0, 0] == pytest.approx(64 * 0.5 / math.tan(0.15))
    assert kp[0, 1, 2] == pytest.approx(24.0)
    torch.testing.assert_close(normalize_intrinsics(kp, 48, 64), k)


def test_relative_to_first_makes_view0_identity_and_keeps_relative_motion():
    extr, _ = random_cameras(2, 3)
    rel = relative_to_first(extr)
    assert torch.equal(rel[:, 0], torch.eye(4).expand(2, 4, 4))
    # The pose of view 2 relative to view 1 is unchanged by the change of frame.
    a = invert_pose(extr[:, 1]) @ extr[:, 2]
    r = invert_pose(rel[:, 1]) @ rel[:, 2]
    torch.testing.assert_close(a, r, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(invert_pose(extr) @ extr, torch.eye(4).expand_as(extr), atol=1e-5, rtol=0)


@pytest.mark.parametrize(("aspect", "height", "width"), [(2.0, 20, 40), (0.5, 40, 20), (16 / 9, 90, 160)])
def test_intrinsics_from_fov_have_square_pixels_and_the_fov_across_the_shorter_side(aspect, height, width):
    fov = torch.tensor([0.9, 1.3])
    k = intrinsics_from_fov(fov, aspect)
    pixels = denormalize_intrinsics(k, height, width)
    torch.testing.assert_close(pixels[:, 0, 0], pixels[:, 1, 1])  # square pixels: one focal length in pixels
    short = min(height, width)  # the FOV spans the shorter side
    torch.testing.assert_close(2 * torch.atan(0.5 * short / pixels[:, 0, 0]), fov)
    torch.testing.assert_close(k[:, 0, 0] / k[:, 1, 1], torch.full((2,), height / width))
    torch.testing.assert_close(k[:, :2, 2], torch.full((2, 2), 0.5))
    square = intrinsics_from_fov(fov)
    torch.testing.assert_close(square[:, 0, 0], square[:, 1, 1])
    with pytest.raises(ValueError, match="aspect"):
        intrinsics_from_fov(fov, 0.0)
