"""Gaussians to and from a PLY file in the reference 3DGS layout (Kerbl et al. 2023), readable by common 3DGS
viewers.

One vertex per Gaussian, binary little-endian float32 properties in this order:

    x y z                      centre (the view-0 camera frame, OpenCV axes)
    nx ny nz                   zeros (the reference writes them; viewers expect them)
    f_dc_0 f_dc_1 f_dc_2       DC SH coefficient per colour channel
    f_rest_0 .. f_rest_{3(K-1)-1}
                               higher-order SH, channel-major: red's K-1 coefficients, then green's, then
                               blue's (the reference transposes [N, K-1, 3] to [N, 3, K-1], then flattens)
    opacity                    logit of the opacity (the reference applies a sigmoid when loading)
    scale_0 scale_1 scale_2    log of the standard deviations (the reference applies exp)
    rot_0 .. rot_3             quaternion (w, x, y, z), normalised here

The SH basis and the +0.5 colour offset of this project are the reference's, so coefficients are copied as is.
:func:`read_ply` reads any PLY of this layout (other properties, such as the normals, may be missing or extra).
"""

from __future__ import annotations

import re
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from ..errors import MissingFileError, UserError
from ..geometry import MAX_SH_DEGREE, num_sh_coeffs
from ..types import Gaussians
from .prune import drop_non_finite

# The reference 3DGS code and most viewers stop at SH degree 3 (45 f_rest properties).
VIEWER_MAX_SH_DEGREE = 3
_LOGIT_EPS = 1e-6  # keeps logit(opacity) and log(scale) finite for opacity 0/1 and zero scales


def ply_property_names(sh_degree: int) -> list[str]:
    """Vertex property names, in file order, for SH degree ``sh_degree``."""
    num_rest = 3 * (num_sh_coeffs(sh_degree) - 1)
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(num_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def gaussians_to_ply_array(gaussians: Gaussians, index: int = 0, sh_degree: int | None = None) -> np.ndarray:
    """The vertex table [N, P] (float32) of scene ``index`` of a batch, columns as :func:`ply_property_names`.

    sh_degree: write only the bands up to this degree (default: all the Gaussians carry).
    """
    degree = gaussians.sh_degree if sh_degree is None else sh_degree
    if not 0 <= degree <= gaussians.sh_degree:
        raise ValueError(f"cannot write SH degree {degree}: the Gaussians carry degree {gaussians.sh_degree}")
    if not 0 <= index < gaussians.batch_size:
        raise IndexError(f"scene index {index} out of range for a batch of {gaussians.batch_size}")
    g = gaussians.detach().to("cpu", torch.float32)
    means = g.means[index]  # [N, 3]
    sh = g.sh[index, :, : num_sh_coeffs(degree)]  # [N, K, 3]
    n = means.shape[0]
    f_dc = sh[:, 0]  # [N, 3]
    f_rest = sh[:, 1:].transpose(1, 2).reshape(n, -1)  # [N, 3 * (K - 1)], channel-major
    opacity = g.opacities[index].clamp(_LOGIT_EPS, 1.0 - _LOGIT_EPS)
    logit = torch.log(opacity) - torch.log1p(-opacity)  # [N]
    log_scales = torch.log(g.scales[index].clamp_min(_LOGIT_EPS))  # [N, 3]
    quats = g.quats[index]
    norm = quats.norm(dim=-1, keepdim=True)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand_as(quats)
    quats = torch.where(norm > 1e-12, quats / norm.clamp_min(1e-12), identity)  # [N, 4]
    table = torch.cat([means, torch.zeros_like(means), f_dc, f_rest, logit[:, None], log_scales, quats], dim=1)
    return table.numpy().astype(np.float32, copy=False)


def write_ply(path: str | Path, gaussians: Gaussians, index: int = 0, sh_degree: int | None = None) -> Path:
    """Write scene ``index`` of ``gaussians`` to ``path`` as a binary 3DGS PLY; returns the path.

    sh_degree: bands to keep (default: all). Use ``VIEWER_MAX_SH_DEGREE`` (3) for viewers that stop at 3.
    """
    degree = gaussians.sh_degree if sh_degree is None else sh_degree
    table = gaussians_to_ply_array(gaussians, index, degree)
    names = ply_property_names(degree)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {table.shape[0]}"]
    header += [f"property float {name}" for name in names] + ["end_header"]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(table.astype("<f4", copy=False).tobytes())
    return path


_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}


def _vertex_count(path: Path, header: list[str]) -> int:
    """The count of the header's one element, ``element vertex COUNT``; a UserError for any other element, or
    an element line without a kind or a whole count of 0 or more."""
    lines = [line for line in header if line.split()[:1] == ["element"]]
    for line in lines:
        fields = line.split()
        if len(fields) != 3 or not re.fullmatch(r"[0-9]+", fields[2]):
            raise UserError(f"{str(path)!r}: header line '{line.strip()}' is not 'element NAME COUNT' with a "
                            "whole count of 0 or more; the file is damaged or not a 3DGS PLY")  # fmt: skip
    kinds = [line.split()[1] for line in lines]
    if kinds != ["vertex"]:
        raise UserError(f"{str(path)!r} holds elements {kinds}; a 3DGS PLY holds vertices only")
    return int(lines[0].split()[2])


