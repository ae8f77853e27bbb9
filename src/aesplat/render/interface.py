"""The one rasterizer interface (docs/rendering.md) and the registry of backends.

``render`` checks inputs, picks the working precision (float32, or float64 when an input is float64; autocast
is off inside), resolves the background and the SH degree actually in use, and hands over to a backend:

    BACKENDS = {"torch": render_torch, "gsplat": render_gsplat}
    get_backend("auto", device, dtype)  # per call: gsplat for float32 CUDA tensors with gsplat, else torch
"""

from __future__ import annotations

import importlib.util
from dataclasses import fields
from typing import Protocol

import torch
from torch import Tensor

from aesplat.geometry import sh_degree_from_coeffs
from aesplat.types import Gaussians, RenderOutput

from .gsplat_backend import render_gsplat
from .projection import active_sh_degree
from .settings import RenderSettings, RenderStats
from .torch_backend import render_torch


class Backend(Protocol):
    """A rasterizer backend, as ``render`` calls it: the inputs checked and in the working dtype, ``sh_degree``
    the bands to evaluate; ``RenderSettings`` says which of its fields each backend reads."""

    def __call__(
        self,
        gaussians: Gaussians,
        extrinsics: Tensor,  # [B, V, 4, 4] camera-to-world
        intrinsics: Tensor,  # [B, V, 3, 3] normalised
        height: int,
        width: int,
        background: Tensor,  # [B, 3]
        sh_degree: int,
        settings: RenderSettings,
    ) -> tuple[RenderOutput, RenderStats]: ...


BACKENDS: dict[str, Backend] = {"torch": render_torch, "gsplat": render_gsplat}  # gsplat imported when it runs


def gsplat_available() -> bool:
    """True when CUDA is available and the gsplat package can be imported."""
    return torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None


def get_backend(
    name: str, device: torch.device | str, dtype: torch.dtype = torch.float32
) -> tuple[str, Backend]:
    """Resolve a backend name ("torch", "gsplat" or "auto") for tensors on ``device`` computed in ``dtype``.

    "auto" follows the tensors, call by call: gsplat for float32 CUDA tensors when gsplat imports, torch for
    everything else (CPU tensors, float64, a machine without gsplat). An explicit name is taken as given.
    Returns (resolved name, function).
    """
    if name == "auto":
        on_cuda = torch.device(device).type == "cuda"
        name = "gsplat" if on_cuda and dtype == torch.float32 and gsplat_available() else "torch"
    if name not in BACKENDS:
        raise ValueError(f"unknown render backend {name!r}; choose one of {sorted(BACKENDS) + ['auto']}")
    return name, BACKENDS[name]


def _check_cameras(
    gaussians: Gaussians, extrinsics: Tensor, intrinsics: Tensor, height: int, width: int
) -> None:
    b = gaussians.batch_size
    if extrinsics.ndim != 4 or extrinsics.shape[0] != b or extrinsics.shape[-2:] != (4, 4):
        raise ValueError(f"extrinsics must be [B={b}, V, 4, 4] camera-to-world, got {tuple(extrinsics.shape)}")
    if intrinsics.shape != (*extrinsics.shape[:2], 3, 3):
        raise ValueError(
            f"intrinsics must be [B, V, 3, 3] = {(*extrinsics.shape[:2], 3, 3)} (normalised), "
            f"got {tuple(intrinsics.shape)}"
        )
    if not (isinstance(height, int) and isinstance(width, int) and height > 0 and width > 0):
        raise ValueError(f"height and width must be positive ints, got {height!r} x {width!r}")


def _background(background: Tensor | None, b: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """None (black), [3] or [B, 3] -> [B, 3]."""
    if background is None:
        return torch.zeros(b, 3, dtype=dtype, device=device)
    background = torch.as_tensor(background, device=device).to(dtype)
    if background.shape == (3,):
        return background.expand(b, 3)
    if background.shape == (b, 3):
        return background
    raise ValueError(f"background must be None, [3] or [B={b}, 3], got {tuple(background.shape)}")


def render_with_stats(
    gaussians: Gaussians,
    extrinsics: Tensor,  # [B, V, 4, 4] camera-to-world
    intrinsics: Tensor,  # [B, V, 3, 3] normalised
    height: int,
    width: int,
    *,
    background: Tensor | None = None,  # [3] or [B, 3]; None = black
    sh_degree: int | None = None,
    backend: str = "auto",
    **options,
) -> tuple[RenderOutput, RenderStats]:
    """``render`` that also returns what was culled and which SH degree was evaluated."""
    known = {f.name for f in fields(RenderSettings)}
    unknown = sorted(set(options) - known)
    if unknown:
        raise TypeError(f"unknown render option(s) {unknown}; known options: {sorted(known)}")
    settings = RenderSettings(**options)
    _check_cameras(gaussians, extrinsics, intrinsics, height, width)

    available = sh_degree_from_coeffs(gaussians.sh.shape[2])
    requested = available if sh_degree is None else int(sh_degree)
    if not 0 <= requested <= available:
        raise ValueError(f"sh_degree={sh_degree} but the Gaussians carry SH up to degree {available}")
    # Skipping silent bands is exact for the image; their gradient is not zero, so keep them when needed.
    needs_grad = torch.is_grad_enabled() and gaussians.sh.requires_grad
    active = requested if needs_grad else active_sh_degree(gaussians.sh.detach(), requested, settings.sh_tol)

    tensors = [gaussians.means, extrinsics, intrinsics] + ([] if background is None else [background])
    dtype = torch.float64 if any(torch.as_tensor(t).dtype == torch.float64 for t in tensors) else torch.float32
    device = gaussians.means.device
    name, fn = get_backend(backend, device, dtype)
    with torch.autocast(device_type=device.type, enabled=False):
        g = gaussians.to(dtype=dtype)
        bg = _background(background, g.batch_size, dtype, device)
        out, stats = fn(g, extrinsics.to(dtype), intrinsics.to(dtype), height, width, bg, active, settings)
    return out, _with_degrees(stats, name, requested, active)


def _with_degrees(stats: RenderStats, name: str, requested: int, active: int) -> RenderStats:
    values = {f.name: getattr(stats, f.name) for f in fields(stats)}
    values.update(backend=name, sh_degree_requested=requested, sh_degree_active=active)
    return RenderStats(**values)


def render(
    gaussians: Gaussians,
    extrinsics: Tensor,  # [B, V, 4, 4] camera-to-world
    intrinsics: Tensor,  # [B, V, 3, 3] normalised
    height: int,
    width: int,
    *,
    background: Tensor | None = None,  # [3] or [B, 3]; None = black
    sh_degree: int | None = None,
    backend: str = "auto",
    **options,
) -> RenderOutput:
    """Render Gaussians into V cameras per batch element (gsplat "classic" semantics, docs/rendering.md).

    Returns colour [B, V, 3, H, W] over the background, expected z-depth [B, V, 1, H, W] (0 where nothing
    is seen) and alpha [B, V, 1, H, W]. Differentiable with respect to the Gaussians, both camera matrices
    and the background. Computes in float32 (float64 when given float64), whatever the autocast state.
    ``sh_degree`` caps the SH bands used (default: all the Gaussians carry). ``options`` are the fields of
    ``RenderSettings`` (which names the backends that read each). ``backend``
    "auto" is resolved on every call from the inputs (see ``get_backend``): gsplat only for float32 CUDA
    tensors with gsplat installed.
    """
    out, _ = render_with_stats(
        gaussians, extrinsics, intrinsics, height, width,
        background=background, sh_degree=sh_degree, backend=backend, **options,
    )  # fmt: skip
    return out
