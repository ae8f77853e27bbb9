"""Backward passes AT the singular points of the geometry: exact identities, 180° turns, zero vectors.

Each check holds on every torch release, whatever its autograd does with 0 · inf: gradients are compared
with an analytic derivative where one exists, must be finite on the exact singular inputs, and a float64
gradcheck sits next to them. Rotations are moved along the group, R0 · exp([ω]x), so that a check never
leaves SO(3) and never depends on how a formula extends to matrices that are not rotations.
"""

import math

import pytest
import torch
from torch.autograd.functional import jacobian

from aesplat.geometry import (
    DEFAULT_FOV,
    covariance_from_scale_rot,
    focal_to_fov,
    fov_to_focal,
    homogeneous_to_translation,
    intrinsics_from_fov,
    matrix_to_quat,
    quat_to_matrix,
    rot6d_to_matrix,
    safe_norm,
    safe_normalize,
)
from aesplat.model.camera_head import FOV_MAX, FOV_MIN


def _hat(w: torch.Tensor) -> torch.Tensor:
    """[..., 3] -> skew-symmetric [..., 3, 3] with hat(w) v = w x v."""
    zero = torch.zeros_like(w[..., 0])
    x, y, z = w.unbind(-1)
    rows = [zero, -z, y, z, zero, -x, -y, x, zero]
    return torch.stack(rows, dim=-1).reshape(*w.shape[:-1], 3, 3)


def _turn(axis, angle: float, dtype=torch.float64) -> torch.Tensor:
    """Rotation [3, 3] by ``angle`` about ``axis`` (Rodrigues), built in float64 then cast."""
    n = torch.tensor(axis, dtype=torch.float64)
    k = _hat(n / n.norm())
    r = torch.eye(3, dtype=torch.float64) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)
    return r.to(dtype)


def _exact(diag) -> torch.Tensor:
    return torch.diag(torch.tensor(diag, dtype=torch.float64))


# The singular rotations: the identity, the three exact 180° coordinate turns (integer matrices), 180° turns
# about oblique axes (two diagonal entries tie about (1, 1, 0)), and a generic rotation as a control.
ROTATIONS = {
    "identity": torch.eye(3, dtype=torch.float64),
    "x180": _exact([1.0, -1.0, -1.0]),
    "y180": _exact([-1.0, 1.0, -1.0]),
    "z180": _exact([-1.0, -1.0, 1.0]),
    "xy180": _turn([1.0, 1.0, 0.0], math.pi),
    "oblique180": _turn([1.0, 2.0, -3.0], math.pi),
    "generic": _turn([0.3, -0.5, 0.8], 1.1),
}


def _along(r0: torch.Tensor, fn):
    """ω [3] -> fn(R0 · exp([ω]x)): a function of a tangent vector at R0."""
    return lambda w: fn(r0 @ torch.linalg.matrix_exp(_hat(w)))


def _round_trip(r: torch.Tensor) -> torch.Tensor:
    return quat_to_matrix(matrix_to_quat(r))


def _outer(r: torch.Tensor) -> torch.Tensor:
    """q q^T: the same for q and -q, so smooth across the w >= 0 sign choice at 180° turns."""
    q = matrix_to_quat(r)
    return q[..., :, None] * q[..., None, :]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", list(ROTATIONS))
