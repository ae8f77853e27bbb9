"""Real spherical harmonics up to degree 4, in the reference-3DGS / gsplat basis order and constants.

Within degree l the order is m = -l .. l. Each basis function is the textbook real SH times (-1)^m,
which is what 3DGS and gsplat evaluate (e.g. degree 1 is -C1 y, C1 z, -C1 x).
colour = max(sum_k c_k Y_k(d) + 0.5, 0) with d the unit direction from the camera centre to the Gaussian.
"""

from __future__ import annotations

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
C4 = (
    2.5033429417967046,
    -1.7701307697799304,
    0.9461746957575601,
    -0.6690465435572892,
    0.10578554691520431,
    -0.6690465435572892,
    0.47308734787878004,
    -1.7701307697799304,
    0.6258357354491761,
)
MAX_SH_DEGREE = 4


def num_sh_coeffs(degree: int) -> int:
    """Number of coefficients K = (L + 1)^2 for SH degree L."""
    return (degree + 1) ** 2


def sh_degree_from_coeffs(k: int) -> int:
    """Inverse of :func:`num_sh_coeffs`; raises for a K that is not a square."""
    degree = round(k**0.5) - 1
    if num_sh_coeffs(degree) != k or not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"{k} SH coefficients is not (L+1)^2 for an SH degree L in 0..{MAX_SH_DEGREE}")
    return degree


# Every basis function as a polynomial in the direction's x, y, z: terms (coefficient, (i, j, k)) of
# coefficient * x^i y^j z^k, expanded from the usual product forms (degree 2, m = 0 is C (2zz - xx - yy)).
# Band l only uses monomials of degree <= l. Evaluating all monomials first and the basis as one matrix
# product needs a dozen tensor ops instead of about seventy.
_TERMS: tuple[tuple[tuple[float, tuple[int, int, int]], ...], ...] = (
    ((C0, (0, 0, 0)),),
    ((-C1, (0, 1, 0)),),
    ((C1, (0, 0, 1)),),
    ((-C1, (1, 0, 0)),),
    ((C2[0], (1, 1, 0)),),
    ((C2[1], (0, 1, 1)),),
    ((2.0 * C2[2], (0, 0, 2)), (-C2[2], (2, 0, 0)), (-C2[2], (0, 2, 0))),
    ((C2[3], (1, 0, 1)),),
    ((C2[4], (2, 0, 0)), (-C2[4], (0, 2, 0))),
    ((3.0 * C3[0], (2, 1, 0)), (-C3[0], (0, 3, 0))),
    ((C3[1], (1, 1, 1)),),
    ((4.0 * C3[2], (0, 1, 2)), (-C3[2], (2, 1, 0)), (-C3[2], (0, 3, 0))),
    ((2.0 * C3[3], (0, 0, 3)), (-3.0 * C3[3], (2, 0, 1)), (-3.0 * C3[3], (0, 2, 1))),
    ((4.0 * C3[4], (1, 0, 2)), (-C3[4], (3, 0, 0)), (-C3[4], (1, 2, 0))),
    ((C3[5], (2, 0, 1)), (-C3[5], (0, 2, 1))),
    ((C3[6], (3, 0, 0)), (-3.0 * C3[6], (1, 2, 0))),
    ((C4[0], (3, 1, 0)), (-C4[0], (1, 3, 0))),
    ((3.0 * C4[1], (2, 1, 1)), (-C4[1], (0, 3, 1))),
    ((7.0 * C4[2], (1, 1, 2)), (-C4[2], (1, 1, 0))),
    ((7.0 * C4[3], (0, 1, 3)), (-3.0 * C4[3], (0, 1, 1))),
    ((35.0 * C4[4], (0, 0, 4)), (-30.0 * C4[4], (0, 0, 2)), (3.0 * C4[4], (0, 0, 0))),
    ((7.0 * C4[5], (1, 0, 3)), (-3.0 * C4[5], (1, 0, 1))),
    ((7.0 * C4[6], (2, 0, 2)), (-C4[6], (2, 0, 0)), (-7.0 * C4[6], (0, 2, 2)), (C4[6], (0, 2, 0))),
    ((C4[7], (3, 0, 1)), (-3.0 * C4[7], (1, 2, 1))),
    ((C4[8], (4, 0, 0)), (-6.0 * C4[8], (2, 2, 0)), (C4[8], (0, 4, 0))),
)


