"""`aesplat bench`: what accuracy costs in time, for every knob that trades one for the other (docs/bench.md).

    aesplat bench --ckpt CKPT [--out DIR]

For a trained model on evaluation scenes, each knob is swept on its own from a baseline (every SH band, the
data's resolution, all Gaussians, fp32, the default renderer backend):

    sh_degree         SH bands used when rendering (0 .. the model's degree)
    context_views     context views fed to the model (2, 3, 4, 6): each evaluation sample's k-view context
                      (the one `aesplat test --data.num_context_views k` evaluates), the same target views
    input_size        side of the images fed to the model (multiples of its patch size); Gaussians rendered
                      at full size
    render_size       side of the rendered image, upsampled (bilinear) to full size for the metrics
    keep_fraction     only the most opaque fraction of the Gaussians is rendered
    min_opacity       Gaussians below an opacity threshold are dropped
    precision         fp32, or bf16 autocast around the model forward (the renderer is always fp32)
    backend           renderer backends available here (torch, torch compiled, gsplat with CUDA)

Quality is PSNR (per image, then averaged) and SSIM against the ground-truth target images, rendered with
the *predicted* target cameras (the data set's for a checkpoint trained with ``model.cameras: dataset``),
and the rotation error of the predicted cameras against the data set's (degrees, views relative to view 0).
Time is milliseconds per scene for the model forward and for rendering the target views: median over repeats
of each scene (warm-up runs excluded), then averaged over scenes.

Writes DIR/bench.csv, DIR/BENCH.md (tables), DIR/accuracy_vs_time.png (quality against milliseconds, one
series per knob) and DIR/bench.json (rows plus the machine and settings they were measured with).
"""

from __future__ import annotations

import argparse
import csv
import inspect
import json
import math
import os
import platform
import statistics
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm import tqdm

from .commands import HelpFormatter, OneLineParser, resolve_device
from .errors import UserError
from .export import drop_transparent, keep_most_opaque
from .model import forward_batch
from .render import render
from .threads import ENV_OVERRIDE, apply_thread_policy
from .train.metrics import psnr, relative_pose_errors, ssim
from .types import BatchedExample, BatchedViews, Gaussians

# ---------------------------------------------------------------------------------------------------
# Settings: one value per knob


@dataclass(frozen=True)
class Setting:
    """One point of a sweep: a value for every knob. ``None`` sizes mean the data's own resolution."""

    sh_degree: int | None = None  # SH bands used at render time (None: all the model predicts)
    context_views: int | None = None  # context views fed to the model (None: every one the sample holds)
    input_size: int | None = None  # model input side, a multiple of the model's patch size
    render_size: int | None = None  # render side; upsampled to the data's side for the metrics
    keep_fraction: float = 1.0  # most opaque fraction of the Gaussians kept
    min_opacity: float = 0.0  # Gaussians below this opacity dropped
    precision: str = "fp32"  # "fp32" or "bf16" (autocast around the model forward)
    backend: str = "torch"  # renderer backend
    render_options: tuple[tuple[str, Any], ...] = ()  # extra keyword arguments of ``render``

    def forward_key(self) -> tuple:
        """Settings with the same key share the model forward (only rendering differs)."""
        return (self.context_views, self.input_size, self.precision)


@dataclass(frozen=True)
class Point:
    """A setting as one point of one knob's series."""

    knob: str  # the knob this series varies
    label: str  # its value in words, e.g. "SH 2", "112 px", "25 %"
    setting: Setting


def model_input_sizes(native: int, scales: Sequence[float], patch: int) -> list[int]:
    """Input sides for ``scales`` of the native side: multiples of ``patch`` (at least two), unique, sorted."""
    return sorted({max(2 * patch, round(native * s / patch) * patch) for s in scales} | {native})


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