def _vertex_dtype(path: Path, header: list[str]) -> np.dtype:
    """The vertex record of the header's ``property TYPE NAME`` lines; a UserError for a line without a name,
    a type other than float or double, or a name given twice."""
    props = [line.split() for line in header if line.split()[:1] == ["property"]]
    if odd := next((p for p in props if len(p) != 3 and p[1:2] != ["list"]), None):
        raise UserError(f"{str(path)!r}: header line '{' '.join(odd)}' is not 'property TYPE NAME'; the file "
                        "is damaged or not a 3DGS PLY")  # fmt: skip
    if odd := next((p for p in props if p[1] not in _PLY_TYPES), None):
        kind = " ".join(odd[1:])
        raise UserError(f"{str(path)!r} has property '{kind}'; a 3DGS PLY has float properties only")
    if twice := next((name for name, n in Counter(p[2] for p in props).items() if n > 1), None):
        raise UserError(f"{str(path)!r} has property {twice} twice; the file is damaged or not a 3DGS PLY")
    return np.dtype([(p[2], _PLY_TYPES[p[1]]) for p in props])


def read_ply(path: str | Path) -> Gaussians:
    """A binary little-endian 3DGS PLY -> Gaussians [1, N] (sigmoid of the opacity, exp of the scales).

    Needs the vertex properties ``x y z f_dc_0..2 opacity scale_0..2 rot_0..3`` and ``f_rest_*`` for SH degree
    0..4, as float or double. Anything else, a malformed header or data shorter than the header says is refused
    with a :class:`UserError` naming what is wrong. Gaussians that hold NaN or Inf (as stored, or once loaded:
    the exp of a huge log-scale) are dropped, with one line on stderr saying how many; none may be left.
    """
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"{str(path)!r} does not exist (or is not a file)")
    with open(path, "rb") as f:
        data = f.read()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise UserError(f"{str(path)!r} is not a PLY file (no 'ply' ... 'end_header' header)")
    header = [line for line in data[:end].decode("ascii", errors="replace").splitlines() if line.strip()]
    body = data[end + len(b"end_header\n") :]
    if "format binary_little_endian 1.0" not in header:
        fmt = next((line for line in header if line.startswith("format")), "no format line")
        raise UserError(f"{str(path)!r} is a PLY in '{fmt}'; a 3DGS PLY is binary_little_endian")
    count = _vertex_count(path, header)
    dtype = _vertex_dtype(path, header)
    names = set(dtype.names or ())
    rest = sum(name.startswith("f_rest_") for name in names)
    degree = next((d for d in range(MAX_SH_DEGREE + 1) if 3 * (num_sh_coeffs(d) - 1) == rest), None)
    needed = [n for n in ply_property_names(0) if n not in ("nx", "ny", "nz")]
    missing = [n for n in needed if n not in names]
    if missing or degree is None:
        what = f"no {', '.join(missing[:4])}" if missing else f"{rest} f_rest properties, not 3 ((L+1)^2 - 1)"
        raise UserError(
            f"{str(path)!r} is not a 3DGS PLY of the reference layout ({what}); give the gaussians.ply of "
            "`aesplat predict` or another 3DGS PLY"
        )
    if len(body) < count * dtype.itemsize:
        raise UserError(f"{str(path)!r} is truncated: {count} vertices need {count * dtype.itemsize} bytes")
    table = np.frombuffer(body, dtype=dtype, count=count)

    def cols(*keys: str) -> torch.Tensor:  # [N, len(keys)] float32; a value not finite in float32 is NaN
        with np.errstate(over="ignore", invalid="ignore"):  # a double beyond float32's range: Inf, then NaN
            values = np.stack([table[k].astype(np.float32) for k in keys], axis=-1)
        return torch.from_numpy(np.where(np.isfinite(values), values, np.float32(np.nan)))

    k = num_sh_coeffs(degree)
    dc = cols("f_dc_0", "f_dc_1", "f_dc_2")  # [N, 3]
    f_rest = cols(*(f"f_rest_{i}" for i in range(3 * (k - 1)))) if k > 1 else torch.zeros(count, 0)
    f_rest = f_rest.reshape(count, 3, k - 1)  # channel-major in the file
    sh = torch.cat([dc[:, None], f_rest.transpose(1, 2)], dim=1)  # [N, K, 3]
    gaussians, dropped = drop_non_finite(Gaussians(
        means=cols("x", "y", "z")[None],
        quats=cols("rot_0", "rot_1", "rot_2", "rot_3")[None],
        scales=cols("scale_0", "scale_1", "scale_2").exp()[None],
        opacities=torch.sigmoid(cols("opacity")[:, 0])[None],  # NaN stays NaN, where +-Inf would be 1 or 0
        sh=sh[None],
    ))  # fmt: skip
    if dropped:
        print(f"aesplat: {str(path)!r}: dropped {dropped:,} of {count:,} Gaussians holding NaN or Inf; "
              f"{count - dropped:,} left", file=sys.stderr)  # fmt: skip
    return gaussians