def test_matrix_to_quat_round_trip_has_the_analytic_derivative(name, dtype):
    """d/dω quat_to_matrix(matrix_to_quat(R0 exp([ω]x))) at ω = 0 is R0 [e_i]x, column by column."""
    r0 = ROTATIONS[name].to(dtype)
    jac = jacobian(_along(r0, _round_trip), torch.zeros(3, dtype=dtype))  # [3, 3, 3]
    expected = torch.stack([r0 @ _hat(e) for e in torch.eye(3, dtype=dtype)], dim=-1)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(jac, expected, atol=tol, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matrix_to_quat_derivative_at_identity(dtype):
    """At the identity q(ω) = (cos |ω|/2, sin(|ω|/2) ω/|ω|): dq/dω = [0; I/2], and with respect to the
    matrix entries dq_x/dR_21 = 1/4 = -dq_x/dR_12 (cyclically), nothing else."""
    jac = jacobian(_along(torch.eye(3, dtype=dtype), matrix_to_quat), torch.zeros(3, dtype=dtype))
    expected = torch.cat([torch.zeros(1, 3, dtype=dtype), 0.5 * torch.eye(3, dtype=dtype)])
    torch.testing.assert_close(jac, expected, atol=1e-7, rtol=0)

    jac_m = jacobian(matrix_to_quat, torch.eye(3, dtype=dtype))  # [4, 3, 3]
    expected_m = torch.zeros(4, 3, 3, dtype=dtype)
    for i, (a, b) in enumerate([(2, 1), (0, 2), (1, 0)], start=1):
        expected_m[i, a, b], expected_m[i, b, a] = 0.25, -0.25
    torch.testing.assert_close(jac_m, expected_m, atol=1e-7, rtol=0)


@pytest.mark.parametrize("name", list(ROTATIONS))
def test_matrix_to_quat_gradients_are_finite_at_the_singular_rotations(name):
    r = ROTATIONS[name].float().requires_grad_(True)
    q = matrix_to_quat(r)
    torch.testing.assert_close(q.norm(), torch.tensor(1.0))
    assert q[0] >= 0
    (q * torch.tensor([0.3, -1.0, 2.0, 0.7])).sum().backward()
    assert torch.isfinite(r.grad).all()


@pytest.mark.parametrize("name", list(ROTATIONS))
def test_matrix_to_quat_gradcheck_float64(name):
    fn = _along(ROTATIONS[name], _outer)
    assert torch.autograd.gradcheck(fn, (torch.zeros(3, dtype=torch.float64, requires_grad=True),))
    off = torch.tensor([1e-3, -2e-3, 5e-4], dtype=torch.float64, requires_grad=True)  # just beside it
    assert torch.autograd.gradcheck(fn, (off,))


def test_camera_head_start_has_finite_gradients_near_the_identity():
    """The camera head (VGGT's) starts at the quaternion (x, y, z, w) = (0, 0, 0, 1): quat_to_matrix must give
    finite gradients for every rotation near there, for the exact identity and 180° turns (w = 0), and for
    the zero quaternion (all outputs zero), which is the identity with a zero gradient."""
    gen = torch.Generator().manual_seed(0)
    base = torch.tensor([1.0, 0.0, 0.0, 0.0])  # (w, x, y, z)
    near = [base + s * torch.randn(200, 4, generator=gen) for s in (1e-2, 1e-3, 1e-4, 1e-6)]
    exact = torch.tensor(
        [[1.0, 0, 0, 0], [-1.0, 0, 0, 0], [0.0, 1, 0, 0], [0.0, 0, 1, 0], [0.0, 0, 0, -1], [0.0, 0, 0, 0]]
    )
    q = torch.cat([*near, exact]).requires_grad_(True)
    rot = quat_to_matrix(q)
    (rot * torch.randn(rot.shape, generator=gen)).sum().backward()
    bad = (~torch.isfinite(q.grad).all(-1)).sum()
    assert bad == 0, f"{int(bad)} of {q.shape[0]} rotations have non-finite gradients"
    torch.testing.assert_close(rot[-1], torch.eye(3))  # the zero quaternion: the identity ...
    assert torch.equal(q.grad[-1], torch.zeros(4))  # ... held constant
    assert q.grad[-6].abs().sum() > 0  # the exact identity still learns


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_quat_to_matrix_derivative_at_the_identity(dtype):
    """At q = (1, 0, 0, 0) (w, x, y, z): dR/dv_i = 2 [e_i]x for the vector part, and dR/dw = 0 (the
    normalisation takes out the radial direction)."""
    jac = jacobian(quat_to_matrix, torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype))  # [3, 3, 4]
    expected = torch.stack([torch.zeros(3, 3, dtype=dtype)] + [2 * _hat(e) for e in torch.eye(3, dtype=dtype)],
                           dim=-1)  # fmt: skip
    torch.testing.assert_close(jac, expected, atol=1e-7, rtol=0)


def test_safe_norm_and_normalize_at_the_zero_vector():
    x = torch.zeros(2, 3, requires_grad=True)
    n, u = safe_norm(x, eps=1e-8), safe_normalize(x)
    assert torch.equal(u, torch.zeros(2, 3))
    torch.testing.assert_close(n, torch.full((2,), 1e-8))
    (n.sum() + (u * torch.tensor([1.0, -2.0, 3.0])).sum()).backward()
    assert torch.equal(x.grad, torch.zeros(2, 3))  # both are constant at (and around) zero

    z = torch.zeros(3, requires_grad=True)
    safe_norm(z, eps=0.0).backward()  # eps 0: the exact norm, 0 at zero, still a finite gradient
    assert torch.equal(z.grad, torch.zeros(3))


