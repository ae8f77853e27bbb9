"""Shard samples -> ``Example`` -> ``BatchedExample``: decoding the members of both layouts
(:mod:`aesplat.data.layout`), the flip augmentation and collation. ``StreamConfig`` holds what that takes."""

from __future__ import annotations

import io
import json
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor

from aesplat.types import BatchedExample, BatchedViews, Example

from .layout import EXTRINSICS, INTRINSICS, META, evaluation_stems, highlight_member, image_member
from .sampler import ContextCount, ViewPick
from .tar_files import FrameReader, SceneEntry

REFLECT = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))


def flip_views(images: Tensor, extrinsics: Tensor, intrinsics: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Mirror views horizontally and the world with them: images [..., 3, H, W], camera-to-world [..., 4, 4],
    normalised intrinsics [..., 3, 3]. Pixel u maps to W - u; a world point X maps to diag(-1, 1, 1) X."""
    intrinsics = intrinsics.clone()
    intrinsics[..., 0, 2] = 1.0 - intrinsics[..., 0, 2]
    reflect = REFLECT.to(extrinsics)
    return images.flip(-1), reflect @ extrinsics @ reflect, intrinsics


@dataclass(frozen=True)
class StreamConfig:
    """What a stream needs to turn shard samples into batches (built by the DataModule).

    context_views: the count of context views (training: per batch, see :class:`ContextCount`; evaluation: a
    fixed count); num_target_views: targets per example (None: every target of an evaluation sample);
    examples_per_scene: training examples drawn from each scene read (they enter the shuffle buffer
    separately). Which views a training example has: :class:`aesplat.data.sampler.ViewSampler`."""

    image_size: int
    batch_size: int
    context_views: ContextCount = ContextCount(2, 2)
    num_target_views: int | None = 1
    flip_augment: bool = False
    examples_per_scene: int = 1
    large_scale: int = 1  # evaluation: also decode each target at image_size x this (1: no)


def _image(data: bytes, name: str, size: int) -> Tensor:
    """An encoded square image -> uint8 [3, size, size] (resized when stored at another size: square to square
    maps the full extent onto the full extent, so normalised intrinsics are unchanged)."""
    with Image.open(io.BytesIO(data)) as pil:
        img = torch.from_numpy(np.array(pil.convert("RGB"))).permute(2, 0, 1)
    if img.shape[1:] != (size, size):
        if img.shape[1] != img.shape[2]:
            raise ValueError(f"{name} is {tuple(img.shape[1:])}, shard images must be square")
        img = F.interpolate(img[None].float(), size=(size, size), mode="bilinear", antialias=True,
                            align_corners=False)[0].round().clamp(0, 255).to(torch.uint8)  # fmt: skip
    return img


def _mask(data: bytes, name: str, size: int) -> Tensor:
    """A highlight mask PNG -> bool [1, size, size] (nearest neighbour keeps it a mask)."""
    with Image.open(io.BytesIO(data)) as pil:
        mask = torch.from_numpy(np.array(pil.convert("L")) > 127)[None]
    if mask.shape[-1] != mask.shape[-2]:
        raise ValueError(f"{name} is {tuple(mask.shape[1:])}, shard masks must be square")
    if mask.shape[-1] != size:
        mask = F.interpolate(mask[None].float(), size=(size, size), mode="nearest-exact")[0] > 0.5
    return mask


def _cameras(raw: dict[str, bytes], rows: int) -> tuple[Tensor, Tensor]:
    extrinsics = torch.from_numpy(np.load(io.BytesIO(raw[EXTRINSICS]))).float()
    intrinsics = torch.from_numpy(np.load(io.BytesIO(raw[INTRINSICS]))).float()
    if extrinsics.shape != (rows, 4, 4) or intrinsics.shape != (rows, 3, 3):
        raise ValueError(f"camera arrays {tuple(extrinsics.shape)}, {tuple(intrinsics.shape)} do not match "
                         f"{rows} frames")  # fmt: skip
    if not (torch.isfinite(extrinsics).all() and torch.isfinite(intrinsics).all()):
        raise ValueError("non-finite cameras")
    return extrinsics, intrinsics


def decode_scene_example(entry: SceneEntry, reader: FrameReader, pick: ViewPick, cfg: StreamConfig,
                         rng: np.random.Generator) -> Example:  # fmt: skip
    """A training example from a whole-scene sample: only the picked frames are read and decoded. ``rng`` draws
    the flip. ``ValueError`` on a bad sample."""
    meta = json.loads(entry.members[META])
    frames = list(meta["frames"])
    views = [*pick.context, *pick.target]
    extrinsics, intrinsics = _cameras(entry.members, len(frames))
    data = reader.frames(entry, views)
    images = torch.stack([_image(d, f"frame {v}", cfg.image_size) for v, d in zip(views, data)])
    extrinsics, intrinsics = extrinsics[views], intrinsics[views]
    if cfg.flip_augment and rng.uniform() < 0.5:
        images, extrinsics, intrinsics = flip_views(images, extrinsics, intrinsics)
    return Example(images, extrinsics, intrinsics, torch.tensor([frames[v] for v in views]), len(pick.context),
                   str(meta["scene"]), str(meta.get("dataset", "")), pick.gap)  # fmt: skip


class NoContext(ValueError):
    """An evaluation sample that carries no context of the evaluated count (shards made for fewer views)."""


class TooFewTargets(ValueError):
    """An evaluation sample with fewer targets than ``data.eval_num_target_views`` asks for."""


def decode_evaluation_sample(raw: dict[str, bytes], cfg: StreamConfig) -> Example:
    """An evaluation example: the sample's context of ``cfg.context_views`` views (its index's own, or the
    k-view context the shards state), every target or the first ``num_target_views``. ``NoContext`` when the
    sample has no context of that count; ``ValueError`` on a bad sample."""
    meta = json.loads(raw[META])
    context, target, extra = list(meta["context"]), list(meta["target"]), list(meta.get("extra", []))
    # A frame both context and target (as in the literature's indices) is stored twice, alike; its later copy
    # (the target's, with its highlight mask) serves both.
    frames = [*context, *target, *extra]
    names = dict(zip(frames, evaluation_stems(len(context), len(target), len(extra))))
    rows = {f: i for i, f in enumerate(frames)}
    k = cfg.context_views.lo
    chosen = meta.get("context_views", {}).get(str(k)) or (context if len(context) == k else None)
    if chosen is None:
        raise NoContext(f"it carries no {k}-view context (too few frames between its outer context views, or "
                        f"converted with --eval-context-views below {k})")  # fmt: skip
    want = len(target) if cfg.num_target_views is None else cfg.num_target_views
    if len(target) < want:
        raise TooFewTargets(f"it has {len(target)} targets, data.eval_num_target_views asks for {want}")
    targets = target[:want]
    views = [*chosen, *targets]
    extrinsics, intrinsics = _cameras(raw, len(frames))
    picked = [rows[f] for f in views]
    images = torch.stack([_image(raw[image_member(names[f])], names[f], cfg.image_size) for f in views])
    masks = [highlight_member(names[f]) for f in targets]
    highlight = None
    if masks and all(m in raw for m in masks):
        highlight = torch.stack([_mask(raw[m], m, cfg.image_size) for m in masks])
    large = None
    if cfg.large_scale > 1:
        size = cfg.image_size * cfg.large_scale
        large = torch.stack([_image(raw[image_member(names[f])], names[f], size) for f in targets])
    overlap = meta.get("overlap")
    return Example(images, extrinsics[picked], intrinsics[picked], torch.tensor(views, dtype=torch.int64),
                   len(chosen), str(meta["scene"]), str(meta.get("dataset", "")), int(meta["gap"]),
                   float("nan") if overlap is None else float(overlap), highlight, large)  # fmt: skip


def collate(examples: list[Example]) -> BatchedExample:
    """Decoded examples -> ``BatchedExample`` with uint8 images [B, V, 3, H, W]."""
    counts = sorted({(e.num_context, e.images.shape[0] - e.num_context) for e in examples})
    if len(counts) > 1:
        raise ValueError(
            f"examples of one batch have different numbers of (context, target) views {counts} (scenes "
            f"{[e.scene for e in examples]}): set eval_num_target_views or eval_batch_size=1"
        )
    nc = counts[0][0]

    def views(sl: slice) -> BatchedViews:
        return BatchedViews(
            images=torch.stack([e.images[sl] for e in examples]),
            extrinsics=torch.stack([e.extrinsics[sl] for e in examples]),
            intrinsics=torch.stack([e.intrinsics[sl] for e in examples]),
            index=torch.stack([e.index[sl] for e in examples]),
        )

    with_masks = [e.highlight is not None for e in examples]
    if any(with_masks) and not all(with_masks):
        raise ValueError(
            f"only some samples of one batch have highlight masks (scenes {[e.scene for e in examples]}): "
            "evaluate shards with and without masks separately, or set eval_batch_size=1"
        )
    return BatchedExample(
        context=views(slice(0, nc)),
        target=views(slice(nc, None)),
        scene=[e.scene for e in examples],
        overlap=torch.tensor([e.overlap for e in examples], dtype=torch.float32),
        gap=torch.tensor([e.gap for e in examples], dtype=torch.int64),
        dataset=[e.dataset for e in examples],
        highlight=torch.stack([e.highlight for e in examples]) if all(with_masks) else None,
        target_large=None
        if examples[0].target_large is None
        else torch.stack([e.target_large for e in examples]),
    )
