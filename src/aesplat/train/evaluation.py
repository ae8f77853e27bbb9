"""Evaluation outputs of `aesplat test`: per-scene CSV, summary JSON with overlap buckets, sample renders.

Rows are plain dicts (one per scene) so that every rank's rows can be gathered and written by rank 0.
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..files import atomic_write
from .metrics import AUC_THRESHOLDS_DEG, OVERLAP_BUCKETS, pose_auc

# psnr_highlight / psnr_rest: PSNR on the target pixels the shards mark as specular highlights and on the others
# (per image, averaged over a scene's views that have such pixels; empty where none has); highlight_fraction:
# the share of highlight pixels. Empty for data without highlight masks.
# rot_err_target_deg / trans_err_target_deg: the pose errors of the target views alone, the same views at
# every count of context views (rot_err_deg / trans_err_deg average over the other context views too).
# opaque_share, subpixel_share, fusion_gain_db, psnr_transfer, psnr_upsampled, transfer_gain_db: whether the
# Gaussians form a 3D scene or a point lattice (train/splat_metrics.py); the transfer figures only with
# data.eval_transfer_scale.
SPLAT_METRICS = ("opaque_share", "subpixel_share", "fusion_gain_db", "psnr_transfer", "psnr_upsampled",
                 "transfer_gain_db")  # fmt: skip
# rot_err_last_deg / trans_err_last_deg / pose_err_last_deg: the pose errors of the pose-AUC benchmarks, the
# last context view against context view 0 (NAS3R's); rot_err_ctx_deg / trans_err_ctx_deg / pose_err_ctx_deg:
# the mean over context views 1..V-1 (SPFSplatV2's). The translation angle is folded to min(e, 180 - e), the
# pose error is the larger of the two (train/metrics.py context_pose_errors); summary["pose"] holds their AUCs
# and medians.
POSE_KINDS, POSE_VARIANTS = ("rot", "trans", "pose"), ("last", "ctx")
POSE_AUC_METRICS = tuple(f"{kind}_err_{variant}_deg" for variant in POSE_VARIANTS for kind in POSE_KINDS)
METRICS = ("psnr", "ssim", "lpips", "rot_err_deg", "trans_err_deg", "rot_err_target_deg",
           "trans_err_target_deg", *POSE_AUC_METRICS, "psnr_highlight", "psnr_rest", "highlight_fraction",
           *SPLAT_METRICS)  # fmt: skip
# context_frames / target_frames: the frames evaluated (space-separated, view 0 first), so evaluations at
# different counts of context views can be checked to render the same targets.
CSV_COLUMNS = ("scene", "dataset", "overlap", "bucket", "gap", "context_views", "context_frames",
               "target_frames", *METRICS)  # fmt: skip


@dataclass
class EvalConfig:
    """Where `aesplat test` writes and what it logs (config section ``model.eval``)."""

    output_dir: str | None = None  # `aesplat test` writes into a new <this or the run dir>/test-<UTC time>/
    num_sample_renders: int = 8  # scenes whose render grid is saved as PNG
    log_images_every_n_steps: int = 500  # training image grids sent to the logger
    metrics_lpips: bool = True  # compute the LPIPS metric when its weights are present
    # `aesplat test`: the Gaussians' opaque and sub-pixel shares, the fusion gain (one more render of the
    # targets per context view) and, with data.eval_transfer_scale, the resolution-transfer gain
    splat_metrics: bool = True


def _finite(value: float | None) -> bool:
    return value is not None and math.isfinite(value)


def _mean(values: list[float]) -> float | None:
    finite = [v for v in values if _finite(v)]
    return float(np.mean(finite)) if finite else None


def summarize(rows: list[dict], lpips_unavailable: str | None = None) -> dict:
    """Mean of every metric over all scenes, per overlap bucket (small / medium / large / unknown) and per
    number of context views (``context_views``: {"2": {...}, "3": {...}}; rows without the count are left out
    of it), and the pose AUCs and medians (``pose``, :func:`pose_summary`).

    A metric is averaged over the scenes where it is finite (a scene without highlight pixels has no
    ``psnr_highlight``); ``counts`` says over how many. A metric nobody could compute is reported as null;
    with ``lpips_unavailable`` its reason is recorded.
    """
    rows = sorted(rows, key=lambda r: r["scene"])
    summary: dict = {"num_scenes": len(rows), "metrics": {m: _mean([r.get(m) for r in rows]) for m in METRICS}}
    summary["counts"] = {m: sum(_finite(r.get(m)) for r in rows) for m in METRICS}
    summary["buckets"] = {
        bucket: {"num_scenes": len(members), **{m: _mean([r.get(m) for r in members]) for m in METRICS}}
        for bucket, members in _by_bucket(rows).items()
    }
    summary["context_views"] = {
        count: {"num_scenes": len(members), **{m: _mean([r.get(m) for r in members]) for m in METRICS}}
        for count, members in _by_context_views(rows).items()
    }
    summary["pose"] = pose_summary(rows)
    edges = {k: [lo, hi if math.isfinite(hi) else None] for k, (lo, hi) in OVERLAP_BUCKETS.items()}
    summary["bucket_edges"] = edges
    if lpips_unavailable:
        summary["unavailable"] = {"lpips": lpips_unavailable}
    return summary


def _by_bucket(rows: list[dict]) -> dict[str, list[dict]]:
    """The rows of each overlap bucket; ``unknown`` only when some row is in it."""
    groups = {bucket: [r for r in rows if r["bucket"] == bucket] for bucket in (*OVERLAP_BUCKETS, "unknown")}
    return {bucket: members for bucket, members in groups.items() if members or bucket != "unknown"}


def _by_context_views(rows: list[dict]) -> dict[str, list[dict]]:
    """The rows of each number of context views, keyed by the number as a string, ascending."""
    counts = sorted({r["context_views"] for r in rows if r.get("context_views") is not None})
    return {str(count): [r for r in rows if r.get("context_views") == count] for count in counts}


def pose_summary(rows: list[dict]) -> dict | None:
    """The pose AUCs and median errors of both variants (``last``, ``ctx``: the ``*_err_last_deg`` and
    ``*_err_ctx_deg`` columns) over all scenes (``all``), per overlap bucket and per number of context views::

        {"thresholds_deg": [5, 10, 20],
         "all": {"last": STATS, "ctx": STATS},
         "buckets": {"small": {"last": STATS, "ctx": STATS}, ...},
         "context_views": {"2": {"last": STATS, "ctx": STATS}, ...}}

    with STATS ``{"auc": {KIND: {"5": a, "10": b, "20": c}}, "median": {KIND: m}, "num_scenes": {KIND: n},
    "non_finite": {KIND: k}}`` for KIND in rot, trans, pose: the AUC and median over the n scenes whose error
    is finite, the k non-finite ones left out. STATS is null for a group where no scene has the variant's
    errors, an AUC or median null where none is finite; the whole is null when no scene has pose errors (the
    data set's cameras).
    """
    if not any(r.get(m) is not None for r in rows for m in POSE_AUC_METRICS):
        return None
    return {
        "thresholds_deg": list(AUC_THRESHOLDS_DEG),
        "all": _pose_group(rows),
        "buckets": {bucket: _pose_group(members) for bucket, members in _by_bucket(rows).items()},
        "context_views": {count: _pose_group(members) for count, members in _by_context_views(rows).items()},
    }


def _pose_group(rows: list[dict]) -> dict[str, dict | None]:
    return {variant: _pose_stats(rows, variant) for variant in POSE_VARIANTS}


def _pose_stats(rows: list[dict], variant: str) -> dict | None:
    """STATS of :func:`pose_summary` for one variant over ``rows``; None when no row has its errors."""
    columns = {kind: [r.get(f"{kind}_err_{variant}_deg") for r in rows] for kind in POSE_KINDS}
    if all(v is None for values in columns.values() for v in values):
        return None
    stats: dict = {"auc": {}, "median": {}, "num_scenes": {}, "non_finite": {}}
    for kind, values in columns.items():
        finite = [v for v in values if _finite(v)]
        stats["auc"][kind] = dict(zip(map(str, AUC_THRESHOLDS_DEG), pose_auc(finite))) if finite else None
        stats["median"][kind] = float(np.median(finite)) if finite else None
        stats["num_scenes"][kind] = len(finite)
        stats["non_finite"][kind] = sum(v is not None and not _finite(v) for v in values)
    return stats


def pose_auc_scalars(summary: dict, prefix: str = "test/") -> dict[str, float]:
    """The pose AUCs over all scenes as flat scalars for the logger, ``{prefix}auc{T}_{KIND}_{VARIANT}``
    (``test/auc5_pose_last``, ``test/auc20_rot_ctx``); none when the summary has no pose errors."""
    pose = summary.get("pose") or {}
    return {
        f"{prefix}auc{t}_{kind}_{variant}": value
        for variant, stats in pose.get("all", {}).items()
        if stats is not None
        for kind, aucs in stats["auc"].items()
        if aucs is not None
        for t, value in aucs.items()
    }


def write_results(
    rows: list[dict], out_dir: Path, lpips_unavailable: str | None = None, cameras: str = "predicted"
) -> dict:
    """Write ``per_scene.csv`` and ``summary.json`` into ``out_dir``; returns the summary. ``cameras``: where
    the rendering cameras came from (``model.cameras``), recorded in the summary.

    Each file appears whole or not at all (written beside, then renamed), ``summary.json`` last: a folder
    holding it is a finished evaluation, one without it an evaluation that stopped before the end.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = sorted(rows, key=lambda r: r["scene"])
    table = io.StringIO(newline="")
    writer = csv.DictWriter(table, fieldnames=CSV_COLUMNS, extrasaction="ignore")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: _cell(row.get(k)) for k in CSV_COLUMNS})
    atomic_write(out_dir / "per_scene.csv", lambda f: f.write(table.getvalue().encode()))
    summary = {"cameras": cameras, **summarize(rows, lpips_unavailable)}
    atomic_write(out_dir / "summary.json", lambda f: f.write((json.dumps(summary, indent=2) + "\n").encode()))
    return summary


