"""Typed containers passed between modules (docs/design.md, "Conventions"). Nothing passes loose tuples.

Each container checks shapes and dtypes when built and names the offending field in its error.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any

import torch
from torch import Tensor

DATA_RECORD = "aesplat_data"  # the checkpoint key of its run's data settings (image_size)


def _check(name: str, t: Any, ndim: int, tail: tuple[int | None, ...] = (), allow_uint8: bool = False) -> None:
    if not isinstance(t, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if not t.is_floating_point() and not (allow_uint8 and t.dtype == torch.uint8):
        raise TypeError(f"{name} must be a floating-point tensor, got dtype {t.dtype}")
    if t.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {tuple(t.shape)}")
    for i, size in enumerate(tail):
        if size is not None and t.shape[ndim - len(tail) + i] != size:
            want = "[" + ", ".join("*" if s is None else str(s) for s in tail) + "]"
            raise ValueError(f"{name} must end in {want}, got shape {tuple(t.shape)}")


def _same_leading(names: list[str], tensors: list[Tensor], n: int) -> None:
    lead = [tuple(t.shape[:n]) for t in tensors]
    if len(set(lead)) != 1:
        shown = ", ".join(f"{a}={b}" for a, b in zip(names, lead))
        raise ValueError(f"leading dimensions disagree: {shown}")


class _TensorContainer:
    """Shared helpers: map a function over every tensor field."""

    def apply(self, fn):
        return replace(self, **{f.name: fn(getattr(self, f.name)) for f in fields(self)
                                if isinstance(getattr(self, f.name), Tensor)})  # fmt: skip

    def to(self, device=None, dtype: torch.dtype | None = None):
        """Move to ``device``; cast floating-point fields (only) to ``dtype``."""
        return self.apply(lambda t: t.to(device=device, dtype=dtype if t.is_floating_point() else None))

    def detach(self):
        return self.apply(lambda t: t.detach())


@dataclass(frozen=True)
class Gaussians(_TensorContainer):
    """A batch of 3D Gaussians.

    means      [B, N, 3]  centres (world / view-0 frame)
    quats      [B, N, 4]  rotations (w, x, y, z), normalised before use
    scales     [B, N, 3]  standard deviations along the rotated axes, > 0
    opacities  [B, N]     in (0, 1)
    sh         [B, N, K, 3] SH coefficients, K = (L + 1)^2 for degree L in 0..4
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    sh: Tensor

    def __post_init__(self) -> None:
        _check("Gaussians.means", self.means, 3, (3,))
        _check("Gaussians.quats", self.quats, 3, (4,))
        _check("Gaussians.scales", self.scales, 3, (3,))
        _check("Gaussians.opacities", self.opacities, 2)
        _check("Gaussians.sh", self.sh, 4, (None, 3))
        k = self.sh.shape[2]
        if k not in (1, 4, 9, 16, 25):
            raise ValueError(f"Gaussians.sh has K={k} coefficients; K must be (L+1)^2 for L in 0..4")
        names = ["means", "quats", "scales", "opacities", "sh"]
        _same_leading(names, [self.means, self.quats, self.scales, self.opacities, self.sh], 2)

    @property
    def batch_size(self) -> int:
        return self.means.shape[0]

    @property
    def num_gaussians(self) -> int:
        return self.means.shape[1]

    @property
    def sh_degree(self) -> int:
        return round(self.sh.shape[2] ** 0.5) - 1


@dataclass(frozen=True)
class RenderOutput(_TensorContainer):
    """What the rasterizer returns for V cameras.

    color [B, V, 3, H, W]  composited colour over the background
    depth [B, V, 1, H, W]  expected z-depth of what is seen (0 where nothing is seen)
    alpha [B, V, 1, H, W]  1 - final transmittance
    """

    color: Tensor
    depth: Tensor
    alpha: Tensor

    def __post_init__(self) -> None:
        _check("RenderOutput.color", self.color, 5, (3, None, None))
        _check("RenderOutput.depth", self.depth, 5, (1, None, None))
        _check("RenderOutput.alpha", self.alpha, 5, (1, None, None))
        _same_leading(["color", "depth", "alpha"], [self.color, self.depth, self.alpha], 2)


@dataclass(frozen=True)
class BatchedViews(_TensorContainer):
    """A batch of V views of B scenes.

    images      [B, V, 3, H, W]  float in [0, 1], or uint8 straight from the loader (see ``float_images``)
    extrinsics  [B, V, 4, 4]     camera-to-world (OpenCV axes)
    intrinsics  [B, V, 3, 3]     normalised (fx, cx / W; fy, cy / H)
    index       [B, V]           frame index in the source video (int64)
    """

    images: Tensor
    extrinsics: Tensor
    intrinsics: Tensor
    index: Tensor

    def __post_init__(self) -> None:
        # uint8 images come straight from the loader and are converted on the device.
        _check("BatchedViews.images", self.images, 5, (3, None, None), allow_uint8=True)
        _check("BatchedViews.extrinsics", self.extrinsics, 4, (4, 4))
        _check("BatchedViews.intrinsics", self.intrinsics, 4, (3, 3))
        if not isinstance(self.index, Tensor) or self.index.is_floating_point() or self.index.ndim != 2:
            raise TypeError("BatchedViews.index must be an integer tensor of shape [B, V]")
        names = ["images", "extrinsics", "intrinsics", "index"]
        ts = [self.images, self.extrinsics, self.intrinsics, self.index]
        _same_leading(names, ts, 2)

    def float_images(self) -> BatchedViews:
        """The same views with images as float32 in [0, 1] (uint8 images are divided by 255)."""
        if self.images.dtype != torch.uint8:
            return self
        return replace(self, images=self.images.float() / 255.0)

    @property
    def num_views(self) -> int:
        return self.images.shape[1]

    @property
    def image_shape(self) -> tuple[int, int]:
        return tuple(self.images.shape[-2:])


