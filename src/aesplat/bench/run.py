"""Measuring a sweep: the ``Bench`` runner (model forwards shared between settings, an untimed first pass of
every setting for its quality, then interleaved timing rounds) and the single-scene examples it measures on."""

from __future__ import annotations

import itertools
import math
import statistics
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, replace
from functools import partial

import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm import tqdm

from ..export import drop_transparent, keep_most_opaque
from ..model import forward_batch
from ..render import render
from ..stats import mean_difference
from ..train.metrics import psnr, relative_pose_errors, ssim
from ..types import BatchedExample, BatchedViews, Gaussians
from .sweep import PRECISIONS, Point, Setting
from .timing import Estimate, Stopwatch, calls_per_round, interleaved, per_round_totals, speedup


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
    """Measured figures of one point. Quality: means over the scenes' target images, and the changes from the
    baseline as means of per-scene differences with 95 % t-intervals (``_lo``/``_hi``). Time: milliseconds per
    scene, medians over the timing rounds with distribution-free 95 % intervals; ``speedup`` is the median of
    the per-round ratios baseline / this setting (total ms), with its interval. NaN bounds: too few scenes or
    rounds for an interval."""

    knob: str
    label: str
    psnr: float = math.nan
    psnr_delta: float = math.nan
    psnr_delta_lo: float = math.nan
    psnr_delta_hi: float = math.nan
    ssim: float = math.nan
    ssim_delta: float = math.nan
    ssim_delta_lo: float = math.nan
    ssim_delta_hi: float = math.nan
    rot_err_deg: float = math.nan  # rotation error of the predicted cameras (none with the data set's)
    forward_ms: float = math.nan
    forward_ms_lo: float = math.nan
    forward_ms_hi: float = math.nan
    render_ms: float = math.nan
    render_ms_lo: float = math.nan
    render_ms_hi: float = math.nan
    total_ms: float = math.nan
    total_ms_lo: float = math.nan
    total_ms_hi: float = math.nan
    speedup: float = math.nan
    speedup_lo: float = math.nan
    speedup_hi: float = math.nan
    render_calls: int = 0  # back-to-back render calls per timing (more for a cheap setting)
    gaussians: float = math.nan  # mean number rendered per scene
    baseline: bool = False
    skipped: str = ""  # why this point could not be measured here (then it has no figures)
    scene_psnr: list[float] = field(default_factory=list)  # per scene, mean over its target images
    scene_ssim: list[float] = field(default_factory=list)
    setting: dict = field(default_factory=dict)


@dataclass
class _Forward:
    """Model outputs of one scene at one forward key."""

    gaussians: Gaussians
    extrinsics: Tensor  # [1, Vt, 4, 4] target cameras (predicted, or the data set's)
    intrinsics: Tensor  # [1, Vt, 3, 3]
    rot_err_deg: float  # mean over the views but view 0 (NaN with the data set's cameras)


@dataclass
class _Quality:
    """What the untimed first pass of a setting found: the images' quality and the cost of one render pass."""

    psnr: list[float]  # per target image, scenes in order
    scene_psnr: list[float]
    scene_ssim: list[float]
    gaussians: float
    rot_err_deg: float
    render_first_ms: float  # one untimed pass over the scenes


