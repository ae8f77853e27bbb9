"""Image and pose metrics for validation and test (docs/evaluation.md).

Image metrics are per image (data range 1) so that PSNR is averaged over images, not computed on a pooled
MSE. Pose errors compare predicted and ground-truth poses *relative to context view 0*, so they are
independent of the ground truth's world frame; the translation error is an angle because a pose-free model
recovers translation only up to scale.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure

from aesplat.geometry import matrix_to_quat, relative_to_first, safe_norm

OVERLAP_BUCKETS = {"small": (0.0, 0.3), "medium": (0.3, 0.55), "large": (0.55, math.inf)}


def psnr(pred: Tensor, target: Tensor) -> Tensor:
    """Per-image PSNR in dB: pred, target [N, 3, H, W] in [0, 1] -> [N]."""
    return peak_signal_noise_ratio(
        pred.float().clamp(0, 1), target.float(), data_range=1.0, reduction="none", dim=(1, 2, 3)
    )


def masked_psnr(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """Per-image PSNR in dB over the masked pixels only (all three channels of each):
    pred, target [N, 3, H, W] in [0, 1], mask [N, 1, H, W] bool -> [N].

    An image with an empty mask has no such PSNR: NaN, never a made-up number (``nanmean`` or the summary's
    finite mean skips it). A perfect match on a non-empty mask gives +inf, like ``psnr``.
    """
    weight = mask.to(pred.dtype).expand_as(pred)
    count = weight.flatten(1).sum(-1)  # [N] masked values
    sq = (pred.float().clamp(0, 1) - target.float()) ** 2
    mse = (sq * weight).flatten(1).sum(-1) / count.clamp_min(1.0)
    value = -10.0 * torch.log10(mse)
    return torch.where(count > 0, value, torch.full_like(value, math.nan))


def highlight_psnr(pred: Tensor, target: Tensor, highlight: Tensor) -> dict[str, Tensor]:
    """PSNR on highlight pixels and on the rest, and the highlight share, per image:
    pred, target [N, 3, H, W], highlight [N, 1, H, W] bool -> {"psnr_highlight", "psnr_rest",
    "highlight_fraction"}, each [N] (NaN where the pixel set is empty)."""
    return {
        "psnr_highlight": masked_psnr(pred, target, highlight),
        "psnr_rest": masked_psnr(pred, target, ~highlight),
        "highlight_fraction": highlight.float().flatten(1).mean(-1),
    }


def ssim(pred: Tensor, target: Tensor) -> Tensor:
    """Per-image SSIM (Gaussian window 11, σ 1.5): pred, target [N, 3, H, W] in [0, 1] -> [N]."""
    return structural_similarity_index_measure(
        pred.float().clamp(0, 1), target.float(), data_range=1.0, reduction="none"
    ).reshape(pred.shape[0])


def rotation_angle_deg(rel_pred: Tensor, rel_gt: Tensor) -> Tensor:
    """Angle of the rotation taking one pose's rotation to the other's: [..., 4, 4] x2 -> [...] in degrees."""
    delta = rel_pred[..., :3, :3].transpose(-1, -2) @ rel_gt[..., :3, :3]
    q = matrix_to_quat(delta)  # w >= 0, so the angle lies in [0, 180]
    # safe_norm (eps 0): a zero vector part (equal rotations) has norm 0 with a finite gradient; then w = 1.
    return torch.rad2deg(2.0 * torch.atan2(safe_norm(q[..., 1:], eps=0.0), q[..., 0]))


def translation_angle_deg(rel_pred: Tensor, rel_gt: Tensor) -> Tensor:
    """Angle between the translation directions of two poses: [..., 4, 4] x2 -> [...] in degrees."""
    a, b = rel_pred[..., :3, 3], rel_gt[..., :3, 3]
    cross = safe_norm(torch.linalg.cross(a, b, dim=-1), eps=0.0)
    dot = (a * b).sum(-1)
    # A zero translation has no direction: angle 0, and atan2(0, 0) is kept out of the backward.
    ok = (cross > 0) | (dot != 0)
    angle = torch.atan2(torch.where(ok, cross, 0.0), torch.where(ok, dot, 1.0))
    return torch.rad2deg(angle)


def relative_pose_errors(pred_extrinsics: Tensor, gt_extrinsics: Tensor) -> tuple[Tensor, Tensor]:
    """Rotation and translation angular errors of views 1..V-1 relative to view 0.

    pred_extrinsics, gt_extrinsics: [B, V, 4, 4] camera-to-world (any world frame for the ground truth)
    -> rotation error [B, V-1], translation error [B, V-1], in degrees.
    """
    rel_pred = relative_to_first(pred_extrinsics.float())[:, 1:]
    rel_gt = relative_to_first(gt_extrinsics.float())[:, 1:]
    return rotation_angle_deg(rel_pred, rel_gt), translation_angle_deg(rel_pred, rel_gt)


def overlap_bucket(overlap: float | None, buckets: dict[str, tuple[float, float]] = OVERLAP_BUCKETS) -> str:
    """Name of the overlap bucket [low, high) holding ``overlap``; "unknown" for None / NaN / outside all."""
    if overlap is None or not math.isfinite(overlap):
        return "unknown"
    for name, (low, high) in buckets.items():
        if low <= overlap < high:
            return name
    return "unknown"