def default_sweep(
    sh_degree: int,
    native_size: int,
    *,
    patch: int = 14,
    context_views: Sequence[int] = (2, 3, 4, 6),
    backends: Sequence[str] = ("torch",),
    input_scales: Sequence[float] = (0.5, 0.75, 1.0),
    render_scales: Sequence[float] = (0.25, 0.5, 0.75, 1.0),
    keep_fractions: Sequence[float] = (1.0, 0.5, 0.25, 0.1),
    min_opacities: Sequence[float] = (0.0, 0.05, 0.2, 0.5, 0.8),
    precisions: Sequence[str] = ("fp32", "bf16"),
    tile_sizes: Sequence[int] = (),
    compiled: bool = False,
    knobs: Iterable[str] | None = None,
) -> tuple[Setting, list[Point]]:
    """Every knob swept alone from the baseline ``Setting(backend=backends[0])``; returns (baseline, points).

    patch: the model's patch size (input sides are multiples of it).
    context_views: counts of context views to feed the model; the baseline feeds every one a sample holds,
    which is the point of the same count.

    tile_sizes: renderer tile sides to try (a speed-only knob: the image does not change); empty = skip.
    compiled: add a "torch compiled" backend point (``render(..., compile=True)``).
    knobs: restrict to these knob names (default: all).
    """
    base = Setting(backend=backends[0])
    render_sizes = sorted({max(8, round(native_size * r)) for r in render_scales} | {native_size})

    def own(size: int) -> int | None:  # None stands for the data's own side
        return None if size == native_size else size

    series: dict[str, list[Point]] = {
        "sh_degree": [Point("sh_degree", f"SH {d}", replace(base, sh_degree=None if d == sh_degree else d))
                      for d in range(sh_degree + 1)],
        "context_views": [Point("context_views", f"{c} views", replace(base, context_views=c))
                          for c in sorted(set(context_views))],
        "input_size": [Point("input_size", f"{s} px", replace(base, input_size=own(s)))
                       for s in model_input_sizes(native_size, input_scales, patch)],
        "render_size": [Point("render_size", f"{s} px", replace(base, render_size=own(s)))
                        for s in render_sizes],
        "keep_fraction": [Point("keep_fraction", f"{100 * f:g} %", replace(base, keep_fraction=f))
                          for f in sorted(set(keep_fractions) | {1.0})],
        "min_opacity": [Point("min_opacity", f"≥ {o:g}", replace(base, min_opacity=o))
                        for o in sorted(set(min_opacities) | {0.0})],
        "precision": [Point("precision", p, replace(base, precision=p)) for p in precisions],
        "backend": [Point("backend", b, replace(base, backend=b)) for b in backends],
        "tile_size": [Point("tile_size", f"tile {t}", replace(base, render_options=(("tile_size", t),)))
                      for t in tile_sizes],
    }  # fmt: skip
    if compiled:
        series["backend"].append(
            Point(
                "backend", "torch compiled", replace(base, backend="torch", render_options=(("compile", True),))
            )
        )
    chosen = list(series) if knobs is None else list(knobs)
    unknown = [k for k in chosen if k not in series]
    if unknown:
        raise ValueError(f"unknown knob(s) {unknown}; choose from {list(series)}")
    return base, [point for knob in chosen for point in series[knob]]


# ---------------------------------------------------------------------------------------------------
# Measuring


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
            for i, (scene, fwd) in enumerate(zip(self.scenes, forwards)):
                size = s.render_size or self.native

                options = {**self.render_kwargs, **dict(s.render_options), "backend": s.backend}

                def run(fwd: _Forward = fwd, size: int = size, options: dict = options):
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
        options = {**self.render_kwargs, **dict(setting.render_options), "backend": setting.backend}
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
    scenes: list[BatchedExample] = []
    for scene in each_scene(batches, device):
        if len(scenes) >= limit:
            break
        scenes.append(scene)
    return scenes


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


# ---------------------------------------------------------------------------------------------------
# Reporting


CSV_FIELDS = ["knob", "label", "psnr", "ssim", "rot_err_deg", "forward_ms", "render_ms", "total_ms",
              "gaussians", "baseline", "skipped"]  # fmt: skip