class Bench:
    """Measures points of a sweep on a fixed list of single-scene examples, sharing model forwards.

    Every setting first runs once untimed over the scenes: its images give the quality figures, and the pass
    warms it up. Then ``repeats`` rounds time every distinct model forward and every setting's render, all
    interleaved (``aesplat.bench.timing``), the baseline in every round.

    model: called as ``model(context_images, target_images)`` (see aesplat.model), in eval mode.
    scenes: BatchedExample with B = 1 each, float images on ``device``, square images of one size.
    repeats: timing rounds (6 or more give 95 % intervals). round_scenes: scenes each round times every
        setting on, the next ones in turn each round (all of them once rounds x round_scenes reaches their
        number). warmup: further untimed runs of each timed task before the rounds.
    contexts: per count of context views k, the k-view context of each scene (``scenes`` order; None for a
        scene whose evaluation sample carries none): the ``context_views`` knob feeds these, so every count
        renders the same target views. A scene's own count needs no entry.
    render_kwargs: keyword arguments of ``render`` every point shares (background, tile_size, ...); a
        setting's own ``render_options`` override them.
    cameras: ``model.cameras`` of the checkpoint (``predicted`` or ``dataset``: see ``forward_batch``).
    stopwatch: how a timing is taken (default: ``Stopwatch(device)``; a test passes one with a fake clock).
    """

    def __init__(
        self,
        model: torch.nn.Module,
        scenes: Sequence[BatchedExample],
        device: torch.device,
        *,
        repeats: int = 9,
        round_scenes: int = 2,
        warmup: int = 0,
        render_kwargs: dict | None = None,
        progress: bool = True,
        cameras: str = "predicted",
        contexts: Mapping[int, Sequence[BatchedViews | None]] | None = None,
        stopwatch: Stopwatch | None = None,
    ) -> None:
        if not scenes:
            raise ValueError("the benchmark needs at least one evaluation scene")
        if repeats < 1 or round_scenes < 1:
            raise ValueError(
                f"repeats (timing rounds) and round_scenes must be >= 1, got {repeats}, {round_scenes}"
            )
        self.model, self.scenes, self.device = model, list(scenes), device
        self.contexts = dict(contexts or {})
        self.repeats, self.warmup, self.progress, self.cameras = repeats, warmup, progress, cameras
        self.round_scenes = min(round_scenes, len(self.scenes))
        self.render_kwargs = dict(render_kwargs or {})
        self.native = scenes[0].target.images.shape[-1]
        self.stopwatch = stopwatch or Stopwatch(device)
        self._forwards: dict[tuple, list[_Forward]] = {}
        self._forward_first_ms: dict[tuple, float] = {}

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

    def forward_task(self, setting: Setting) -> Callable[[Sequence[int]], list]:
        """One model forward of each of the scenes a call names (indices) at the forward key of ``setting``;
        returns their outputs in that order."""
        if setting.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {setting.precision!r}")
        bf16 = setting.precision == "bf16"
        inputs = [replace(scene, context=resize_views(scene.context, setting.input_size),
                          target=resize_views(scene.target, setting.input_size))
                  for scene in self.with_context(setting.context_views)]  # fmt: skip

        def run(indices: Sequence[int]) -> list:
            with torch.autocast(self.device.type, dtype=torch.bfloat16) if bf16 else nullcontext():
                return [forward_batch(self.model, inputs[i], self.cameras) for i in indices]

        return run

    @torch.no_grad()
    def forward(self, setting: Setting) -> list[_Forward]:
        """Model outputs of every scene for the forward key of ``setting`` (computed once, untimed for the
        figures; the time of that pass decides how many calls one timing makes)."""
        key = setting.forward_key()
        if key in self._forwards:
            return self._forwards[key]
        ms, outputs = self.stopwatch(partial(self.forward_task(setting), range(len(self.scenes))))
        results = []
        for scene, out in zip(self.with_context(setting.context_views), outputs):
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
                    rot_err_deg=rot_err,
                )
            )
        self._forwards[key], self._forward_first_ms[key] = results, ms
        return results

    def render_task(self, setting: Setting) -> Callable[[Sequence[int]], list]:
        """Rendering the target views of each of the scenes a call names for ``setting``; returns their images
        and Gaussian counts in that order."""
        forwards = self.forward(setting)
        size, options = setting.render_size or self.native, self.render_options(setting)

        def run(indices: Sequence[int]) -> list:
            out = []
            for fwd in (forwards[i] for i in indices):
                gaussians = select_gaussians(fwd.gaussians, setting)
                image = render(gaussians, fwd.extrinsics, fwd.intrinsics, size, size,
                               sh_degree=setting.sh_degree, **options)  # fmt: skip
                out.append((image, gaussians.num_gaussians))
            return out

        return run

    @torch.no_grad()
    def first_pass(self, setting: Setting) -> _Quality:
        """Render ``setting`` once (untimed for the figures): PSNR and SSIM per image and scene, Gaussians."""
        forwards = self.forward(setting)
        ms, outputs = self.stopwatch(partial(self.render_task(setting), range(len(self.scenes))))
        psnrs, scene_psnr, scene_ssim, counts = [], [], [], []
        for scene, (out, count) in zip(self.scenes, outputs):
            color = out.color[0]  # [Vt, 3, size, size]
            if color.shape[-1] != self.native:
                color = F.interpolate(color, size=(self.native,) * 2, mode="bilinear", align_corners=False)
            target = scene.target.images[0]
            per_image = psnr(color, target).tolist()
            psnrs += per_image
            scene_psnr.append(statistics.fmean(per_image))
            scene_ssim.append(statistics.fmean(ssim(color, target).tolist()))
            counts.append(count)
        rot_err = statistics.fmean(f.rot_err_deg for f in forwards)
        return _Quality(psnrs, scene_psnr, scene_ssim, statistics.fmean(counts), rot_err, ms)

    @torch.no_grad()
    def warm_up(self, setting: Setting, runs: int) -> None:
        """Untimed forward + render passes of the first scene before anything is measured.

        The first few calls in a process are several times slower on the CPU (allocator and kernel warm-up),
        longer than one untimed pass per setting absorbs; without this the first settings look slow.
        """
        scene = self.with_context(setting.context_views)[0]
        options = self.render_options(setting)
        for _ in range(runs):
            out = forward_batch(self.model, scene, self.cameras)
            vc = scene.context.num_views
            render(out.gaussians, out.extrinsics[:, vc:], out.intrinsics[:, vc:], self.native, self.native,
                   **options)  # fmt: skip

    def round_indices(self, r: int) -> list[int]:
        """The scenes round ``r`` times: ``round_scenes`` of them, taking turns."""
        n = len(self.scenes)
        return [(r * self.round_scenes + i) % n for i in range(self.round_scenes)]

    @torch.no_grad()
    def run(self, points: Sequence[Point], baseline: Setting, warmup_runs: int = 5) -> list[Row]:
        """Measure every point: ``warmup_runs`` untimed baseline passes, the untimed first pass of each distinct
        setting (a setting shared by several series, like the baseline, runs once), then the interleaved
        timing rounds. A setting that cannot run here becomes a skipped row with the reason; a ValueError when
        the baseline cannot."""
        self.warm_up(baseline, warmup_runs)
        settings = list(dict.fromkeys([baseline, *(p.setting for p in points)]))
        bar = tqdm(total=len(settings), desc="aesplat bench", unit="pass", disable=not self.progress)
        quality: dict[Setting, _Quality] = {}
        skipped: dict[Setting, str] = {}
        for setting in settings:
            try:
                quality[setting] = self.first_pass(setting)
            except (RuntimeError, ValueError, TypeError, NotImplementedError, ImportError) as err:
                skipped[setting] = f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"[:200]
            bar.update(1)
        if baseline in skipped:
            bar.close()
            raise ValueError(f"the baseline setting cannot run here: {skipped[baseline]}")

        tasks: dict[tuple, Callable[[Sequence[int]], list]] = {}
        first_ms: dict[tuple, float] = {}
        for setting in quality:
            key = setting.forward_key()
            if ("forward", key) not in tasks:
                tasks["forward", key] = self.forward_task(setting)
                first_ms["forward", key] = self._forward_first_ms[key]
            tasks["render", setting] = self.render_task(setting)
            first_ms["render", setting] = quality[setting].render_first_ms
        share = self.round_scenes / len(self.scenes)  # a timing covers this share of the first pass's scenes
        calls = {k: calls_per_round(first_ms[k] * share) for k in tasks}
        bar.reset(total=(self.warmup + self.repeats) * len(tasks))
        bar.set_description("aesplat bench: timing")
        for _ in range(self.warmup):
            for task in tasks.values():
                task(self.round_indices(0))
                bar.update(1)
        samples = interleaved(tasks, self.repeats, self.stopwatch, calls, round_input=self.round_indices,
                              progress=bar.update)  # fmt: skip
        bar.close()

        def per_scene(key: tuple) -> list[float]:
            return [ms / self.round_scenes for ms in samples[key]]

        base_total = per_round_totals(
            per_scene(("forward", baseline.forward_key())), per_scene(("render", baseline))
        )
        base_quality = quality[baseline]

        def measured(s: Setting) -> Row:
            """The figures of a setting that ran (knob and label are each point's own)."""
            q = quality[s]
            forward, rendered = per_scene(("forward", s.forward_key())), per_scene(("render", s))
            total = per_round_totals(forward, rendered)
            row = Row("", "", psnr=statistics.fmean(q.psnr), ssim=statistics.fmean(q.scene_ssim),
                      rot_err_deg=q.rot_err_deg, gaussians=q.gaussians, scene_psnr=q.scene_psnr,
                      scene_ssim=q.scene_ssim, render_calls=calls["render", s], baseline=s == baseline,
                      setting=asdict(s))  # fmt: skip
            row.psnr_delta, row.psnr_delta_lo, row.psnr_delta_hi = mean_difference(
                q.scene_psnr, base_quality.scene_psnr
            )
            row.ssim_delta, row.ssim_delta_lo, row.ssim_delta_hi = mean_difference(
                q.scene_ssim, base_quality.scene_ssim
            )
            for name, values in (("forward_ms", forward), ("render_ms", rendered), ("total_ms", total)):
                est = Estimate.of(values)
                setattr(row, name, est.value)
                setattr(row, f"{name}_lo", est.lo)
                setattr(row, f"{name}_hi", est.hi)
            ratio = speedup(base_total, total)
            row.speedup, row.speedup_lo, row.speedup_hi = ratio.value, ratio.lo, ratio.hi
            return row

        # A setting shared by several series (the baseline) is one set of figures under each knob's label.
        rows = {s: measured(s) for s in quality}
        rows |= {s: Row("", "", skipped=why, setting=asdict(s)) for s, why in skipped.items()}
        return [replace(rows[p.setting], knob=p.knob, label=p.label) for p in points]


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