def _monomial_exponents(degree: int) -> list[tuple[int, int, int]]:
    """Exponents (i, j, k) of all monomials x^i y^j z^k of total degree <= ``degree``, by degree."""
    return [
        (i, j, d - i - j) for d in range(degree + 1) for i in range(d, -1, -1) for j in range(d - i, -1, -1)
    ]


_PLANS: dict[tuple[int, torch.device], list[tuple[Tensor, Tensor]]] = {}
_MATRICES: dict[tuple[int, torch.dtype, torch.device], Tensor] = {}


def num_monomials(degree: int) -> int:
    """Number of monomials in x, y, z of total degree <= ``degree``."""
    return (degree + 1) * (degree + 2) * (degree + 3) // 6


def _monomial_plan(degree: int, device: torch.device) -> list[tuple[Tensor, Tensor]]:
    """For each degree d in 2..``degree``: the monomials of degree exactly d, each as (position of a monomial
    of degree d - 1 among those of degree exactly d - 1) times (x, y or z: 0, 1 or 2)."""
    key = (degree, device)
    if key not in _PLANS:
        _PLANS[key] = _make_plan(degree, device)
    return _PLANS[key]


@torch.inference_mode(False)  # cached: never an inference tensor (see _fit_tensors)
def _make_plan(degree: int, device: torch.device) -> list[tuple[Tensor, Tensor]]:
    plan = []
    for d in range(2, degree + 1):
        below = _monomial_exponents(d - 1)[num_monomials(d - 2) :]
        parents, axes = [], []
        for e in _monomial_exponents(d)[num_monomials(d - 1) :]:
            axis = next(q for q in range(3) if e[q] > 0)
            parents.append(below.index(tuple(p - (q == axis) for q, p in enumerate(e))))
            axes.append(axis)
        plan.append((torch.tensor(parents, device=device), torch.tensor(axes, device=device)))
    return plan