@dataclass
class Example:
    """One decoded example (context views first, then targets).

    images uint8 [V, 3, H, W]; extrinsics [V, 4, 4] camera-to-world; intrinsics [V, 3, 3] normalised;
    index int64 [V] source frame ids; gap: context gap in stored frames (what the curriculum judges);
    overlap: NaN where unknown; highlight bool [Vt, 1, H, W] target highlight masks, or None; target_large
    uint8 [Vt, 3, sH, sW] the targets at ``data.eval_transfer_scale`` times the size, or None."""

    images: Tensor
    extrinsics: Tensor
    intrinsics: Tensor
    index: Tensor
    num_context: int
    scene: str
    dataset: str
    gap: int
    overlap: float = float("nan")
    highlight: Tensor | None = None
    target_large: Tensor | None = None


@dataclass(frozen=True)
class BatchedExample:
    """One training / evaluation batch: context views, target views and per-scene metadata.

    scene      list of B scene keys
    overlap    [B] context overlap (NaN where unknown), gap [B] context frame gap
    highlight  [B, Vt, 1, H, W] bool, the target pixels whose specular term exceeds the shards' threshold
               (synthetic test data; all false for a diffuse scene), or None where the data carry no masks
    target_large  [B, Vt, 3, sH, sW] the target images at s times the size (uint8 or float, as ``target``),
               for the resolution-transfer metric (``data.eval_transfer_scale``), or None
    """

    context: BatchedViews
    target: BatchedViews
    scene: list[str] = field(default_factory=list)
    overlap: Tensor | None = None
    gap: Tensor | None = None
    dataset: list[str] = field(default_factory=list)
    highlight: Tensor | None = None
    target_large: Tensor | None = None

    def __post_init__(self) -> None:
        b = self.context.images.shape[0]
        if self.target.images.shape[0] != b:
            raise ValueError(f"context and target batch sizes differ: {b} vs {self.target.images.shape[0]}")
        if self.context.image_shape != self.target.image_shape:
            raise ValueError(
                f"context and target image sizes differ: {self.context.image_shape} vs "
                f"{self.target.image_shape}"
            )
        if self.highlight is not None:
            want = (*self.target.images.shape[:2], 1, *self.target.image_shape)
            if not isinstance(self.highlight, Tensor) or self.highlight.dtype != torch.bool:
                raise TypeError("BatchedExample.highlight must be a bool tensor [B, Vt, 1, H, W] or None")
            if tuple(self.highlight.shape) != want:
                raise ValueError(
                    f"BatchedExample.highlight must have shape {want}, got {tuple(self.highlight.shape)}"
                )
        if self.target_large is not None:
            large, target = self.target_large, self.target.images
            h, w = self.target.image_shape
            ok = large.ndim == 5 and large.shape[:3] == target.shape[:3] and large.dtype == target.dtype
            if (
                not ok
                or large.shape[-2] % h
                or large.shape[-1] % w
                or large.shape[-2] // h != large.shape[-1] // w
            ):
                raise ValueError(
                    f"BatchedExample.target_large must be the targets {tuple(target.shape)} ({target.dtype}) "
                    f"at an integer multiple of their size, got {tuple(large.shape)} ({large.dtype})"
                )

    def float_images(self) -> BatchedExample:
        """Convert uint8 images of both view sets to float32 in [0, 1] (do it after moving to the device)."""
        large = self.target_large
        if large is not None and large.dtype == torch.uint8:
            large = large.float() / 255.0
        return replace(self, context=self.context.float_images(), target=self.target.float_images(),
                       target_large=large)  # fmt: skip

    @property
    def batch_size(self) -> int:
        return self.context.images.shape[0]

    def to(self, device=None, dtype: torch.dtype | None = None) -> BatchedExample:
        def move(t: Tensor | None) -> Tensor | None:
            if t is None:
                return None
            return t.to(device=device, dtype=dtype if t.is_floating_point() else None)

        return replace(self, context=self.context.to(device, dtype), target=self.target.to(device, dtype),
                       overlap=move(self.overlap), gap=move(self.gap),
                       highlight=move(self.highlight), target_large=move(self.target_large))  # fmt: skip


class StepTracker:
    """The global step, written by the training module after every optimizer step and read by the data side
    (the view-gap curriculum, where an epoch's stream starts) in every process: it lives in shared memory, so
    DataLoader workers started before a write see it."""

    def __init__(self, step: int = 0) -> None:
        self._step = torch.full((1,), int(step), dtype=torch.int64).share_memory_()

    def set(self, step: int) -> None:
        self._step[0] = int(step)

    def get(self) -> int:
        return int(self._step[0])
