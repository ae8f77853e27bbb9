"""Fewer Gaussians: keep the most opaque ones, drop the nearly transparent ones, or drop those that hold NaN or
Inf (which no exporter can write and no renderer can draw)."""

from __future__ import annotations

import torch
from torch import Tensor

from ..types import Gaussians


def keep_most_opaque(gaussians: Gaussians, fraction: float) -> Gaussians:
    """Keep the most opaque ``fraction`` (in (0, 1]) of each scene's Gaussians (same count per scene).

    Returns Gaussians [B, k] with k = round(fraction * N), at least 1.
    """
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"fraction must be in (0, 1], got {fraction}")
    n = gaussians.num_gaussians
    k = max(1, round(fraction * n))
    if k == n:
        return gaussians
    idx = gaussians.opacities.topk(k, dim=1, sorted=False).indices  # [B, k]

    def take(t: Tensor) -> Tensor:  # [B, N, ...] -> [B, k, ...]
        return torch.gather(t, 1, idx.view(*idx.shape, *([1] * (t.ndim - 2))).expand(*idx.shape, *t.shape[2:]))

    return gaussians.apply(take)


def drop_transparent(gaussians: Gaussians, min_opacity: float) -> Gaussians:
    """Drop Gaussians with opacity below ``min_opacity`` (one scene, B = 1: counts differ between scenes).

    At least one Gaussian (the most opaque) is always kept, so the result is a valid container. A threshold
    of 0 or below keeps every Gaussian: they come back as given.
    """
    if gaussians.batch_size != 1:
        raise ValueError(
            f"drop_transparent works on one scene at a time, got a batch of {gaussians.batch_size}"
        )
    if min_opacity <= 0:
        return gaussians
    keep = gaussians.opacities[0] >= min_opacity  # [N]
    if not keep.any():
        keep = torch.zeros_like(keep)
        keep[gaussians.opacities[0].argmax()] = True
    return gaussians.apply(lambda t: t[:, keep])


def finite_rows(gaussians: Gaussians) -> Tensor:
    """[B, N] True where every parameter of the Gaussian (centre, rotation, scale, opacity, SH) is finite."""
    fields = (gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, gaussians.sh)
    finite = [torch.isfinite(t) for t in fields]  # [B, N, ...] each
    return torch.stack([f.flatten(2).all(dim=-1) if f.ndim > 2 else f for f in finite]).all(dim=0)


def drop_non_finite(gaussians: Gaussians) -> tuple[Gaussians, int]:
    """The Gaussians of one scene (B = 1) without those holding NaN or Inf in any parameter, and how many were
    dropped. May leave none: a caller that needs some says so. All finite: they come back as given."""
    if gaussians.batch_size != 1:
        raise ValueError(f"drop_non_finite works on one scene at a time, got a batch of {gaussians.batch_size}")
    keep = finite_rows(gaussians)[0]  # [N]
    dropped = int((~keep).sum())
    return (gaussians.apply(lambda t: t[:, keep]) if dropped else gaussians), dropped