def _basis_matrix(degree: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """[monomials, K] matrix taking the monomial values to the basis values."""
    key = (degree, dtype, device)
    if key not in _MATRICES:
        with torch.inference_mode(False):  # cached: never an inference tensor (see _fit_tensors)
            index = {e: n for n, e in enumerate(_monomial_exponents(degree))}
            mat = torch.zeros(len(index), num_sh_coeffs(degree), dtype=torch.float64)
            for k, terms in enumerate(_TERMS[: num_sh_coeffs(degree)]):
                for coefficient, exponent in terms:
                    mat[index[exponent], k] += coefficient
            _MATRICES[key] = mat.to(dtype=dtype, device=device)
    return _MATRICES[key]


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """Basis values [..., (degree+1)^2] at unit directions [..., 3]."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    # Monomials as rows [monomials, n] (each row contiguous, gathered by index_select), then one matrix
    # product whose transposed operand gives the basis back as [n, K] without a copy.
    xyz = dirs.reshape(-1, 3).t()
    levels = [torch.ones_like(xyz[:1]), xyz][: degree + 1]  # monomials of degree exactly 0, 1, ...
    for parents, axes in _monomial_plan(degree, dirs.device):
        levels.append(levels[-1].index_select(0, parents) * xyz.index_select(0, axes))
    basis = torch.cat(levels, 0).t() @ _basis_matrix(degree, dirs.dtype, dirs.device)
    return basis.reshape(*dirs.shape[:-1], basis.shape[-1])


def eval_sh(coeffs: Tensor, dirs: Tensor, degree: int | None = None) -> Tensor:
    """Colour from SH coefficients [..., K, 3] along unit directions [..., 3] -> [..., 3].

    Uses bands 0..degree (default: all of ``coeffs``); degree 0 never evaluates the direction-dependent
    basis. Returns max(sum + 0.5, 0) as 3DGS does.
    """
    if degree is None:
        degree = sh_degree_from_coeffs(coeffs.shape[-2])
    if degree == 0:
        return (C0 * coeffs[..., 0, :] + 0.5).clamp_min(0.0)
    basis = sh_basis(dirs, degree)  # [..., K']
    k = num_sh_coeffs(degree)
    # Broadcast multiply-and-sum: a batched [1, K'] @ [K', 3] matmul is faster forward but its backward
    # (batched outer products) is ten times slower on the CPU.
    rgb = (basis[..., None] * coeffs[..., :k, :]).sum(-2)
    return (rgb + 0.5).clamp_min(0.0)


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:
    """I2DC: pixel colour [..., 3] in [0, 1] -> zeroth-order SH coefficient (rgb - 0.5) / C0."""
    return (rgb - 0.5) / C0


def sh_dc_to_rgb(dc: Tensor) -> Tensor:
    """Inverse of :func:`rgb_to_sh_dc`: C0 * dc + 0.5 (no clamping)."""
    return dc * C0 + 0.5


# SH rotation. Rotating a function on the sphere maps each band onto itself, so the rotated coefficients are
# fixed by the rotated function's values at any set of directions on which each band's basis has full rank:
# a least-squares fit on such a set is exact (not an approximation). 64 Fibonacci directions give a basis
# matrix of condition number 1.09 up to degree 4.
_FIT_DIRECTIONS = 64
_FITS: dict[tuple[int, torch.dtype, torch.device], tuple[Tensor, Tensor, Tensor]] = {}


def _rotation_fit(degree: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """Fixed directions [N, 3], the pseudo-inverse [K-1, N] of their basis values in bands 1..``degree``,
    and the block-diagonal mask [K-1, K-1] of those bands (computed in float64, cached)."""
    key = (degree, dtype, device)
    if key not in _FITS:
        _FITS[key] = _fit_tensors(degree, dtype, device)
    return _FITS[key]


# Built outside inference mode: a cache filled during `aesplat test` or Lightning's validation would otherwise
# hold inference tensors, which autograd refuses in any later training step.
@torch.inference_mode(False)
def _fit_tensors(degree: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    i = torch.arange(_FIT_DIRECTIONS, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / _FIT_DIRECTIONS
    r, phi = torch.sqrt(1.0 - z * z), torch.pi * (1.0 + 5.0**0.5) * i
    dirs = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)
    pinv = torch.linalg.pinv(sh_basis(dirs, degree)[:, 1:])
    band = torch.cat([torch.full((2 * l + 1,), l) for l in range(1, degree + 1)])
    mask = (band[:, None] == band[None, :]).to(torch.float64)
    return tuple(t.to(dtype=dtype, device=device) for t in (dirs, pinv, mask))


def sh_rotation_matrix(rotation: Tensor, degree: int) -> Tensor:
    """The matrix M [..., K, K] that rotates SH coefficients of degree ``degree`` by ``rotation`` [..., 3, 3].

    If c [K] are the coefficients of f(d) = sum_k c_k Y_k(d), then M @ c are those of d -> f(R^T d): the
    function turned by R. A colour defined in a camera's frame (directions d_cam) becomes the same colour in
    the world frame with R = the camera-to-world rotation, since d_cam = R^T d_world. M is block diagonal
    (one orthogonal block per band, the DC entry exactly 1), M(R1 R2) = M(R1) M(R2), and it is differentiable
    in R (a polynomial of R's entries). Computed as the least-squares fit of the rotated function's values at
    fixed directions; float32 or float64 as ``rotation``.
    """
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    if rotation.shape[-2:] != (3, 3):
        raise ValueError(f"rotation must be [..., 3, 3], got shape {tuple(rotation.shape)}")
    eye = torch.eye(num_sh_coeffs(degree), dtype=rotation.dtype, device=rotation.device)
    if degree == 0:
        return eye.expand(*rotation.shape[:-2], 1, 1)
    dirs, pinv, mask = _rotation_fit(degree, rotation.dtype, rotation.device)
    values = sh_basis(dirs @ rotation, degree)[..., 1:]  # [..., N, K-1]: basis at R^T d (rows d^T R)
    higher = (pinv @ values) * mask  # [..., K-1, K-1]; the mask zeroes rounding noise between bands
    dc = torch.zeros_like(eye)
    dc[0, 0] = 1.0
    return torch.nn.functional.pad(higher, (1, 0, 1, 0)) + dc
