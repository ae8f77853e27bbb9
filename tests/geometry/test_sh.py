import math

import pytest
import torch

from aesplat.geometry import C0, eval_sh, num_sh_coeffs, rgb_to_sh_dc, sh_basis, sh_dc_to_rgb


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
