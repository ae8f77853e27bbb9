"""Measuring a sweep: the ``Bench`` runner (model forwards shared between settings, renders timed per setting),
the timing, and the single-scene examples it measures on."""

from __future__ import annotations

import itertools
import math
import statistics
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm import tqdm

from ..export import drop_transparent, keep_most_opaque
from ..model import forward_batch
from ..render import render
from ..train.metrics import psnr, relative_pose_errors, ssim
from ..types import BatchedExample, BatchedViews, Gaussians
from .sweep import Point, Setting


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_call(fn: Callable[[], Any], device: torch.device, repeats: int, warmup: int) -> tuple[Any, float]:
    """Run ``fn`` ``warmup`` times untimed, then ``repeats`` times; returns (last result, median ms)."""
    for _ in range(warmup):
        fn()
    times = []
    result = None
    for _ in range(max(1, repeats)):
        _sync(device)
        start = time.perf_counter()
        result = fn()
        _sync(device)
        times.append(1000.0 * (time.perf_counter() - start))
    return result, statistics.median(times)


def resize_views(views: BatchedViews, size: int | None) -> BatchedViews:
    """Square images [B, V, 3, H, W] resized (antialiased bilinear) to ``size``; normalised intrinsics are
    resolution-free and stay as they are."""
    if size is None or size == views.images.shape[-1]:
        return views
    b, v = views.images.shape[:2]
    flat = views.images.flatten(0, 1)
    resized = F.interpolate(flat, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
    return replace(views, images=resized.clamp(0, 1).unflatten(0, (b, v)))


def select_gaussians(gaussians: Gaussians, setting: Setting) -> Gaussians:
    """Apply the Gaussian-count knobs of ``setting`` to one scene's Gaussians (B = 1)."""
    if setting.keep_fraction < 1.0:
        gaussians = keep_most_opaque(gaussians, setting.keep_fraction)
    return drop_transparent(gaussians, setting.min_opacity)


@dataclass
class Row:
    """Measured figures of one point, averaged over the scenes."""

    knob: str
    label: str
    psnr: float = math.nan
    ssim: float = math.nan
    rot_err_deg: float = math.nan  # rotation error of the predicted cameras (none with the data set's)
    forward_ms: float = math.nan
    render_ms: float = math.nan
    total_ms: float = math.nan
    gaussians: float = math.nan  # mean number rendered per scene
    baseline: bool = False
    skipped: str = ""  # why this point could not be measured here
    setting: dict = field(default_factory=dict)


@dataclass
class _Forward:
    """Model outputs of one scene at one forward key, with the median forward time."""

    gaussians: Gaussians
    extrinsics: Tensor  # [1, Vt, 4, 4] target cameras (predicted, or the data set's)
    intrinsics: Tensor  # [1, Vt, 3, 3]
    ms: float
    rot_err_deg: float  # mean over the views but view 0 (NaN with the data set's cameras)


class Bench:
    """Measures points of a sweep on a fixed list of single-scene examples, sharing model forwards.

    model: called as ``model(context_images, target_images)`` (see aesplat.model), in eval mode.
    scenes: BatchedExample with B = 1 each, float images on ``device``, square images of one size.
    contexts: per count of context views k, the k-view context of each scene (``scenes`` order; None for a
        scene whose evaluation sample carries none): the ``context_views`` knob feeds these, so every count
        renders the same target views. A scene's own count needs no entry.
    render_kwargs: keyword arguments of ``render`` every point shares (background, tile_size, ...); a
        setting's own ``render_options`` override them.
    cameras: ``model.cameras`` of the checkpoint (``predicted`` or ``dataset``: see ``forward_batch``).
    """

    def __init__(
        self,
        model: torch.nn.Module,
        scenes: Sequence[BatchedExample],
        device: torch.device,
        *,
        repeats: int = 3,
        warmup: int = 1,
        render_kwargs: dict | None = None,
        progress: bool = True,
        cameras: str = "predicted",
        contexts: Mapping[int, Sequence[BatchedViews | None]] | None = None,
    ) -> None:
        if not scenes:
            raise ValueError("the benchmark needs at least one evaluation scene")
        self.model, self.scenes, self.device = model, list(scenes), device
        self.contexts = dict(contexts or {})
        self.repeats, self.warmup, self.progress, self.cameras = repeats, warmup, progress, cameras
        self.render_kwargs = dict(render_kwargs or {})
        self.native = scenes[0].target.images.shape[-1]
        self._forwards: dict[tuple, list[_Forward]] = {}

    def with_context(self, count: int | None) -> list[BatchedExample]:
        """Every scene with ``count`` context views (None: its own); a ValueError when some scene's evaluation
        sample carries no context of that count."""
        if count is None:
            return self.scenes
        contexts = self.contexts.get(count, [None] * len(self.scenes))
        out = [s if s.context.num_views == count else None if c is None else replace(s, context=c)
               for s, c in zip(self.scenes, contexts)]  # fmt: skip
        missing = [s.scene[0] for s, o in zip(self.scenes, out) if o is None]
        if missing:
            raise ValueError(
                f"{len(missing)} of {len(out)} scenes ({', '.join(missing[:2])}{', ...' * (len(missing) > 2)}) "
                f"carry no {count}-view context: too few frames between their outer context views, or shards "
                f"converted with --eval-context-views below {count}"
            )
        return out

    def render_options(self, setting: Setting) -> dict:
        """Keyword arguments of ``render`` for ``setting``: the shared ones, its own, its backend."""
        return {**self.render_kwargs, **dict(setting.render_options), "backend": setting.backend}

    @torch.no_grad()
    def forward(self, setting: Setting) -> list[_Forward]:
        """Model outputs (and forward times) of every scene for the forward key of ``setting`` (cached)."""
        key = setting.forward_key()
        if key in self._forwards:
            return self._forwards[key]
        if setting.precision not in ("fp32", "bf16"):
            raise ValueError(f"precision must be 'fp32' or 'bf16', got {setting.precision!r}")
        autocast = (torch.autocast(self.device.type, dtype=torch.bfloat16) if setting.precision == "bf16"
                    else nullcontext())  # fmt: skip
        results = []
        for i, scene in enumerate(self.with_context(setting.context_views)):
            size = setting.input_size
            resized = replace(scene, context=resize_views(scene.context, size),
                              target=resize_views(scene.target, size))  # fmt: skip

            def run(resized: BatchedExample = resized):
                with autocast:
                    return forward_batch(self.model, resized, self.cameras)

            out, ms = time_call(run, self.device, self.repeats, self.warmup if i == 0 else 0)
            vc = scene.context.num_views
            rot_err = math.nan
            if self.cameras == "predicted":
                truth = torch.cat([scene.context.extrinsics, scene.target.extrinsics], dim=1)
                rot_err = relative_pose_errors(out.extrinsics, truth)[0].mean().item()
            results.append(
                _Forward(
                    gaussians=out.gaussians.to(dtype=torch.float32),
                    extrinsics=out.extrinsics[:, vc:].float(),
                    intrinsics=out.intrinsics[:, vc:].float(),
                    ms=ms,
                    rot_err_deg=rot_err,
                )
            )
        self._forwards[key] = results
        return results

    @torch.no_grad()
    def measure(self, point: Point) -> Row:
        """PSNR, SSIM and milliseconds of one point; a failing setting becomes a skipped row with the reason."""
        s = point.setting
        row = Row(point.knob, point.label, setting=asdict(s))
        try:
            forwards = self.forward(s)
            psnrs, ssims, render_ms, counts = [], [], [], []
            size, options = s.render_size or self.native, self.render_options(s)
            for i, (scene, fwd) in enumerate(zip(self.scenes, forwards)):

                def run(fwd: _Forward = fwd):
                    gaussians = select_gaussians(fwd.gaussians, s)
                    out = render(gaussians, fwd.extrinsics, fwd.intrinsics, size, size, sh_degree=s.sh_degree,
                                 **options)  # fmt: skip
                    return out, gaussians.num_gaussians

                (out, count), ms = time_call(run, self.device, self.repeats, self.warmup if i == 0 else 0)
                color = out.color[0]  # [Vt, 3, size, size]
                if size != self.native:
                    color = F.interpolate(color, size=(self.native,) * 2, mode="bilinear", align_corners=False)
                target = scene.target.images[0]
                psnrs += psnr(color, target).tolist()
                ssims += ssim(color, target).tolist()
                render_ms.append(ms)
                counts.append(count)
        except (RuntimeError, ValueError, TypeError, NotImplementedError, ImportError) as err:
            row.skipped = f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"[:200]
            return row
        row.psnr, row.ssim = statistics.fmean(psnrs), statistics.fmean(ssims)
        row.rot_err_deg = statistics.fmean(f.rot_err_deg for f in forwards)
        row.forward_ms = statistics.fmean(f.ms for f in forwards)
        row.render_ms = statistics.fmean(render_ms)
        row.total_ms = row.forward_ms + row.render_ms
        row.gaussians = statistics.fmean(counts)
        return row

    @torch.no_grad()
    def warm_up(self, setting: Setting, runs: int) -> None:
        """Untimed forward + render passes of the first scene before anything is measured.

        The first few calls in a process are several times slower on the CPU (allocator and kernel warm-up),
        longer than one per-setting warm-up run absorbs; without this the first settings measured look slow.
        """
        scene = self.with_context(setting.context_views)[0]
        options = self.render_options(setting)
        for _ in range(runs):
            out = forward_batch(self.model, scene, self.cameras)
            vc = scene.context.num_views
            render(out.gaussians, out.extrinsics[:, vc:], out.intrinsics[:, vc:], self.native, self.native,
                   **options)  # fmt: skip

    def run(self, points: Sequence[Point], baseline: Setting, warmup_runs: int = 5) -> list[Row]:
        """Measure every point (after ``warmup_runs`` untimed baseline passes); a setting shared by several
        series (the baseline) is measured once."""
        self.warm_up(baseline, warmup_runs)
        done: dict[Setting, Row] = {}
        rows = []
        for point in tqdm(points, desc="aesplat bench", unit="setting", disable=not self.progress):
            if point.setting not in done:
                done[point.setting] = self.measure(point)
            row = replace(done[point.setting], knob=point.knob, label=point.label)
            row.baseline = point.setting == baseline
            rows.append(row)
        return rows


def single_scenes(batches: Iterable[BatchedExample], limit: int, device: torch.device) -> list[BatchedExample]:
    """Split loader batches into at most ``limit`` single-scene examples (B = 1), float images on ``device``."""
    return list(itertools.islice(each_scene(batches, device), limit))


def each_scene(batches: Iterable[BatchedExample], device: torch.device) -> Iterator[BatchedExample]:
    """Loader batches split into single-scene examples (B = 1), float images on ``device``, as they are read."""
    for batch in batches:
        for b in range(batch.batch_size):

            def pick(t: Tensor | None, b: int = b) -> Tensor | None:
                return None if t is None else t[b : b + 1]

            one = BatchedExample(
                context=batch.context.apply(pick),
                target=batch.target.apply(pick),
                scene=batch.scene[b : b + 1],
                overlap=pick(batch.overlap),
                gap=pick(batch.gap),
                dataset=batch.dataset[b : b + 1],
            )
            yield one.to(device).float_images()


def contexts_of(stream: Iterable[BatchedExample], keys: Sequence[str]) -> list[BatchedViews | None]:
    """The context views ``stream`` gives each scene of ``keys``, None where it gives none.

    ``stream`` yields single scenes (B = 1) with the k-view contexts of the evaluation samples, in the shards'
    order, leaving out the samples that carry no k-view context; ``keys`` are scenes read from the same shards
    in the same order (at another count). A scene of the stream that is not among ``keys`` is one the other
    count left out, and is passed over. The stream is read up to the last of ``keys`` (or to its end when that
    scene has no k-view context)."""
    wanted = set(keys)
    scenes = iter(stream)
    head = next(scenes, None)
    out: list[BatchedViews | None] = []
    for key in keys:
        while head is not None and head.scene[0] not in wanted:
            head = next(scenes, None)
        if head is not None and head.scene[0] == key:
            out.append(head.context)
            head = next(scenes, None) if len(out) < len(keys) else None
        else:
            out.append(None)
    return out
