import torch

from aesplat.geometry import (
    covariance_from_scale_rot,
    homogeneous_to_translation,
    matrix_to_quat,
    matrix_to_rot6d,
    quat_to_matrix,
    rot6d_to_matrix,
)


def assert_rotation(r: torch.Tensor, atol: float = 1e-5) -> None:
    assert torch.isfinite(r).all()
    eye = torch.eye(3, dtype=r.dtype).expand_as(r)
    torch.testing.assert_close(r @ r.transpose(-1, -2), eye, atol=atol, rtol=0)
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(r.shape[:-2], dtype=r.dtype), atol=atol, rtol=0)


def test_rot6d_random_is_rotation_and_round_trips():
    d6 = torch.randn(1000, 6)
    r = rot6d_to_matrix(d6)
    assert_rotation(r)
    torch.testing.assert_close(rot6d_to_matrix(matrix_to_rot6d(r)), r, atol=1e-5, rtol=0)
    assert torch.equal(rot6d_to_matrix(torch.tensor([1.0, 0, 0, 0, 1, 0])), torch.eye(3))


def test_rot6d_degenerate_inputs_give_rotations_and_finite_gradients():
    a = torch.randn(50, 3)
    cases = [
        torch.cat([a, 2.5 * a], -1),  # collinear
        torch.cat([a, -a], -1),  # anti-parallel
        torch.cat([a, a + 1e-9], -1),  # near collinear
        torch.cat([torch.zeros(50, 3), a], -1),  # zero first vector
        torch.zeros(50, 6),  # all zero
    ]
    for d6 in cases:
        d6 = d6.clone().requires_grad_(True)
        r = rot6d_to_matrix(d6)
        assert_rotation(r.detach())
        r.sum().backward()
        assert torch.isfinite(d6.grad).all()


def test_quaternion_round_trip_and_zero_quaternion():
    q = torch.randn(500, 4, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    r = quat_to_matrix(q)
    assert_rotation(r, atol=1e-10)
    torch.testing.assert_close(matrix_to_quat(r), q, atol=1e-10, rtol=0)
    # Scaled quaternions give the same rotation (normalised inside).
    torch.testing.assert_close(quat_to_matrix(3.7 * q), r)
    z = torch.zeros(3, 4, requires_grad=True)
    rz = quat_to_matrix(z)
    assert torch.equal(rz.detach(), torch.eye(3).expand(3, 3, 3))
    rz.sum().backward()
    assert torch.isfinite(z.grad).all()
    # 180-degree rotations are where naive formulas divide by zero.
    flips = torch.diag_embed(torch.tensor([[1.0, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=torch.float64))
    torch.testing.assert_close(quat_to_matrix(matrix_to_quat(flips)), flips, atol=1e-12, rtol=0)


def test_covariance_is_symmetric_psd_with_given_eigenvalues():
    s = torch.rand(100, 3, dtype=torch.float64) + 0.1
    q = torch.randn(100, 4, dtype=torch.float64)
    cov = covariance_from_scale_rot(s, q)
    torch.testing.assert_close(cov, cov.transpose(-1, -2))
    eig = torch.linalg.eigvalsh(cov)
    torch.testing.assert_close(eig, (s**2).sort(-1).values)


def test_homogeneous_translation_keeps_denominator_away_from_zero():
    t4 = torch.tensor([[1.0, 2.0, 3.0, -1e4], [1.0, 0.0, 0.0, 30.0]], requires_grad=True)
    t = homogeneous_to_translation(t4)
    assert torch.isfinite(t).all() and t[0].abs().max() <= 3.0 / 1e-3 + 1
    torch.testing.assert_close(t[1], torch.tensor([1.0 / 30.0, 0.0, 0.0]), atol=1e-4, rtol=1e-4)
    t.sum().backward()
    assert torch.isfinite(t4.grad).all()
