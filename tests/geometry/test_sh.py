import math

import pytest
import torch

from aesplat.geometry import (
    C0,
    eval_sh,
    num_sh_coeffs,
    quat_to_matrix,
    rgb_to_sh_dc,
    sh_basis,
    sh_dc_to_rgb,
    sh_rotation_matrix,
)


def assoc_legendre_cs(l: int, m: int, x: torch.Tensor) -> torch.Tensor:
    """P_l^m(x) with the Condon-Shortley phase, m >= 0, by the standard recurrences (independent check)."""
    pmm = torch.ones_like(x)
    somx2 = torch.sqrt((1 - x) * (1 + x))
    fact = 1.0
    for _ in range(m):
        pmm = -pmm * fact * somx2
        fact += 2.0
    if l == m:
        return pmm
    pmmp1 = x * (2 * m + 1) * pmm
    if l == m + 1:
        return pmmp1
    for ll in range(m + 2, l + 1):
        pll = ((2 * ll - 1) * x * pmmp1 - (ll + m - 1) * pmm) / (ll - m)
        pmm, pmmp1 = pmmp1, pll
    return pmmp1


def reference_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Textbook real SH with the Condon-Shortley phase (= the 3DGS basis), order m = -l..l."""
    x, y, z = dirs.unbind(-1)
    phi = torch.atan2(y, x)
    out = []
    for l in range(degree + 1):
        for m in range(-l, l + 1):
            am = abs(m)
            k = math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - am) / math.factorial(l + am))
            p = assoc_legendre_cs(l, am, z)
            if m == 0:
                out.append(k * p)
            elif m > 0:
                out.append(math.sqrt(2) * k * p * torch.cos(am * phi))
            else:
                out.append(math.sqrt(2) * k * p * torch.sin(am * phi))
    return torch.stack(out, -1)


def fibonacci_sphere(n: int) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    r = torch.sqrt(1 - z * z)
    phi = math.pi * (1 + 5**0.5) * i
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_basis_is_orthonormal_on_the_sphere(degree):
    d = fibonacci_sphere(200_000)
    y = sh_basis(d, degree)
    gram = (y.T @ y) * (4 * math.pi / d.shape[0])
    torch.testing.assert_close(gram, torch.eye(num_sh_coeffs(degree), dtype=torch.float64), atol=2e-4, rtol=0)


def test_basis_matches_closed_form_and_3dgs_constants():
    d = torch.randn(64, 3, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(sh_basis(d, 4), reference_basis(d, 4), atol=1e-12, rtol=0)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    y = sh_basis(up, 2)
    assert y[0] == pytest.approx(C0) and C0 == pytest.approx(1 / (2 * math.sqrt(math.pi)))
    assert y[2] == pytest.approx(math.sqrt(3 / (4 * math.pi)))  # Y_1^0 at the pole
    assert y[6] == pytest.approx(2 * 0.31539156525252005)  # 3DGS's C2[2] * (2z^2 - x^2 - y^2)
    x_axis = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    assert sh_basis(x_axis, 1)[3] == pytest.approx(-0.4886025119029199)  # 3DGS: -C1 * x


def test_eval_sh_degree_zero_and_clamp():
    coeffs = torch.randn(10, 25, 3)
    dirs = torch.nn.functional.normalize(torch.randn(10, 3), dim=-1)
    torch.testing.assert_close(eval_sh(coeffs, dirs, 0), (C0 * coeffs[:, 0] + 0.5).clamp_min(0))
    c = eval_sh(coeffs, dirs)
    assert (c >= 0).all()
    manual = (sh_basis(dirs, 4)[..., None] * coeffs).sum(-2) + 0.5
    torch.testing.assert_close(c, manual.clamp_min(0))


def test_i2dc_reproduces_pixels():
    rgb = torch.rand(4, 32, 32, 3)
    torch.testing.assert_close(sh_dc_to_rgb(rgb_to_sh_dc(rgb)), rgb, atol=1e-7, rtol=0)
    dirs = torch.nn.functional.normalize(torch.randn(4, 32, 32, 3), dim=-1)
    torch.testing.assert_close(eval_sh(rgb_to_sh_dc(rgb)[..., None, :], dirs), rgb, atol=1e-7, rtol=0)


def _rotations(n: int, dtype=torch.float64) -> torch.Tensor:
    return quat_to_matrix(torch.randn(n, 4, dtype=dtype))


def _unit(n: int, dtype=torch.float64) -> torch.Tensor:
    d = torch.randn(n, 3, dtype=dtype)
    return d / d.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
def test_rotated_coefficients_evaluate_the_turned_function(degree):
    """f_rotated(d) == f(R^T d) at random directions, for every band up to ``degree``, in float64."""
    rot = _rotations(5)  # [5, 3, 3]
    coeffs = torch.randn(5, num_sh_coeffs(degree), 3, dtype=torch.float64)
    rotated = sh_rotation_matrix(rot, degree) @ coeffs  # [5, K, 3]
    d = _unit(200)
    for i in range(5):
        turned = d @ rot[i]  # rows (R^T d)^T
        want = sh_basis(turned, degree) @ coeffs[i]  # f(R^T d), no clamping
        got = sh_basis(d, degree) @ rotated[i]
        torch.testing.assert_close(got, want, atol=1e-12, rtol=0)
    # the top band alone, turned, stays in its band
    top = torch.zeros_like(coeffs)
    top[:, degree**2 :] = coeffs[:, degree**2 :]
    lower = (sh_rotation_matrix(rot, degree) @ top)[:, : degree**2]
    assert lower.abs().max() == 0


def test_rotation_matrix_identity_composition_orthogonality_and_dc():
    eye = torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(
        sh_rotation_matrix(eye, 4), torch.eye(25, dtype=torch.float64), atol=1e-12, rtol=0
    )
    r1, r2 = _rotations(4), _rotations(4)
    m1, m2, m12 = (sh_rotation_matrix(r, 4) for r in (r1, r2, r1 @ r2))
    torch.testing.assert_close(m12, m1 @ m2, atol=1e-12, rtol=0)
    torch.testing.assert_close(
        m1 @ m1.mT, torch.eye(25, dtype=torch.float64).expand(4, 25, 25), atol=1e-12, rtol=0
    )
    torch.testing.assert_close(sh_rotation_matrix(r1.mT, 4), m1.mT, atol=1e-12, rtol=0)  # R^-1 -> M^-1
    assert torch.equal(m1[:, 0], torch.eye(25, dtype=torch.float64)[0].expand(4, 25))  # DC untouched, exactly
    assert sh_rotation_matrix(r1, 0).shape == (4, 1, 1)


def test_rotation_matrix_float32_and_batched_shapes():
    rot = _rotations(6).reshape(2, 3, 3, 3)
    m64 = sh_rotation_matrix(rot, 3)
    m32 = sh_rotation_matrix(rot.float(), 3)
    assert m32.dtype == torch.float32 and m32.shape == (2, 3, 16, 16)
    torch.testing.assert_close(m32.double(), m64, atol=1e-5, rtol=0)


def test_rotation_matrix_is_differentiable_in_the_rotation():
    q = torch.randn(2, 4, dtype=torch.float64, requires_grad=True)
    c = torch.randn(2, 9, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda q, c: sh_rotation_matrix(quat_to_matrix(q), 2) @ c, (q, c))


def test_caches_first_filled_in_inference_mode_still_train():
    """Evaluation (`aesplat test`, Lightning's validation) runs under inference mode; the SH tables it caches
    then must not be inference tensors, or the next training step's backward fails."""
    from aesplat.geometry import sh

    for cache in (sh._PLANS, sh._MATRICES, sh._FITS):
        cache.clear()
    dirs = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    coeffs = torch.randn(5, 16, 3)
    rotation = quat_to_matrix(torch.tensor([[0.9, 0.1, -0.2, 0.3]]))
    with torch.inference_mode():
        eval_sh(coeffs, dirs, 3)
        sh_rotation_matrix(rotation, 3)
    q = torch.tensor([[0.9, 0.1, -0.2, 0.3]], requires_grad=True)
    coeffs.requires_grad_(True)
    (eval_sh(coeffs, dirs, 3).sum() + sh_rotation_matrix(quat_to_matrix(q), 3).sum()).backward()
    assert torch.isfinite(q.grad).all() and torch.isfinite(coeffs.grad).all()
