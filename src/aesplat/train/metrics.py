"""Image and pose metrics for validation and test (docs/evaluation.md).

Image metrics are per image (data range 1) so that PSNR is averaged over images, not computed on a pooled
MSE. Pose errors compare predicted and ground-truth poses *relative to context view 0*, so they are
independent of the ground truth's world frame; the translation error is an angle because a pose-free model
recovers translation only up to scale. The pose AUC (``pose_auc``) follows the pose-free literature: errors
of the context views alone, the translation angle folded to [0, 90] and the pose error the larger of the two.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure

from aesplat.geometry import matrix_to_quat, relative_to_first, safe_norm

OVERLAP_BUCKETS = {"small": (0.0, 0.3), "medium": (0.3, 0.55), "large": (0.55, math.inf)}
AUC_THRESHOLDS_DEG = (5, 10, 20)


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


def folded_translation_angle_deg(rel_pred: Tensor, rel_gt: Tensor) -> Tensor:
    """Translation-direction error with the sign of the direction ignored, min(e, 180 - e) in [0, 90], as for
    an essential matrix: [..., 4, 4] x2 -> [...] in degrees. A zero translation has no direction: 90, the
    worst error (``translation_angle_deg`` gives it 0)."""
    angle = translation_angle_deg(rel_pred, rel_gt)
    # A NaN translation is not "still": its NaN error stays NaN.
    still = (rel_pred[..., :3, 3].norm(dim=-1) == 0) | (rel_gt[..., :3, 3].norm(dim=-1) == 0)
    return torch.where(still, torch.full_like(angle, 90.0), torch.minimum(angle, 180.0 - angle))


def context_pose_errors(pred_context: Tensor, gt_context: Tensor) -> dict[str, Tensor]:
    """The pose-AUC errors of the context views, relative to context view 0, in degrees, each [B]:

    - ``*_last_deg``: the last context view alone (NAS3R's choice);
    - ``*_ctx_deg``: the mean over context views 1..V-1 (SPFSplatV2's; equal to the former for two views).

    ``rot`` is the angle of R_pred^T R_gt, ``trans`` the folded direction error
    (``folded_translation_angle_deg``), ``pose`` the larger of the two (of the means, for ``ctx``).
    pred_context, gt_context: [B, V, 4, 4] camera-to-world, V >= 2.
    """
    rel_pred = relative_to_first(pred_context.float())[:, 1:]
    rel_gt = relative_to_first(gt_context.float())[:, 1:]
    rot = rotation_angle_deg(rel_pred, rel_gt)  # [B, V-1]
    trans = folded_translation_angle_deg(rel_pred, rel_gt)
    errors = {}
    for variant, (r, t) in {"last": (rot[:, -1], trans[:, -1]), "ctx": (rot.mean(1), trans.mean(1))}.items():
        errors[f"rot_err_{variant}_deg"], errors[f"trans_err_{variant}_deg"] = r, t
        errors[f"pose_err_{variant}_deg"] = torch.maximum(r, t)  # NaN stays NaN
    return errors


def pose_auc(
    errors_deg: Sequence[float] | np.ndarray, thresholds: Sequence[float] = AUC_THRESHOLDS_DEG
) -> list[float]:
    """Area under the recall-error curve up to each threshold, divided by it (SuperGlue's pose AUC).

    The curve runs through (0, 0) and (e_i, i / n) for the errors sorted ascending, linear between them; at
    a threshold it stays at the recall of the last error below it (an error equal to the threshold does not
    count). ``errors_deg``: n >= 1 finite errors in degrees, thresholds > 0 -> one AUC in [0, 1] each.
    """
    errors = np.sort(np.asarray(errors_deg, dtype=np.float64))
    if errors.size == 0 or not np.isfinite(errors).all():
        raise ValueError(f"pose_auc needs at least one error, all finite; got {errors.size} errors")
    recall = np.r_[0.0, np.arange(1, errors.size + 1) / errors.size]
    errors = np.r_[0.0, errors]
    aucs = []
    for t in thresholds:
        below = int(np.searchsorted(errors, t))  # the points with an error under t, (0, 0) included
        x = np.r_[errors[:below], t]
        y = np.r_[recall[:below], recall[below - 1]]
        aucs.append(float(np.sum((y[1:] + y[:-1]) / 2 * np.diff(x)) / t))  # the trapezoid rule
    return aucs


def overlap_bucket(overlap: float | None, buckets: dict[str, tuple[float, float]] = OVERLAP_BUCKETS) -> str:
    """Name of the overlap bucket [low, high) holding ``overlap``; "unknown" for None / NaN / outside all."""
    if overlap is None or not math.isfinite(overlap):
        return "unknown"
    for name, (low, high) in buckets.items():
        if low <= overlap < high:
            return name
    return "unknown"