KNOB_TITLES = {
    "sh_degree": "SH degree at render",
    "context_views": "context views",
    "input_size": "model input resolution",
    "render_size": "render resolution",
    "keep_fraction": "Gaussians kept (most opaque)",
    "min_opacity": "Gaussians kept (opacity threshold)",
    "precision": "model precision",
    "backend": "renderer backend",
    "tile_size": "renderer tile size",
}


def write_csv(rows: Sequence[Row], path: Path) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: getattr(row, k) for k in CSV_FIELDS})


def markdown_tables(rows: Sequence[Row], meta: dict) -> str:
    """One markdown table per knob, with PSNR change and speed-up against the baseline."""
    base = next((r for r in rows if r.baseline and not r.skipped), None)
    lines = [
        "# Accuracy versus time",
        "",
        f"Checkpoint `{meta.get('ckpt', '?')}`, {meta.get('scenes', '?')} evaluation scenes, "
        f"{meta.get('device', '?')}, torch {meta.get('torch', '?')} with {meta.get('threads', '?')} threads; "
        f"median of {meta.get('repeats', '?')} repeats per scene after {meta.get('warmup', '?')} warm-up "
        f"run(s) per setting and {meta.get('process_warmup', 0)} of the baseline before the first. "
        "Milliseconds are per scene (model forward on context + target views, on the context views alone with "
        "the data set's cameras; rendering of the target views). "
        f"Cameras: {meta.get('cameras', 'predicted')} (`model.cameras`).",
        "",
    ]
    if base is not None:
        lines += [
            f"Baseline: every context view of a sample ({meta.get('context_views', '?')}), all SH bands, "
            f"{meta.get('native_size', '?')} px, all Gaussians, fp32, "
            f"`{base.setting.get('backend')}` backend — PSNR {base.psnr:.2f} dB, SSIM {base.ssim:.4f}, "
            f"{base.total_ms:.1f} ms ({base.forward_ms:.1f} forward + {base.render_ms:.1f} render).",
            "",
        ]
    for knob in dict.fromkeys(r.knob for r in rows):
        lines += [
            f"## {KNOB_TITLES.get(knob, knob)}",
            "",
            "| setting | PSNR (dB) | Δ PSNR | SSIM | rot. err (°) | forward ms | render ms | total ms "
            "| speed-up | Gaussians |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for r in (r for r in rows if r.knob == knob):
            label = f"**{r.label}**" if r.baseline else r.label
            if r.skipped:
                lines.append(f"| {label} | not measured here: {r.skipped} | | | | | | | | |")
                continue
            dpsnr = f"{r.psnr - base.psnr:+.2f}" if base else ""
            speed = f"{base.total_ms / r.total_ms:.2f}×" if base else ""
            rot = f"{r.rot_err_deg:.2f}" if math.isfinite(r.rot_err_deg) else "–"
            lines.append(
                f"| {label} | {r.psnr:.2f} | {dpsnr} | {r.ssim:.4f} | {rot} | {r.forward_ms:.1f} | "
                f"{r.render_ms:.1f} | {r.total_ms:.1f} | {speed} | {r.gaussians:,.0f} |"
            )
        lines.append("")
    lines.append("Bold: the baseline setting. Plot: `accuracy_vs_time.png`; raw figures: `bench.csv`.")
    return "\n".join(lines) + "\n"


def plot(rows: Sequence[Row], path: Path) -> None:
    """Quality against milliseconds: an overview (PSNR vs total ms, every knob), then one panel per knob
    (PSNR, and SSIM dashed on the right axis, vs total ms; points joined in the knob's own order)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    knobs = [k for k in dict.fromkeys(r.knob for r in rows) if any(r.knob == k and not r.skipped for r in rows)]
    cols = 3
    nrows = math.ceil((len(knobs) + 1) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(5.6 * cols, 4.2 * nrows), squeeze=False)
    flat = list(axes.flat)
    base = next((r for r in rows if r.baseline and not r.skipped), None)
    overview = flat[0]
    for i, knob in enumerate(knobs):
        pts = [r for r in rows if r.knob == knob and not r.skipped]
        xs, psnrs, ssims = [r.total_ms for r in pts], [r.psnr for r in pts], [r.ssim for r in pts]
        title = KNOB_TITLES.get(knob, knob)
        overview.plot(xs, psnrs, marker="o", color=f"C{i}", label=title, alpha=0.85)
        ax = flat[i + 1]
        ax.plot(xs, psnrs, marker="o", color=f"C{i}")
        for r, x, y in zip(pts, xs, psnrs):
            ax.annotate(r.label, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
        twin = ax.twinx()
        twin.plot(xs, ssims, marker="s", linestyle="--", color="0.5", alpha=0.7)
        twin.set_ylabel("SSIM (dashed)", color="0.4")
        _min_span(ax, psnrs, 1.0)  # flat series stay flat instead of magnifying 1e-6 dB differences
        _min_span(twin, ssims, 0.02)
        ax.set_title(title)
        ax.set_xlabel("total ms per scene")
        ax.set_ylabel("PSNR (dB)")
        ax.grid(True, alpha=0.3)
    if base is not None:
        overview.scatter([base.total_ms], [base.psnr], marker="*", s=220, color="k", zorder=5, label="baseline")
    overview.set_xscale("log")
    overview.set_title("all knobs")
    overview.set_xlabel("total ms per scene (forward + render)")
    overview.set_ylabel("PSNR (dB)")
    overview.grid(True, which="both", alpha=0.3)
    overview.legend(fontsize=7, loc="best")
    for ax in flat[len(knobs) + 1 :]:
        ax.set_visible(False)
    fig.suptitle("aesplat: accuracy versus time (each knob varied alone from the baseline)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _min_span(ax, values: Sequence[float], span: float) -> None:
    """Give a y axis at least ``span`` of range around ``values``, without offset notation."""
    lo, hi = min(values), max(values)
    if hi - lo < span:
        mid = 0.5 * (lo + hi)
        ax.set_ylim(mid - 0.6 * span, mid + 0.6 * span)
    ax.ticklabel_format(axis="y", useOffset=False)


def write_report(rows: Sequence[Row], out_dir: str | Path, meta: dict) -> dict[str, Path]:
    """Write bench.csv, BENCH.md, accuracy_vs_time.png and bench.json under ``out_dir``; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {name: out / name for name in ("bench.csv", "BENCH.md", "accuracy_vs_time.png", "bench.json")}
    write_csv(rows, paths["bench.csv"])
    paths["BENCH.md"].write_text(markdown_tables(rows, meta))
    plot(rows, paths["accuracy_vs_time.png"])
    paths["bench.json"].write_text(json.dumps({"meta": meta, "rows": [asdict(r) for r in rows]}, indent=1))
    return paths


def machine_meta(device: torch.device) -> dict:
    """Where the figures were measured."""
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
    else:
        name = _cpu_name() or platform.processor() or platform.machine()
        name = f"{name}, {os.cpu_count()} logical cores"
    return {"device": f"{device.type} ({name})", "torch": torch.__version__, "threads": torch.get_num_threads()}


def _cpu_name() -> str:
    """The CPU model from /proc/cpuinfo (Linux), else an empty string."""
    try:
        with open("/proc/cpuinfo") as f:
            return next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        return ""


# ---------------------------------------------------------------------------------------------------
# Command line


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def _names(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="aesplat bench",
        description="Accuracy versus time: sweep every quality knob of a trained model on evaluation scenes "
        "and write tables (markdown, CSV) and a plot of PSNR/SSIM against milliseconds.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--ckpt", required=True, help="checkpoint written by `aesplat fit`")
    parser.add_argument("--out", default=None, help="output directory (default: RUN_DIR/bench next to the "
                        "checkpoint's run, else outputs/bench)")  # fmt: skip
    parser.add_argument("--data-root", default=None, help="shard folder with test/*.tar (default: the run's "
                        "data.root from its config.yaml)")  # fmt: skip
    parser.add_argument("--image-size", type=int, default=None, help="evaluation image side (default: the "
                        "run's data.image_size)")  # fmt: skip
    parser.add_argument("--scenes", type=int, default=8, help="evaluation scenes measured")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per scene and setting (median)")
    parser.add_argument("--warmup", type=int, default=1, help="untimed runs before each setting")
    parser.add_argument("--process-warmup", type=int, default=5,
                        help="untimed baseline passes before the first measurement")  # fmt: skip
    parser.add_argument("--context-views", type=_ints, default=[2, 3, 4, 6],
                        help="context-view counts fed to the model: each evaluation sample's k-view context, "
                        "the same targets (a count some scene carries no context of, or one the model cannot "
                        "take, is reported as not measured)")  # fmt: skip
    parser.add_argument("--data-context-views", type=int, default=None,
                        help="context views of every other knob's settings (default: the run's "
                        "data.num_context_views, the lower end of a range)")  # fmt: skip
    parser.add_argument("--knobs", type=_names, default=None,
                        help=f"comma-separated subset of {', '.join(KNOB_TITLES)} (default: all)")  # fmt: skip
    parser.add_argument(
        "--input-scales",
        type=_floats,
        default=[0.5, 0.75, 1.0],
        help="model input sides as fractions of the data's (rounded to multiples of 14)",
    )
    parser.add_argument(
        "--render-scales",
        type=_floats,
        default=[0.25, 0.5, 0.75, 1.0],
        help="render sides as fractions of the data's",
    )
    parser.add_argument(
        "--keep-fractions",
        type=_floats,
        default=[1.0, 0.5, 0.25, 0.1],
        help="fractions of the most opaque Gaussians kept",
    )
    parser.add_argument(
        "--min-opacities",
        type=_floats,
        default=[0.0, 0.05, 0.2, 0.5, 0.8],
        help="opacity thresholds below which Gaussians are dropped",
    )
    parser.add_argument("--precisions", type=_names, default=["fp32", "bf16"], help="model precisions")
    parser.add_argument("--backends", type=_names, default=None,
                        help="renderer backends (default: torch, plus gsplat when CUDA and gsplat are here; "
                        "the first is the baseline's)")  # fmt: skip
    parser.add_argument("--tile-sizes", type=_floats, default=[8, 16], help="renderer tile sides")
    parser.add_argument(
        "--compile",
        action="store_true",
        help="also measure the torch backend with torch.compile (cold compiles take minutes)",
    )
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:1, ... (auto: cuda if available)")
    parser.add_argument("--threads", type=int, default=None,
                        help=f"torch CPU threads (default: the usable cores, or ${ENV_OVERRIDE})")  # fmt: skip
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def evaluation_scenes(loaded, data_root: str | None, image_size: int | None, limit: int, device: torch.device,
                      context_views: int | None = None) -> list[BatchedExample]:  # fmt: skip
    """The first ``limit`` test scenes of the run's data set, one per example, on ``device``;
    ``context_views``: the count of context views (default: the run's; see ``evaluation_stream``)."""
    return single_scenes(evaluation_stream(loaded, data_root, image_size, context_views), limit, device)


def evaluation_stream(loaded, data_root: str | None, image_size: int | None, context_views: int | None = None):
    """The test stream of the run's data set (``aesplat.data.EvalStream``) with the k-view contexts of its
    evaluation samples for k = ``context_views`` (default: the run's ``data.num_context_views``, the lower
    end of a range), as ``aesplat test --data.num_context_views k`` reads them. A UserError when the shards
    carry no contexts of that count."""
    from .data import DataModule

    data = dict(loaded.data or {})
    if data_root is not None:
        data["root"] = data_root
    if "root" not in data:
        why = loaded.config_problem or "there is no config.yaml beside the checkpoint's run"
        raise SystemExit(f"aesplat bench: the data set is not known ({why}); give --data-root DIR")
    if image_size is not None:
        data["image_size"] = image_size
    elif loaded.trained_size is not None:
        data["image_size"] = loaded.trained_size
    else:
        raise UserError(f"{loaded.path} does not say which image size it was trained at: give --image-size")
    if context_views is not None:
        data["num_context_views"] = context_views
    data.update(num_workers=0, eval_batch_size=1)
    known = set(inspect.signature(DataModule).parameters)
    datamodule = DataModule(**{k: v for k, v in data.items() if k in known})
    try:
        return datamodule.eval_dataset("test")
    except FileNotFoundError as err:
        raise SystemExit(f"aesplat bench: {err}") from err


def context_views_of(
    loaded,
    data_root: str | None,
    image_size: int | None,
    scenes: Sequence[BatchedExample],
    counts: Iterable[int],
    device: torch.device,
) -> dict[int, list[BatchedViews | None]]:
    """Per count k, the k-view context the evaluation sample of each of ``scenes`` carries (None where it
    carries none; every entry None when the shards were converted for fewer views)."""
    keys = [s.scene[0] for s in scenes]
    contexts = {}
    for k in sorted(set(counts) - {s.context.num_views for s in scenes}):
        try:
            stream = evaluation_stream(loaded, data_root, image_size, k)
        except UserError:
            contexts[k] = [None] * len(keys)
            continue
        contexts[k] = contexts_of(each_scene(stream, device), keys)
    return contexts


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``aesplat bench`` (see ``--help``)."""
    from .checkpoint import load_checkpoint
    from .render import get_backend

    args = build_parser().parse_args(argv)
    apply_thread_policy(num_workers=0, override=args.threads)  # the scenes are read in this process
    device = resolve_device(args.device)
    loaded = load_checkpoint(args.ckpt, device)  # a UserError is one line (aesplat.cli reports it)
    scenes = evaluation_scenes(loaded, args.data_root, args.image_size, args.scenes, device,
                               args.data_context_views)  # fmt: skip
    if not scenes:
        raise SystemExit("aesplat bench: the test split holds no scenes")
    contexts = {}
    if args.knobs is None or "context_views" in args.knobs:
        contexts = context_views_of(loaded, args.data_root, args.image_size, scenes, args.context_views, device)
    native = scenes[0].target.images.shape[-1]
    # The scenes' tensors are float32 on `device`: "auto" picks what a render of them would use.
    auto = get_backend("auto", device)[0]
    backends = args.backends or (["gsplat", "torch"] if auto == "gsplat" else ["torch"])
    baseline, points = default_sweep(
        loaded.sh_degree, native, patch=loaded.patch_size, context_views=args.context_views,
        backends=backends, input_scales=args.input_scales,
        render_scales=args.render_scales, keep_fractions=args.keep_fractions, min_opacities=args.min_opacities,
        precisions=args.precisions, tile_sizes=[int(t) for t in args.tile_sizes], compiled=args.compile,
        knobs=args.knobs,
    )  # fmt: skip
    render_kwargs = loaded.render_options(device)
    render_kwargs.pop("compile", None)  # compiling is a knob of its own here
    bench = Bench(loaded.model, scenes, device, repeats=args.repeats, warmup=args.warmup,
                  render_kwargs=render_kwargs, progress=not args.no_progress,
                  cameras=loaded.cameras, contexts=contexts)  # fmt: skip
    rows = bench.run(points, baseline, warmup_runs=args.process_warmup)
    if args.out is not None:
        out = Path(args.out)
    elif loaded.data is not None:
        out = loaded.path.parent.parent / "bench"
    else:
        out = Path("outputs/bench")
    meta = {
        **machine_meta(device), "ckpt": str(loaded.path), "scenes": len(scenes), "native_size": native,
        "context_views": scenes[0].context.num_views,
        "view_aggregation": loaded.net.get("view_aggregation", "concat"),
        "repeats": args.repeats, "warmup": args.warmup, "process_warmup": args.process_warmup,
        "sh_degree": loaded.sh_degree,
        "model_size": loaded.net.get("size"), "appearance": loaded.net.get("appearance"),
        "cameras": loaded.cameras,
    }  # fmt: skip
    paths = write_report(rows, out, meta)
    print(paths["BENCH.md"].read_text())
    print(f"aesplat bench: wrote {', '.join(str(p) for p in paths.values())}")
    return 0