def _cell(value):
    """A CSV cell: empty for a missing value or NaN (a metric the scene does not have)."""
    return "" if value is None or (isinstance(value, float) and math.isnan(value)) else value


def depth_to_rgb(depth: Tensor) -> Tensor:
    """Depth [..., 1, H, W] -> grey-scale [..., 3, H, W] in [0, 1], near = bright, normalised per image."""
    flat = depth.flatten(-3)
    lo, hi = flat.amin(-1)[..., None, None, None], flat.amax(-1)[..., None, None, None]
    near_bright = 1.0 - (depth - lo) / (hi - lo).clamp_min(1e-8)
    return near_bright.expand(*depth.shape[:-3], 3, *depth.shape[-2:])


def visual_grid(context: Tensor, target: Tensor, render: Tensor, depth: Tensor) -> Tensor:
    """One row per scene: context views | target views | renders | rendered depth.

    context [B, Vc, 3, H, W], target and render [B, Vt, 3, H, W], depth [B, Vt, 1, H, W] -> [3, B*H, X*W].
    """
    tiles = torch.cat([context, target, render.clamp(0, 1), depth_to_rgb(depth)], dim=1).float().cpu()
    b, n, c, h, w = tiles.shape
    return tiles.permute(2, 0, 3, 1, 4).reshape(c, b * h, n * w)