def test_safe_normalize_has_the_analytic_derivative():
    """d(x/|x|)/dx = (I - u u^T) / |x|, also for tiny vectors far below any eps of a clamp."""
    for scale in (1.0, 1e-20):
        x = torch.tensor([0.3, -1.2, 0.4], dtype=torch.float64) * scale
        u = x / x.norm()
        expected = (torch.eye(3, dtype=torch.float64) - u[:, None] * u[None]) / x.norm()
        torch.testing.assert_close(jacobian(safe_normalize, x), expected, rtol=1e-12, atol=0)
    x = torch.tensor([0.3, -1.2, 0.4], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: (safe_norm(v), safe_normalize(v)), (x,))


def test_rot6d_at_identity_and_half_turns_has_finite_gradients_and_gradchecks():
    cases = torch.tensor(
        [[1.0, 0, 0, 0, 1, 0], [1.0, 0, 0, 0, -1, 0], [-1.0, 0, 0, 0, -1, 0], [0.0, 0, 0, 0, 1, 0],
         [1.0, 0, 0, 2.0, 0, 0], [0.0, 0, 0, 0, 0, 0]]
    )  # fmt: skip
    d6 = cases.clone().requires_grad_(True)
    (rot6d_to_matrix(d6) * torch.randn(6, 3, 3)).sum().backward()
    assert torch.isfinite(d6.grad).all()
    for row in cases[:3].double():
        assert torch.autograd.gradcheck(rot6d_to_matrix, (row.clone().requires_grad_(True),))


def test_quaternion_and_covariance_at_zero_and_half_turns():
    q = torch.tensor([[0.0, 0, 0, 0], [1.0, 0, 0, 0], [0.0, 1, 0, 0], [0.0, 0, 0, -1]], requires_grad=True)
    s = torch.tensor([[0.0, 0, 0], [1.0, 1, 1], [0.0, 2, 0], [1e-7, 1, 3]], requires_grad=True)
    (covariance_from_scale_rot(s, q) * torch.randn(4, 3, 3)).sum().backward()
    assert torch.isfinite(q.grad).all() and torch.isfinite(s.grad).all()
    assert torch.equal(q.grad[0], torch.zeros(4))  # the zero quaternion is the identity, held constant
    for row in q.detach()[1:].double():
        assert torch.autograd.gradcheck(quat_to_matrix, (row.clone().requires_grad_(True),))


def test_homogeneous_translation_at_a_vanishing_w():
    """w = softplus(raw) + eps: raw -> -inf leaves the denominator at eps with finite gradients (a geometry
    helper; the camera head predicts its translation directly, as VGGT's)."""
    t4 = torch.tensor([[1.0, -2.0, 3.0, -200.0], [0.0, 0.0, 0.0, 0.0]], requires_grad=True)
    t = homogeneous_to_translation(t4)
    torch.testing.assert_close(t[0], torch.tensor([1.0, -2.0, 3.0]) / 1e-3)
    t.sum().backward()
    assert torch.isfinite(t4.grad).all()
    x = torch.tensor([0.5, -1.0, 2.0, -3.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(homogeneous_to_translation, (x,))


def test_fov_to_focal_at_the_camera_heads_bounds_has_the_analytic_derivative():
    """The camera head clamps the FOV to [0.09, 2.97] rad (VGGT's); d/dfov 0.5 / tan(fov / 2) =
    -1 / (4 sin²(fov / 2))."""
    fov = torch.tensor([FOV_MIN, DEFAULT_FOV, FOV_MAX], dtype=torch.float64)
    jac = jacobian(fov_to_focal, fov).diagonal()
    torch.testing.assert_close(jac, -0.25 / torch.sin(0.5 * fov) ** 2, rtol=1e-12, atol=0)
    fov32 = fov.float().requires_grad_(True)
    intrinsics_from_fov(fov32).sum().backward()
    assert torch.isfinite(fov32.grad).all()
    assert torch.autograd.gradcheck(focal_to_fov, (fov_to_focal(fov).detach().requires_grad_(True),))
